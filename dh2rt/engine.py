"""One module's DH2 main loop (the paper's Fig. 3), sans-IO.

An :class:`Engine` holds one module's state: ConnectorStatus, its topological type T,
sensors S, variables V, hormones present H, receptor status R, LocalTimer (mod ClockCycle)
and the two actuator targets DOF1/DOF2. It never touches a link or a servo: a caller (the
in-process robot, the module runtime on a real transport) hands :meth:`Engine.step` what
arrived and sends what it returns.

One step::

    receive   for each arrival (a hormone, the connector it arrived at, the connector it was
              sent through): ConnectorStatus[at] = remote; the hormone, its path extended by
              the hop (remote, at), is present in H for this step
    receptors for each active receptor worth matching (see the compiler's index), in program
              order: if its pattern matches, run its actions (new hormones go to the Buffer);
              it stays active only if its actions include keep_alive()
    forward   each hormone no receptor bound goes out through every linked connector except
              the one it came in on; a routed hormone (a reply) goes on along its route,
              bound or not; one whose path has reached max_hops is dropped
    send      the Buffer is returned; the caller reports failed sends through
              send_failed(), which sets ConnectorStatus to 0
    timer     LocalTimer = (LocalTimer + 1) mod ClockCycle

This is Fig. 3's loop with the bookkeeping's receive moved to the top of the step: the
Mailbox read in one step holds exactly what neighbours sent in the previous one, so in a
lockstep run every hormone crosses one link per cycle whatever order modules are stepped in.

Presence sensing (:meth:`link_up`, :meth:`link_down`) lets whatever plays the physical layer
report a docked or lost neighbour directly, as CONRO's infrared connectors sense each other;
liveness over real links is built on it by the module runtime.

Three layers make up a module's main loop; each names the others: :meth:`dh2rt.engine.Engine.step`
is one cycle of the paper's Fig. 3 over the module's state (no I/O); :class:`dh2rt.runtime.ModuleRuntime`
runs those cycles on a real transport at the module's period, with liveness, sensors and servos;
``firmware/main_loop.py`` is the program a module boots (``dh2rt module --config module.toml``):
config, links, flash, control channel, then the runtime's cycles until power-off or a signal.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from dh2rt.errors import DH2Error, MissingNatives, UnknownName
from dh2rt.hormone import Arrival, Emission, Hormone
from dh2rt.profile import TopoType
from dh2rt.program import ACTIVE, PASSIVE, CompiledProgram, Entry

#: A native action: called with the engine and the evaluated arguments.
Native = Callable[..., None]

# Shared empty sentinels: an idle module reads these instead of its own empty containers.
_NO_HORMONES: dict[str, list[Entry]] = {}
_NO_PERIODICS: dict[str, _Periodic] = {}
_NO_NATIVES: Mapping[str, Native] = {}
_NO_FAULTS: list[str] = []  # never appended to: see _fault
_NO_ENTRIES: list[Entry] = []  # never appended to: steps make their own
_NO_EMISSIONS: list[Emission] = []  # never appended to: steps make their own
MAX_FAULTS_KEPT = 16
#: What a receptor's actions may raise by design, and the engine survives as a fault: a
#: dh2rt error (a hormone argument out of range, a failing servo in a native action) or a
#: division by zero in a DH2 expression. Anything else is a bug in a native or in dh2rt and
#: surfaces to the caller.
ACTION_FAULTS = (DH2Error, ZeroDivisionError)


@dataclass(slots=True)
class _Periodic:
    """A periodic hormone: sent through ``send`` every ``period`` cycles."""

    period: int
    countdown: int
    send: Callable[[Engine], None]


class Engine:
    """The state and main loop of one module. See the module docs for one step."""

    # Hot fields first: __slots__ order is memory order, so the fields every step reads
    # share cache lines (it matters with thousands of modules in one process).
    __slots__ = (
        "clock",
        "dof",
        "dof_changed",
        "effects",
        "faults",
        "index",
        "matched",
        "n_dropped_hops",
        "n_faults",
        "n_forwarded",
        "n_received",
        "n_send_failed",
        "n_sent",
        "natives",
        "out",
        "periodics",
        "present",
        "profile",
        "program",
        "rstatus",
        "sensors",
        "status",
        "timer",
        "type_index",
        "type_table",
        "vars",
    )

    def __init__(
        self,
        program: CompiledProgram,
        *,
        timer_phase: int = 0,
        natives: Mapping[str, Native] | None = None,
    ) -> None:
        self.program = program
        self.index = program.index
        self.profile = program.profile
        self.clock = program.clock_cycle
        self.type_table = program.profile.type_of_status
        self.status: list[int] = [0] * program.profile.connector_count
        self.type_index: int = self.type_table[tuple(self.status)]
        self.timer = timer_phase % self.clock
        self.vars: list[int] = list(program.var_initial)
        self.sensors: list[int] = [0] * len(program.sensor_names)
        self.rstatus: list[int] = [r.initial for r in program.receptors]
        self.dof: list[float] = [0.0, 0.0]
        self.dof_changed = False
        self.present: dict[str, list[Entry]] = _NO_HORMONES
        self.periodics: dict[str, _Periodic] = _NO_PERIODICS
        self.out: list[Emission] = _NO_EMISSIONS
        self.matched: list[Entry] = _NO_ENTRIES
        self.effects: Sequence[tuple[str, tuple[Any, ...]]] = ()
        self.faults: list[str] = _NO_FAULTS  # a list of its own from the first fault
        self.n_received = 0
        self.n_sent = 0
        self.n_forwarded = 0
        self.n_dropped_hops = 0
        self.n_send_failed = 0
        self.n_faults = 0
        natives = natives or _NO_NATIVES  # shared, not copied: thousands of engines share one
        missing = sorted(set(program.natives) - set(natives))
        if missing:
            lacking = ", ".join(missing)
            raise MissingNatives(f"program {program.name} needs native action(s) the runtime lacks: {lacking}")
        self.natives: Mapping[str, Native] = natives

    # ------------------------------------------------------------ what callers read

    @property
    def topo_type(self) -> TopoType:
        return self.profile.types[self.type_index]

    @property
    def counters(self) -> dict[str, int]:
        """Hormones received, sent, forwarded, dropped at max_hops, failed sends, faults."""
        return {
            "received": self.n_received,
            "sent": self.n_sent,
            "forwarded": self.n_forwarded,
            "dropped_hops": self.n_dropped_hops,
            "send_failed": self.n_send_failed,
            "faults": self.n_faults,
        }

    def variables(self) -> dict[str, int]:
        """V by name: the program's variables as they stand (empty when it declares none)."""
        return dict(zip(self.program.var_names, self.vars, strict=True))

    def named_sensors(self) -> dict[str, int]:
        """S by name, as the last cycle read them (empty when the program declares none)."""
        return dict(zip(self.program.sensor_names, self.sensors, strict=True))

    def var(self, name: str) -> int:
        return self.vars[self._slot(self.program.var_names, name, "variable")]

    def set_var(self, name: str, value: int) -> None:
        self.vars[self._slot(self.program.var_names, name, "variable")] = value

    def set_sensor(self, name: str, value: int) -> None:
        self.sensors[self._slot(self.program.sensor_names, name, "sensor")] = value

    def receptor_status(self, name: str) -> int:
        names = tuple(r.name for r in self.program.receptors)
        return self.rstatus[self._slot(names, name, "receptor")]

    def _slot(self, names: tuple[str, ...], name: str, what: str) -> int:
        try:
            return names.index(name)
        except ValueError:
            known = ", ".join(names) or "none"
            raise UnknownName(f"program {self.program.name} has no {what} {name!r} (it has: {known})") from None

    def effect(self, kind: str, *args: Any) -> None:
        """Ask the physical layer for something (used by native actions); read via ``effects``."""
        if not self.effects:
            self.effects = []
        self.effects.append((kind, args))  # type: ignore[attr-defined]

    # ------------------------------------------------------------ presence sensing

    def link_up(self, connector: int, remote: int) -> None:
        """The physical layer senses a neighbour's ``remote`` connector at ``connector``."""
        self._set_status(connector, remote)

    def link_down(self, connector: int) -> None:
        """The physical layer senses nothing at ``connector`` any more."""
        self._set_status(connector, 0)

    def send_failed(self, connector: int) -> None:
        """A send through ``connector`` failed: ConnectorStatus[connector] = 0 (Fig. 3)."""
        self.n_send_failed += 1
        self._set_status(connector, 0)

    def _set_status(self, connector: int, remote: int) -> None:
        if self.status[connector - 1] != remote:
            self.status[connector - 1] = remote
            self.type_index = self.type_table[tuple(self.status)]

    def start_periodic(self, name: str, period: int, send: Callable[[Engine], None]) -> None:
        """Emit through ``send`` every ``period`` cycles from now (the paper's periodical_hormone)."""
        if self.periodics is _NO_PERIODICS:
            self.periodics = {}
        # Actions run before this step's periodic countdown, which takes one off at once:
        # start one higher so that the next send comes ``period`` cycles after the first.
        self.periodics[name] = _Periodic(period, period + 1, send)

    def stop_periodic(self, name: str) -> None:
        """The paper's stop_hormone."""
        self.periodics.pop(name, None)
        if not self.periodics:
            self.periodics = _NO_PERIODICS

    def quiet_cycles(self) -> int | None:
        """How many coming cycles are sure to do nothing but advance LocalTimer if no mail
        arrives and no link changes: 0 when the next one might act; None for "forever"."""
        if self.periodics:
            return 0
        return self.index.quiet[self.type_index][self.timer]

    def skip(self, cycles: int) -> None:
        """Advance LocalTimer over ``cycles`` quiet cycles (see :meth:`quiet_cycles`):
        exactly what stepping through them with no arrivals would do."""
        self.timer = (self.timer + cycles) % self.clock
        self.present = _NO_HORMONES

    def matching_receptors(self) -> list[int]:
        """Receptors whose patterns match the present state, without running any action.

        The same index and closures as :meth:`step` (for debugging tools and benchmarks).
        """
        program = self.program
        index = self.index
        t = self.type_index
        present = self.present
        cands = index.candidates(t, self.timer, present) if present else index.base[t][self.timer]
        out: list[int] = []
        if not cands:
            return out
        for i in cands:
            if self.rstatus[i] == ACTIVE:
                self.matched = []
                if program.receptors[i].match(self, {}):
                    out.append(i)
        return out

    # ------------------------------------------------------------ the loop

    def step(self, arrivals: Sequence[Arrival] = ()) -> Sequence[Emission]:
        """Run one cycle on what arrived; return the Buffer to send (see the module docs)."""
        index = self.index
        if self.effects:
            self.effects = ()
        if not arrivals and not self.periodics:
            # Nothing arrived and nothing periodic: unless a receptor is filed under this
            # type and LocalTimer, the cycle only advances the timer (most cycles, most modules).
            cands = index.base[self.type_index][self.timer]
            if not cands:
                self.present = _NO_HORMONES
                timer = self.timer + 1
                self.timer = 0 if timer >= self.clock else timer
                return ()
        out: list[Emission] = []
        self.out = out
        # receive: ConnectorStatus and H
        if arrivals:
            present: dict[str, list[Entry]] = {}
            status = self.status
            changed = False
            for at, remote, h in arrivals:
                if not at:  # injected: sensed or created here, not received over a link
                    entry: Entry = (h.name, h.args, h.path, h.route, 0)
                else:
                    if status[at - 1] != remote:
                        status[at - 1] = remote
                        changed = True
                    entry = (h.name, h.args, ((remote, at), *h.path), h.route, at)
                bucket = present.get(h.name)
                if bucket is None:
                    present[h.name] = [entry]
                else:
                    bucket.append(entry)
            if changed:
                self.type_index = self.type_table[tuple(status)]
            self.n_received += len(arrivals)
            self.present = present
        else:
            present = _NO_HORMONES
            self.present = present
        t = self.type_index
        # receptors: only those the index says can match this type, timer and H
        cands = index.candidates(t, self.timer, present) if present else index.base[t][self.timer]
        bound: set[int] = set()
        if cands:
            receptors = self.program.receptors
            rstatus = self.rstatus
            for i in cands:
                if rstatus[i] != ACTIVE:
                    continue
                r = receptors[i]
                matched: list[Entry] = []
                self.matched = matched
                b: dict[str, Any] = {}
                if not r.match(self, b):
                    continue
                for entry in matched:
                    bound.add(id(entry))
                try:
                    r.act(self, b)
                except ACTION_FAULTS as exc:  # what an action can raise by design: keep the module alive
                    self._fault(f"receptor {r.name}", str(exc))
                if not r.keep_alive and rstatus[i] == ACTIVE:
                    rstatus[i] = PASSIVE
        # forward what no receptor bound; routed hormones go on along their route
        if present:
            self._forward(present, bound, out)
        # periodic hormones
        if self.periodics:
            for name, p in list(self.periodics.items()):  # a periodic may stop another
                p.countdown -= 1
                if p.countdown <= 0:
                    p.countdown = p.period
                    try:
                        p.send(self)
                    except ACTION_FAULTS as exc:
                        self._fault(f"periodic {name}", str(exc))
        self.n_sent += len(out)
        timer = self.timer + 1
        self.timer = 0 if timer >= self.clock else timer
        # Let go of this step's scratch now, while it is in cache: kept until the module's
        # next step, it would be a third of the module's memory, freed when long gone cold.
        self.present = _NO_HORMONES
        self.matched = _NO_ENTRIES
        self.out = _NO_EMISSIONS
        return out

    def _forward(self, present: dict[str, list[Entry]], bound: set[int], out: list[Emission]) -> None:
        max_hops = self.program.max_hops
        for entries in present.values():
            for entry in entries:
                name, args, path, route, at = entry
                if route is not None:
                    if route:  # not yet at its destination: on along the route, bound or not
                        if len(path) >= max_hops:
                            self.n_dropped_hops += 1
                            continue
                        out.append(Emission(route[0], Hormone(name, args, path, route[1:])))
                        self.n_forwarded += 1
                    continue
                if id(entry) in bound:
                    continue
                if len(path) >= max_hops:
                    self.n_dropped_hops += 1
                    continue
                h = None
                for i, s in enumerate(self.status):
                    c = i + 1
                    if s and c != at:
                        if h is None:
                            h = Hormone(name, args, path)
                        out.append(Emission(c, h))
                        self.n_forwarded += 1

    def _fault(self, source: str, message: str) -> None:
        """An action failed as actions may (see ACTION_FAULTS): count it, keep the message,
        and tell the host through an effect ``("fault", (source, message))`` so that it can
        say when and where (the host knows the cycle and the module; the engine does not)."""
        self.n_faults += 1
        text = f"{source}: {message}"
        if self.faults is _NO_FAULTS:
            self.faults = []
        self.faults.append(text)
        del self.faults[:-MAX_FAULTS_KEPT]
        self.effect("fault", source, message)
