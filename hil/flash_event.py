"""The launcher's ``--event CYCLE:flash:M:IMAGE``: a programming cable into module M's free
connector at a world cycle, the flasher on it (:class:`firmware.flash.cable.FlashCable`, in a
thread of the launcher), its progress, and the rollout report at the end.

On serial links the cable is one more emulated link into M's first free connector (front,
back, left, right); on a bus it is a node of its own whose connector-local channel touches
that connector, so that the two negotiate a link as modules do. It is pulled out when the
flasher is done.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from dh2rt.errors import EventError, SignedImageError, TopologyError
from dh2rt.flash.flasher import Progress
from dh2rt.flash.pacing import link_pacing
from dh2rt.flash.reports import RANK, ModuleReport, describe_path
from dh2rt.signed_image import parse as parse_image
from dh2rt.topology import Topology
from dh2rt.transport.base import PortEnd, Transport
from dh2rt.transport.registry import open_transport
from dh2rt.transport.serial_link import SerialTransport
from drivers.connector_channel import ConnectorChannels
from firmware.flash.cable import BusCable, FlashCable, FlashResult, hello_codec
from hil.world import World

#: Seconds a rollout may take before the flasher gives up.
FLASH_TIMEOUT = 120.0

#: Seconds a flasher told to stop has to leave its tick (one tick is a cycle period).
STOP_GRACE = 10.0


#: Outcomes of a module that runs the image.
_RUNS_IT = frozenset({"committed", "current", "confirmed"})


@dataclass(frozen=True, slots=True)
class ModuleRow:
    """One module of the robot in a rollout report: its world name, its path from the cable
    (None: never heard of), the outcome, the version and program SHA-256 it runs, and the
    verdict and reason of a refusal."""

    module: str
    path: str | None
    outcome: str
    version: object
    sha256: object
    verdict: str
    reason: str

    def describe(self) -> str:
        why = f" ({self.verdict}: {self.reason})" if self.verdict or self.reason else ""
        sha = f", sha256 {str(self.sha256)[:16]}" if self.sha256 else ""
        where = self.path or "(no path)"
        return f"{where}: {self.outcome}, runs version {self.version}{sha}{why}  [{self.module}]"

    def to_json(self) -> dict[str, object]:
        return {"path": self.path, "module": self.module, "outcome": self.outcome, "version": self.version,
                "sha256": self.sha256, "verdict": self.verdict, "reason": self.reason}  # fmt: skip


@dataclass(slots=True)
class FlashEvent:
    """``CYCLE:flash:M:IMAGE``: the image's bytes, flashed through module M's ``connector``."""

    cycle: int
    module: int
    connector: int
    image: bytes
    text: str
    result: FlashResult | None = None
    _thread: threading.Thread | None = field(default=None, repr=False)
    # (the serial cable's link id, or the bus cable's connector; its transport)
    _cable: tuple[int, Transport] | None = field(default=None, repr=False)
    _bus: BusCable | None = field(default=None, repr=False)
    _flash: FlashCable | None = field(default=None, repr=False)
    #: set when the run ends before the flasher is done: it stops at its next tick
    _stop: threading.Event = field(default_factory=threading.Event, repr=False)
    #: the run ended while the flasher was still at work (not its own timeout)
    cut_short: bool = False


def is_flash_event(text: str) -> bool:
    parts = text.split(":", 2)
    return len(parts) == 3 and parts[1] == "flash"


def parse_flash_event(text: str, topology: Topology) -> FlashEvent:
    """Parse ``CYCLE:flash:M:IMAGE``; EventError naming the event and what is wrong."""
    cycle_text, _, rest = text.split(":", 2)
    ref, sep, path = rest.partition(":")
    if not cycle_text.strip().isdigit() or not sep or not path:
        raise EventError(f"event {text!r}: expected CYCLE:flash:MODULE:IMAGE")
    try:
        module = topology.module_index(ref.strip())
    except TopologyError as exc:
        raise EventError(f"event {text!r}: {exc}") from None
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise EventError(f"event {text!r}: cannot read the image {path}: {exc.strerror or exc}") from None
    try:
        parse_image(data)
    except SignedImageError as exc:
        raise EventError(f"event {text!r}: {path}: {exc}") from None
    docked = {(lk.a, lk.a_conn) for lk in topology.links} | {(lk.b, lk.b_conn) for lk in topology.links}
    free = [c for c in range(1, topology.profile.connector_count + 1) if (module, c) not in docked]
    if not free:
        raise EventError(f"event {text!r}: module {topology.names[module]} has no free connector for the cable")
    return FlashEvent(int(cycle_text), module, free[0], data, text)


class FlashEvents:
    """Carries out the flash events of a run as the world reaches their cycles."""

    def __init__(self, events: list[FlashEvent], world: World, progress: IO[str]) -> None:
        self.events = sorted(events, key=lambda e: e.cycle)
        self.world = world
        self.progress = progress
        self._lock = threading.Lock()

    @property
    def busy(self) -> bool:
        """A flasher still runs (the world must go on until it is done)."""
        return any(e._thread is not None and e.result is None for e in self.events)

    def step(self) -> None:
        """Plug in the cables whose cycle has come; pull out those whose flasher is done."""
        world = self.world
        for ev in self.events:
            if ev._thread is None and world.cycle >= ev.cycle and not self.busy:
                self._start(ev)
            elif ev._thread is not None and ev.result is None and not ev._thread.is_alive():
                self._finish(ev)

    def _start(self, ev: FlashEvent) -> None:
        world = self.world
        cable = self._serial_cable(ev) if world.contacts is None else self._bus_cable(ev)
        ev._flash = cable
        world.note(f"{ev.text}: cable into {world.where(ev.module, ev.connector)}")

        def show(p: Progress) -> None:
            with self._lock:
                self.progress.write(
                    f"flash: {p.phase.value}: {p.modules} module(s) heard of, {p.staged} staged, "
                    f"{p.committed} committed, {p.failed} failed, {p.bytes_acked} bytes acknowledged, "
                    f"{p.rate:.0f} bytes/s\n"
                )
                self.progress.flush()

        ev._thread = threading.Thread(
            target=lambda: cable.run(timeout=FLASH_TIMEOUT, stop=ev._stop, progress=show),
            name="dh2rt-flasher", daemon=True,
        )  # fmt: skip
        ev._thread.start()

    def _serial_cable(self, ev: FlashEvent) -> FlashCable:
        """A cable is one more emulated serial link, into M's free connector."""
        world = self.world
        link_id, path = world.plug_cable(ev.module, ev.connector)
        transport = SerialTransport(hello_codec())
        transport.attach(1, PortEnd(path))
        pacing, segment, _ = link_pacing("serial", world.cycle_period, 115200, 0)
        ev._cable = (link_id, transport)
        return FlashCable(ev.image, transport, period=world.cycle_period, pacing=pacing, segment_size=segment,
                          expect=world.topology.size, connector_name=world.profile.connector_name)  # fmt: skip

    def _bus_cable(self, ev: FlashEvent) -> FlashCable:
        """On a bus the cable is a node of its own: its connector-local channel touches M's
        free connector, the link is negotiated as modules negotiate theirs, and the rollout
        crosses the bus on it (paced as a module's share of the bus)."""
        world = self.world
        mate, path = world.touch_cable(ev.module, ev.connector)
        transport = open_transport(world.transport_spec, hello_codec(), **world.bus_options)
        try:
            bus_cable = BusCable(ConnectorChannels.open_emulated({mate: path}), transport, mate,
                                 now=time.monotonic(), log=lambda line: world.note(f"{ev.text}: {line}"))  # fmt: skip
        except BaseException:
            transport.close()
            raise
        bitrate = int(world.bus_options.get("bitrate", 1_000_000))
        pacing, segment, _ = link_pacing("can", world.cycle_period, 0, bitrate)
        ev._cable = (mate, transport)
        ev._bus = bus_cable
        return FlashCable(ev.image, transport, period=world.cycle_period, pacing=pacing, segment_size=segment,
                          connector=mate, on_step=bus_cable.step, expect=world.topology.size,
                          connector_name=world.profile.connector_name)  # fmt: skip

    def _finish(self, ev: FlashEvent) -> None:
        assert ev._flash is not None and ev._cable is not None
        ev.result = ev._flash.result()
        ev.cut_short = ev._stop.is_set() and ev.result.timed_out
        link_or_mate, transport = ev._cable
        # the flasher's frames are the run's too (on a bus, with the spans it held its link end in)
        self.world.count_cable(transport.counters, transport.held_ends())
        if ev._bus is not None:
            with ev._flash.lock:
                ev._bus.close()  # the link released on the bus before the contact breaks
            transport.close()
            self.world.pull_cable(ev.module, ev.connector, link_or_mate)
        else:
            transport.close()
            self.world.unplug_cable(ev.module, ev.connector, link_or_mate)
        heard = len(ev.result.modules)
        self.world.note(f"{ev.text}: the flasher is done: {heard} of {self.world.topology.size} module(s) heard of, "
                        f"{'every one committed' if ev.result.succeeded else 'not every one committed'}")  # fmt: skip

    def close(self) -> None:
        """The run ends: flashers still running are stopped and their cables pulled out."""
        for ev in self.events:
            ev._stop.set()
        for ev in self.events:
            if ev._thread is not None and ev.result is None:
                # stopped at its next tick: its transport is closed only once it is out of it
                # (closed under a running flasher, its thread once died mid-send)
                ev._thread.join(timeout=STOP_GRACE)
                if ev._flash is not None and ev._cable is not None and not ev._thread.is_alive():
                    self._finish(ev)

    def report(self) -> list[dict[str, object]]:
        """Every flash event's rollout report (for --json): a row for every module of the robot."""
        out: list[dict[str, object]] = []
        for ev in self.events:
            r = ev.result
            out.append(
                {
                    "event": ev.text,
                    "succeeded": self.event_succeeded(ev),
                    "failure": None if r is None else self.failure(ev),
                    "modules": [] if r is None else [row.to_json() for row in self.rows(ev)],
                }
            )
        return out

    def rows(self, ev: FlashEvent) -> list[ModuleRow]:
        """One row per module of the robot, in the world's order: its path from the cable and
        the flasher's outcome for it (``unreachable``: the flasher never heard of it), and the
        version and program SHA-256 it runs by its own last status."""
        heard: dict[int, ModuleReport] = {}
        for m in [] if ev.result is None else ev.result.modules:
            index = self.module_index(ev, m.path)
            old = heard.get(index) if index is not None else None
            if index is not None and (old is None or RANK[m.outcome] > RANK[old.outcome]):
                heard[index] = m
        name = self.world.profile.connector_name
        out: list[ModuleRow] = []
        for index, view in enumerate(self.world.views):
            program = view.program
            got = heard.get(index)
            version = program.get("version", got.version if got is not None else None)
            if got is None:
                out.append(ModuleRow(view.name, None, "unreachable", version, program.get("sha256"), "",
                                     "the flasher never heard of it"))  # fmt: skip
            else:
                outcome = got.outcome.name.lower()
                out.append(ModuleRow(view.name, describe_path(got.path, name), outcome, version, program.get("sha256"),
                                     got.verdict, got.reason))  # fmt: skip
        return out

    def event_succeeded(self, ev: FlashEvent) -> bool:
        """The flasher succeeded and every module of the robot runs the image."""
        r = ev.result
        if r is None or not r.succeeded:
            return False
        return all(row.outcome in _RUNS_IT for row in self.rows(ev))

    def failure(self, ev: FlashEvent) -> str | None:
        """Why not every module of the robot committed (None: every one did)."""
        r = ev.result
        if r is None:
            return "never started (the run ended first)"
        if self.event_succeeded(ev):
            return None
        if ev.cut_short:
            return f"the run ended before the flasher was done: it had heard of {len(r.modules)} module(s)"
        if r.failure is not None:
            return r.failure
        short = [row for row in self.rows(ev) if row.outcome not in _RUNS_IT]
        if not short:  # the robot runs it; the flasher's own reports said otherwise: name those
            told = [m.describe() for m in r.modules if not m.committed]
            heard = f"it heard from {len(r.modules)} of {self.world.topology.size} modules"
            return f"every module runs it, but the flasher did not see every one commit ({heard})" + (
                ": " + "; ".join(told[:3]) if told else ""
            )
        # named as every report names a module: by its path (the world's name beside it)
        named = ", ".join(f"{row.path or '(no path)'} [{row.module}] {row.outcome}" for row in short[:3])
        return f"not committed: {named}" + (f" and {len(short) - 3} more" if len(short) > 3 else "")

    def module_index(self, ev: FlashEvent, path: tuple[tuple[int, int], ...]) -> int | None:
        """The world's index of the module a path names (the world knows; the robot does not)."""
        here: tuple[int, int] | None = None
        for i, (sent, received) in enumerate(path):
            if i == 0:
                here = (ev.module, received)
                continue
            assert here is not None
            peer = self.world.link_map.peer_of((here[0], sent))
            if peer is None or peer[1] != received:
                return None
            here = peer
        return None if here is None else here[0]

    def module_at(self, ev: FlashEvent, path: tuple[tuple[int, int], ...]) -> str | None:
        """The world's name of the module a path names."""
        index = self.module_index(ev, path)
        return None if index is None else self.world.topology.names[index]

    def lines(self) -> list[str]:
        """The rollout report, one line per module of the robot, for the summary."""
        out: list[str] = []
        for ev in self.events:
            if ev.result is None:
                out.append(f"{ev.text}: never started (the run ended first)")
                continue
            ok = self.event_succeeded(ev)
            head = "every module committed" if ok else f"NOT every module committed ({self.failure(ev)})"
            out.append(f"{ev.text}: {head}")
            out.extend(f"  {row.describe()}" for row in self.rows(ev))
        return out

    @property
    def succeeded(self) -> bool:
        return all(self.event_succeeded(e) for e in self.events)
