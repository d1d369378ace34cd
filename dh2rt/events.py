"""Timed events for a run: live surgery, docking, injected hormones, killed modules, sensors.

Text form (``--event``), with modules by name or index::

    CYCLE:cut:M.CONN                 break the link at module M's connector
    CYCLE:dock:M.CONN-M2.CONN2       dock two connectors
    CYCLE:inject:M:HORMONE           place HORMONE (e.g. LTS or X(A)) in M's mailbox
    CYCLE:kill:M                     the module stops (its neighbours lose the link)
    CYCLE:restart:M                  it boots again with a fresh state
    CYCLE:sense:M:NAME=VALUE         sensor S.NAME of M reads VALUE from then on (e.g. roll=90)

A ``sense`` event names a sensor of the topology's profile and an integer within its range
(``dh2rt.profile.SensorSpec``); the value holds until another ``sense`` event for the same
sensor, even where the physics stand-in fills that sensor (its reading of that module's
sensor is overridden) and across a restart of the module.

:func:`check_events` replays a run's events against its topology before the run starts, so
that a cut of nothing, a dock of two male connectors or an event after the last cycle is
refused up front (naming the event) rather than ending the run at cycle 300 of 400.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass

from dh2rt.docking import check_cut, check_dock
from dh2rt.errors import DH2Error, EventError, ProgramError, TopologyError
from dh2rt.hormone import Hormone, Vocabulary
from dh2rt.lang import ast
from dh2rt.lang.parser import Parser
from dh2rt.profile import Profile, undeclared_sensor
from dh2rt.topology import Topology

KINDS = ("cut", "dock", "inject", "kill", "restart", "sense")


@dataclass(frozen=True, slots=True)
class Event:
    cycle: int
    kind: str
    module: int
    connector: int = 0
    other: int = 0
    other_connector: int = 0
    hormone: Hormone | None = None
    text: str = ""
    #: ``sense``: the sensor's name and the value it reads
    sensor: str = ""
    value: int = 0


def parse_event(text: str, topology: Topology, vocabulary: Vocabulary) -> Event:
    """Parse one event string; errors name the event and the part that is wrong."""
    parts = text.split(":", 2)
    if len(parts) < 3 or not parts[0].strip().isdigit():
        raise EventError(f"event {text!r}: expected CYCLE:KIND:ARGS with KIND one of {', '.join(KINDS)}")
    cycle, kind, rest = int(parts[0]), parts[1], parts[2]
    if kind not in KINDS:
        raise EventError(f"event {text!r}: unknown kind {kind!r} (one of {', '.join(KINDS)})")

    def module(ref: str) -> int:
        try:
            return topology.module_index(ref.strip())
        except TopologyError as exc:
            raise EventError(f"event {text!r}: {exc}") from None

    def endpoint(ref: str) -> tuple[int, int]:
        m, dot, c = ref.partition(".")
        if not dot:
            raise EventError(f"event {text!r}: expected MODULE.CONNECTOR, got {ref!r}")
        index = module(m)
        try:
            return index, topology.profile.connector_index(c.strip())
        except TopologyError as exc:
            raise EventError(f"event {text!r}: {exc}") from None

    if kind == "cut":
        m, c = endpoint(rest)
        return Event(cycle, kind, m, c, text=text)
    if kind == "dock":
        a, sep, b = rest.partition("-")
        if not sep:
            raise EventError(f"event {text!r}: expected M.CONN-M2.CONN2")
        (m, c), (m2, c2) = endpoint(a), endpoint(b)
        return Event(cycle, kind, m, c, m2, c2, text=text)
    if kind == "inject":
        ref, sep, htext = rest.partition(":")
        if not sep:
            raise EventError(f"event {text!r}: expected CYCLE:inject:M:HORMONE")
        return Event(cycle, kind, module(ref), hormone=parse_hormone(htext, vocabulary, f"event {text!r}"), text=text)
    if kind == "sense":
        ref, sep, assignment = rest.partition(":")
        if not sep:
            raise EventError(f"event {text!r}: expected CYCLE:sense:M:NAME=VALUE")
        name, value = parse_sensing(assignment, topology.profile, f"event {text!r}")
        return Event(cycle, kind, module(ref), sensor=name, value=value, text=text)
    return Event(cycle, kind, module(rest), text=text)


def parse_sensing(text: str, profile: Profile, where: str = "sensor") -> tuple[str, int]:
    """``NAME=VALUE``: a sensor of ``profile`` and an integer it can read; EventError naming
    ``where`` and what is wrong otherwise."""
    name, sep, raw = text.partition("=")
    name, raw = name.strip(), raw.strip()
    if not sep or not name:
        raise EventError(f"{where}: expected NAME=VALUE, e.g. roll=90")
    try:
        value = int(raw)
    except ValueError:
        raise EventError(f"{where}: sensor value {raw!r} is not a whole number") from None
    try:
        profile.sensor(name).check(value)
    except TopologyError as exc:
        raise EventError(f"{where}: {exc}") from None
    return name, value


def check_events(
    events: Sequence[Event], topology: Topology, cycles: int, *, sensors: Collection[str] | None = None
) -> None:
    """Replay ``events`` in the order a run applies them against ``topology``'s links and
    raise EventError naming the first event that cannot happen: one at or after cycle
    ``cycles`` (the run ends first), a cut of a connector with nothing docked, a dock the
    profile or the links then do not allow, an injection into or a sensing of a stopped
    module, and, given the program's declared ``sensors``, a sensing of one it does not read.

    Links that native actions change during the run (reach_and_dock) are not known here;
    an event those make impossible is reported when it is applied."""
    profile = topology.profile
    peer: dict[tuple[int, int], tuple[int, int]] = {}
    for link in topology.links:
        peer[(link.a, link.a_conn)] = (link.b, link.b_conn)
        peer[(link.b, link.b_conn)] = (link.a, link.a_conn)
    stopped: set[int] = set()

    def where(m: int, c: int) -> str:
        return f"{topology.names[m]}.{profile.connector_name(c)}"

    for ev in sorted(events, key=lambda e: e.cycle):  # a stable sort: the run's order
        label = f"event {ev.text or ev.kind!r}"
        if ev.cycle >= cycles:
            raise EventError(f"{label} at cycle {ev.cycle} never happens: the run's last cycle is {cycles - 1}")
        try:
            if ev.kind == "cut":
                other = check_cut(peer.get((ev.module, ev.connector)), where(ev.module, ev.connector))
                del peer[(ev.module, ev.connector)], peer[other]
            elif ev.kind == "dock":
                check_dock(profile, peer.__contains__, where, ev.module, ev.connector, ev.other, ev.other_connector)
                peer[(ev.module, ev.connector)] = (ev.other, ev.other_connector)
                peer[(ev.other, ev.other_connector)] = (ev.module, ev.connector)
            elif ev.kind == "kill":
                stopped.add(ev.module)
            elif ev.kind == "restart":
                stopped.discard(ev.module)
            elif ev.kind in ("inject", "sense") and ev.module in stopped:
                raise TopologyError(f"module {topology.names[ev.module]} is stopped then")
            elif ev.kind == "sense" and sensors is not None and ev.sensor not in sensors:
                raise TopologyError(undeclared_sensor(ev.sensor))
        except TopologyError as exc:
            raise EventError(f"{label}: {exc}") from None


def parse_hormone(text: str, vocabulary: Vocabulary, where: str = "hormone") -> Hormone:
    """``NAME`` or ``NAME(arg, ...)`` with atoms and integers, checked against the vocabulary."""
    try:
        parser = Parser(text, where)
        term = parser.hormone_term()
        if parser.tok.kind != "eof":
            raise parser.error(f"unexpected {parser.describe(parser.tok)} after the hormone")
    except ProgramError as exc:
        raise EventError(f"{where}: {exc.message}") from None
    args: list[int | str] = []
    for a in term.args:
        if isinstance(a, ast.Name):
            args.append(a.name)
        elif isinstance(a, ast.Num):
            args.append(a.value)
        elif isinstance(a, ast.Neg) and isinstance(a.operand, ast.Num):
            args.append(-a.operand.value)
        else:
            raise EventError(f"{where}: hormone arguments must be atoms or integers")
    h = Hormone(term.name, tuple(args))
    try:
        vocabulary.check(h)
    except DH2Error as exc:
        raise EventError(f"{where}: {exc}") from None
    return h
