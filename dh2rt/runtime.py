"""One module as its own process: the engine loop on a real transport, with liveness.

A :class:`ModuleRuntime` owns one :class:`~dh2rt.engine.Engine`, one
:class:`~dh2rt.transport.base.Transport` and optionally a driver (anything with
``set_targets(dof1_deg, dof2_deg)``). Its clock is its own (injectable); there is no global
clock and no lockstep: LocalTimer is the engine's, advanced once per cycle.

One cycle (:meth:`ModuleRuntime.step`)::

    sensors   the declared sensors are filled from the module's body (dh2rt.sensing: its
              sources, readings pushed to it, values ``sense`` events forced); a failing
              read is a counted, logged sensor fault, never a stop
    receive   frames polled since the last cycle go through the liveness machine
              (:mod:`dh2rt.liveness`): a Hello verifies the connector's peer (same program
              digest) or refuses it; frames through an unverified or refused connector are
              ignored and counted; any frame heard through a verified connector sets
              ConnectorStatus (engine.link_up)
    liveness  a linked connector that heard nothing for SILENCE_CYCLES consecutive cycles
              falls to 0 (engine.link_down) before the engine runs this cycle
    engine    engine.step(hormones received); each emission is sent; a refused send sets
              ConnectorStatus 0 (engine.send_failed)
    beacons   every attached connector that carried no hormone this cycle sends what the
              liveness machine says: a KeepAlive, or a Hello
    driver    set_targets when DOF1/DOF2 changed (or the targets an outside motion holds,
              :meth:`ModuleRuntime.hold`: the HIL world's docking motion); every
              HEALTH_EVERY cycles (at an offset of the module's own, its LocalTimer
              phase, so that modules sharing a servo bus or a processor do not all read
              their servos in the same cycle) the driver's
              health() (if it has one) is read, since servo faults surface on reads, not
              on unacknowledged writes; a fault is reported (status, log, counters) and,
              while it lasts, recover() (if the driver has one) is tried on each check,
              and only then: a servo that is gone costs a reply timeout per try (34 ms
              with an FTDI adapter's 16 ms latency timer, 102 ms on the HIL world's
              emulated servos), which once a cycle would stretch every cycle by it.
              A DriverError never stops the module: the engine keeps running.

Liveness bound: a neighbour that stops sending is noticed in the SILENCE_CYCLES-th
consecutive cycle without a frame from it, and the engine runs that cycle with the
connector at 0; in wall time, at most (SILENCE_CYCLES + 1) cycle periods plus the link's
latency after its last frame. The rules (Hello, refusal, re-verification) are the liveness
machine's; this module only does the I/O they call for.

Three layers make up a module's main loop; each names the others: :meth:`dh2rt.engine.Engine.step`
is one cycle of the paper's Fig. 3 over the module's state (no I/O); :class:`dh2rt.runtime.ModuleRuntime`
runs those cycles on a real transport at the module's period, with liveness, sensors and servos;
``firmware/main_loop.py`` is the program a module boots (``dh2rt module --config module.toml``):
config, links, flash, control channel, then the runtime's cycles until power-off or a signal.
"""

from __future__ import annotations

import bisect
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, cast

from dh2rt import docking
from dh2rt.engine import Engine, Native
from dh2rt.errors import DriverError
from dh2rt.hormone import Arrival, Emission, Hormone
from dh2rt.liveness import SILENCE_CYCLES, Beacon, Liveness, Verdict
from dh2rt.natives import STANDARD_NATIVES
from dh2rt.program import CompiledProgram
from dh2rt.records import cycle_json
from dh2rt.sensing import SensorFeed, Source
from dh2rt.transport.base import LinkEnd, Received, Transport
from dh2rt.wire.frame import FrameCodec, Hello, program_digest

__all__ = [
    "CYCLE_PERIOD_S",
    "MAX_CYCLE_PERIOD_S",
    "SILENCE_CYCLES",
    "Driver",
    "LinkObserver",
    "ModuleRuntime",
    "RuntimeCounters",
    "ms_to_s",
    "s_to_ms",
]
#: A module's cycle period (s): 50 Hz. The one default of the module runtime, the HIL world,
#: a module's configuration (firmware.config) and module.toml, and every command's
#: ``--cycle-ms`` (dh2rt.cmdline.add_cycle_argument). Code keeps periods in seconds (``_s``);
#: people type them in milliseconds (``--cycle-ms``, ``period_ms``): the two functions below
#: are the one conversion between them.
CYCLE_PERIOD_S = 0.02
#: The longest cycle period anything accepts (s): a module sleeps up to a period at a time,
#: and a minute is already far from any robot's rhythm (``--cycle-ms``, ``period_ms``).
MAX_CYCLE_PERIOD_S = 60.0


def ms_to_s(ms: float) -> float:
    """A period typed in milliseconds (``--cycle-ms``, module.toml's ``period_ms``) in seconds."""
    return ms / 1000.0


def s_to_ms(seconds: float) -> float:
    """A period in seconds as people type and read it: in milliseconds."""
    return seconds * 1000.0


#: A cycle that starts later than this fraction of a period after its deadline is late.
LATE_TOLERANCE = 0.5
#: Cycles between two reads of the driver's health (servo faults show on reads).
HEALTH_EVERY = 25
#: Cycles whose start lateness the status reports percentiles of.
LATENESS_WINDOW = 4096
#: Upper edges (ms) of the buckets of the lateness histogram every status carries, as
#: cyclictest keeps one: counts since the first cycle, so that two statuses give the lateness
#: over the cycles between them (the last bucket is everything later than 1 s).
LATENESS_EDGES_MS = (0.1, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0)
_LATENESS_EDGES_S = tuple(e / 1000 for e in LATENESS_EDGES_MS)


class Driver(Protocol):
    """What the runtime needs of a servo driver (drivers.base.ModuleDriver fits)."""

    def set_targets(self, dof1_deg: float, dof2_deg: float) -> None: ...


class LinkObserver(Protocol):
    """Who else watches the links (a rollout host, :mod:`firmware.flash.module_host`): told of each
    cycle's start before the engine runs, once the cycle's link frames (hormones, beacons) are
    sent, of every Hello (verified or refused), and of connectors liveness found silent. It
    may switch the program at a cycle start."""

    def cycle_start(self, rt: ModuleRuntime, now: float) -> None: ...

    def cycle_sent(self, rt: ModuleRuntime) -> None: ...

    def hello(self, connector: int, remote: int, hello: Hello, now: float) -> None: ...

    def link_down(self, connector: int, now: float) -> None: ...

    def attached(self, connector: int) -> None: ...

    def detached(self, connector: int) -> None: ...


class _Recoverable(Protocol):
    def health(self) -> Any: ...

    def recover(self) -> Any: ...


@dataclass(slots=True)
class RuntimeCounters:
    """The runtime's own counts (the transport, the engine and the liveness machine keep theirs)."""

    cycles: int = 0
    keepalives_sent: int = 0
    hellos_sent: int = 0
    late_cycles: int = 0
    #: periods lost to late starts (a late cycle restarts the schedule from now)
    cycles_skipped: int = 0
    lost_in_flight: int = 0
    hormones_sent: int = 0
    hormones_received: int = 0
    actuator_faults: int = 0
    #: hormones dropped from a neighbour still on another program (a rollout's switch window)
    foreign_hormones: int = 0
    #: programs switched to while running (a rollout)
    switches: int = 0
    log: list[str] = field(default_factory=list)


class ModuleRuntime:
    """One module: engine, transport, driver, liveness. Step it or :meth:`run` it."""

    def __init__(
        self,
        program: CompiledProgram,
        transport: Transport,
        *,
        timer_phase: int = 0,
        natives: Mapping[str, Native] | None = None,
        driver: Driver | None = None,
        cycle_period: float = CYCLE_PERIOD_S,
        silence_cycles: int = SILENCE_CYCLES,
        clock: Callable[[], float] = time.monotonic,
        record: bool = False,
        module: int = 0,
        name: str = "",
        cpu_clock: Callable[[], float] = time.process_time,
    ) -> None:
        if cycle_period <= 0:
            raise ValueError(f"cycle_period {cycle_period!r} must be positive")
        self.program = program
        self.transport = transport
        #: connectors whose peer said it is a tool (runs no program), or docks by a connector
        #: that cannot dock there: each told once in the log
        self._tools: set[int] = set()
        self._misdocked: set[int] = set()
        available = dict(STANDARD_NATIVES)
        available.update(natives or {})
        self._natives = available
        used = {n: available[n] for n in program.natives if n in available}
        self.engine = Engine(program, timer_phase=timer_phase, natives=used)
        self.driver = driver
        #: The servo fault in force, as the driver reported it (None when all is well).
        self.actuator_fault: str | None = None
        self.cycle_period = cycle_period
        self.clock = clock  # the transport stamps arrivals on it too
        self.record = record
        self.module = module
        self.name = name or f"m{module}"
        self.health_offset = timer_phase % HEALTH_EVERY
        self.digest = program_digest(program.image)
        self.liveness = Liveness(self.digest, silence_cycles)
        self.cycle = 0
        self.stats = RuntimeCounters()
        #: the module's sensors: sources, pushed readings, forced values (dh2rt.sensing)
        self.sensing = SensorFeed(self.engine, offset=timer_phase, log=self._log)
        #: how late each recent cycle started (seconds after its deadline), and when the first did
        self.lateness: deque[float] = deque(maxlen=LATENESS_WINDOW)
        #: cycles per lateness bucket (LATENESS_EDGES_MS) since the first
        self.lateness_counts = [0] * (len(LATENESS_EDGES_MS) + 1)
        self.first_cycle_at: float | None = None
        #: the module's own work between recent cycle starts: CPU seconds its process used from
        #: one cycle's start to the next (``cpu_clock``: its thread's when modules are threads
        #: of one process, hil.supervisor.ThreadModule). A cycle that started late after little
        #: work was held by the machine (another process had the processor); one that started
        #: late after as much work as the delay was held by the module itself
        self.work: deque[float] = deque(maxlen=LATENESS_WINDOW)
        self.cpu_clock = cpu_clock
        self._cpu_at: float | None = None
        #: how far late starts moved the schedule in all (s): cycles_skipped is its whole periods
        self._shifted_s = 0.0
        self.records: list[dict[str, Any]] = []
        self.effects: list[tuple[str, tuple[Any, ...]]] = []
        #: The last receptor fault, as ``cycle N: receptor R: message`` (None: none yet).
        self.last_fault: str | None = None
        self._pending: list[Received] = []
        self._heard: set[int] = set()  # connectors heard between cycles (Hellos)
        self._started = 0.0
        self._injected: list[Hormone] = []
        self._commanded: tuple[float, float] | None = (self.engine.dof[0], self.engine.dof[1])
        #: joint targets (degrees, by DOF index 0/1) an outside motion holds (see hold())
        self.held: dict[int, float] = {}
        #: told of cycle starts, Hellos and silent links (None: nobody)
        self.observer: LinkObserver | None = None
        #: paused by the operator (:meth:`pause`): links live, engine and joints still
        self.paused = False
        #: told each cycle of the hormones it received and was given (the operator's watch)
        self.on_arrivals: Callable[[list[Arrival]], None] | None = None
        self._held_arrivals: list[Arrival] = []

    @property
    def clock(self) -> Callable[[], float]:
        """This module's clock (monotonic seconds); the transport stamps arrivals on it."""
        return self._clock

    @clock.setter
    def clock(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self.transport.clock = clock

    # ------------------------------------------------------------ links

    def attach(self, connector: int, end: LinkEnd | str) -> None:
        """Attach ``connector`` to a link end and announce this module's program there."""
        if isinstance(end, str):
            self.transport.attach(connector, end)  # type: ignore[arg-type]  # serial takes a URL
        else:
            self.transport.attach(connector, end)
        self.liveness.attach(connector)
        if self.observer is not None:
            self.observer.attached(connector)

    def detach(self, connector: int) -> None:
        """Detach ``connector``; the engine senses the link gone at once, and what had come
        in through it but was not yet taken in is lost in flight (dh2rt.docking's rule)."""
        self.transport.detach(connector)
        self.liveness.detach(connector)
        self._pending, lost = docking.without_in_flight(self._pending, connector)
        self._heard.discard(connector)
        self.stats.lost_in_flight += lost
        if self.engine.status[connector - 1]:
            self.engine.link_down(connector)
        if self.observer is not None:
            self.observer.detached(connector)

    def inject(self, hormone: Hormone) -> None:
        """Place a hormone in the mailbox, as if sensed or created here (next cycle)."""
        self.program.vocabulary.check(hormone)
        self._injected.append(hormone)

    def pause(self, paused: bool) -> bool:
        """Pause (True) or resume (False) from the next cycle; returns whether that changed
        anything. A paused module keeps its links (Hellos, keep-alives, liveness) and its
        joints at their last targets, and does not step its engine: LocalTimer, periodic
        hormones and receptors stand still, and the hormones that arrive meanwhile wait in
        its mailbox for the cycle it resumes in, so it goes on where it stopped."""
        if paused == self.paused:
            return False
        self.paused = paused
        self._log("paused by the operator" if paused else "resumed by the operator")
        return True

    @property
    def silence_cycles(self) -> int:
        return self.liveness.silence_cycles

    def verified(self, connector: int) -> bool:
        return self.liveness.verified(connector)

    def handshake(self, timeout: float, *, until: float | None = None) -> bool:
        """Before cycle 0: beacon every period until every attached connector heard its
        peer's Hello or ``timeout`` s passed; with ``until`` (a reading of this runtime's
        clock), go on beaconing until then, so that modules told to start together find
        each other linked. Frames that arrive meanwhile are kept for cycle 0. Returns
        whether every connector's peer was verified (or refused)."""
        start = self.clock()
        deadline = start + timeout if until is None else max(until, start)
        next_beacon = start
        while True:
            self._absorb(self.transport.poll(0.0))
            settled = self.liveness.settled
            now = self.clock()
            if (settled and until is None) or now >= deadline:
                return settled
            if now >= next_beacon:
                # a neighbour may have opened its end after our first Hello, and one that is
                # already done waiting must not find us silent: beacon every period meanwhile
                next_beacon = now + self.cycle_period
                self._beacon(set())
            self._absorb(self.transport.poll(min(deadline, next_beacon) - now))

    def listen(self, seconds: float) -> None:
        """Before cycle 0: take frames in for ``seconds`` (Hellos are handled, the rest kept
        for cycle 0), as :meth:`handshake` does between its beacons."""
        deadline = self.clock() + seconds
        while (left := deadline - self.clock()) > 0:
            self._absorb(self.transport.poll(left))

    def take_in(self, timeout: float = 0.0) -> None:
        """Between cycles: take in what came, waiting up to ``timeout`` for it, as :meth:`run`
        does while it waits (for a caller with a loop of its own): Hellos are handled now,
        the rest kept for the next cycle."""
        self._absorb(self.transport.poll(timeout))

    def _absorb(self, received: list[Received]) -> None:
        """Handle Hellos now (verification and link status); keep the rest for the cycle."""
        for r in received:
            if isinstance(r.frame, Hello):
                if self._on_frame(r):
                    self._heard.add(r.at)
            else:
                self._pending.append(r)

    # ------------------------------------------------------------ one cycle

    def step(self) -> None:
        """One cycle: receive, liveness, engine, send, beacons, driver (see module docs)."""
        engine = self.engine
        self._started = self.clock()
        if self.observer is not None:
            self.observer.cycle_start(self, self._started)
            engine = self.engine  # the observer may have switched the program
        self.sensing.fill(self.cycle)
        received = self._pending
        self._pending = []
        received.extend(self.transport.poll(0.0))
        heard = self._heard
        self._heard = set()
        arrivals: list[Arrival] = []
        for r in received:
            if self._on_frame(r):
                heard.add(r.at)
                if isinstance(r.frame, Hormone):
                    if self.liveness.foreign(r.at):
                        self.stats.foreign_hormones += 1
                    else:
                        arrivals.append(Arrival(r.at, r.remote, r.frame))
        linked = {c for c, s in enumerate(engine.status, 1) if s}
        for c, silent in self.liveness.tick(heard, linked):
            engine.link_down(c)
            self._log(f"connector {self._cname(c)} silent for {silent} cycles: status 0")
            if self.observer is not None:
                self.observer.link_down(c, self._started)
        arrivals.sort(key=_by_connector)  # as the in-process robot orders a mailbox
        if self._injected:
            arrivals.extend(Arrival(0, 0, h) for h in self._injected)
            self._injected = []
        self.stats.hormones_received += sum(1 for a in arrivals if a.at)
        if self.on_arrivals is not None and arrivals:
            self.on_arrivals(arrivals)
        if self.paused:  # the engine waits: what came is its mailbox when it resumes
            self._held_arrivals.extend(arrivals)
            arrivals = []
            out: Sequence[Emission] = ()
        else:
            if self._held_arrivals:
                arrivals = self._held_arrivals + arrivals
                self._held_arrivals = []
            out = engine.step(arrivals)
        sent: list[Emission] = []
        carried: set[int] = set()
        for em in out:
            if self.transport.send(em.through, em.hormone):
                sent.append(em)
                carried.add(em.through)
            else:
                engine.send_failed(em.through)
        self.stats.hormones_sent += len(sent)
        self._beacon(carried)
        if self.observer is not None:
            self.observer.cycle_sent(self)
        faults: list[str] = []
        if engine.effects:
            for kind, args in engine.effects:
                if kind == "fault":
                    faults.append(f"{args[0]}: {args[1]}")
                else:
                    self.effects.append((kind, args))
            if faults:
                self.last_fault = f"cycle {self.cycle}: {faults[-1]}"
                self._log(f"fault: {faults[-1]}")
        held = self.held
        self._actuate(held.get(0, engine.dof[0]), held.get(1, engine.dof[1]))
        engine.dof_changed = False
        if self.record:
            self.records.append(self._record(arrivals, sent, faults))
        self.cycle += 1
        self.stats.cycles = self.cycle

    def switch_program(self, program: CompiledProgram, version: int | None, note: str) -> None:
        """Run ``program`` from this cycle on (a rollout's agreed switch): a new engine whose
        LocalTimer goes on from the old one's (modulo the new ClockCycle) and which keeps
        ConnectorStatus and the joints' angles, a codec for its hormones, and a Hello with its
        digest and ``version`` through every attached connector at once."""
        old = self.engine
        used = {n: self._natives[n] for n in program.natives if n in self._natives}
        engine = Engine(program, timer_phase=old.timer, natives=used)
        for c, remote in enumerate(old.status, 1):
            if remote:
                engine.link_up(c, remote)
        engine.dof[0], engine.dof[1] = old.dof[0], old.dof[1]
        self.program, self.engine = program, engine
        self.sensing.rebind(engine)
        self.transport.codec = FrameCodec(program.vocabulary, program.profile.connector_count)
        self.digest = program_digest(program.image)
        self.liveness.announce(self.digest, version)
        self.stats.switches += 1
        self._log(note)
        hello = Hello(self.digest, version)
        for c in self.liveness.connectors:
            if self.transport.send(c, hello):
                self.stats.hellos_sent += 1

    # ------------------------------------------------------------ sensors

    def add_sensor_source(self, source: Source, *, every: int = 1, label: str = "") -> bool:
        """Fill sensors from ``source`` (a ``drivers.base.SensorSource`` or a callable) every
        ``every`` cycles, before the engine runs; False when it reads nothing the program
        declares (it is not read while the running program declares none of its sensors)."""
        return self.sensing.add_source(source, every=every, label=label)

    def sense(self, name: str, value: int) -> None:
        """Sensor ``name`` reads ``value`` from now on (a ``sense`` event); TopologyError if the
        program does not declare it or the value is out of the profile's range."""
        self.sensing.force(name, value)

    def push_readings(self, values: Mapping[str, float]) -> None:
        """Sensor readings measured elsewhere (the HIL world's physics), for the next cycle."""
        self.sensing.push(values)

    def attach_driver(self, driver: Driver, note: str) -> None:
        """Actuators that were missing are back: drive them from now on (the current targets
        are sent in the next cycle) and say so in the log."""
        self.driver = driver
        self.actuator_fault = None
        self._commanded = None
        self._log(f"actuators back: {note}")

    def hold(self, targets: Mapping[int, float]) -> None:
        """From the next cycle on, the driver is sent ``targets`` (degrees, by DOF index: 0 is
        DOF1, 1 is DOF2) for those joints in place of the engine's DOF1/DOF2: a motion outside
        the program owns them (docking by motion in the loop, hil.reach_loop). Empty: the
        joints are the program's again (its targets are sent at the next cycle). The engine's
        own DOF1/DOF2 go on as the program sets them."""
        for dof in targets:
            if dof not in (0, 1):
                raise DriverError(f"hold: joint {dof} is neither DOF1 (0) nor DOF2 (1)")
        self.held = {dof: float(v) for dof, v in targets.items()}

    @property
    def commanded(self) -> tuple[float, float]:
        """The DOF1/DOF2 targets the driver was last given (or the engine's, before any)."""
        return self._commanded or (self.engine.dof[0], self.engine.dof[1])

    def _actuate(self, dof1: float, dof2: float) -> None:
        """Command the driver; report servo faults and try to recover, never stop the module."""
        driver = self.driver
        if driver is None:
            return
        try:
            if self.cycle % HEALTH_EVERY == self.health_offset:
                self._check_health(driver)
            if (dof1, dof2) != self._commanded and self.actuator_fault is None:
                driver.set_targets(dof1, dof2)
                self._commanded = (dof1, dof2)
        except DriverError as exc:
            self._actuator_fault(str(exc))

    def _check_health(self, driver: Driver) -> None:
        """Read the driver's health; while a fault lasts, try recover() straight away (it
        checks the servos itself and stops at the first that does not answer: one reply
        timeout, where health() first would wait one per servo)."""
        health = getattr(driver, "health", None)
        if health is None:
            return
        if self.actuator_fault is not None and callable(getattr(driver, "recover", None)):
            faults = tuple(cast(_Recoverable, driver).recover().faults)
        else:
            faults = tuple(health().faults)
        if faults:
            self._actuator_fault("; ".join(faults))
        elif self.actuator_fault is not None:
            self._log(f"actuators recovered (after: {self.actuator_fault})")
            self.actuator_fault = None
            self._commanded = None  # send the targets again

    def _actuator_fault(self, message: str) -> None:
        self.stats.actuator_faults += 1
        if message != self.actuator_fault:
            self._log(f"actuator fault: {message}")
        self.actuator_fault = message

    def _beacon(self, carried: set[int]) -> None:
        """Send the beacons the liveness machine asks for this cycle."""
        for beacon in self.liveness.beacons(carried, self.cycle):
            self._send(beacon)

    def _send(self, beacon: Beacon) -> None:
        if self.transport.send(beacon.connector, beacon.frame):
            if isinstance(beacon.frame, Hello):
                self.stats.hellos_sent += 1
            else:
                self.stats.keepalives_sent += 1

    def _on_frame(self, r: Received) -> bool:
        """Account for one frame; True if it counts as heard from a verified peer."""
        frame = r.frame
        was_refused = self.liveness.refused(r.at)
        verdict = self.liveness.receive(r.at, frame, self.cycle)
        if self.observer is not None and isinstance(frame, Hello) and verdict is not Verdict.UNATTACHED:
            self.observer.hello(r.at, r.remote, frame, self.clock())
        if verdict is Verdict.TOOL:
            if r.at not in self._tools:
                self._tools.add(r.at)
                self._log(f"connector {self._cname(r.at)}: a programming cable (a peer that runs no program)")
            if self.engine.status[r.at - 1]:
                self.engine.link_down(r.at)
            return False
        self._tools.discard(r.at)
        if verdict is Verdict.REFUSED:
            assert isinstance(frame, Hello)
            if not was_refused:
                self._log(
                    f"connector {self._cname(r.at)}: neighbour runs another program "
                    f"(digest {frame.digest.hex()}, mine {self.digest.hex()}): refused"
                )
            if self.engine.status[r.at - 1]:
                self.engine.link_down(r.at)
            return False
        if verdict is not Verdict.HEARD:
            return False
        if not self.program.profile.can_link(r.at, r.remote):
            # a peer that says it is docked by a connector that cannot dock here (two of one
            # gender): not a link this module's types know; told once, ignored
            if r.at not in self._misdocked:
                self._misdocked.add(r.at)
                self._log(
                    f"connector {self._cname(r.at)}: the peer's {self._cname(r.remote)} cannot dock here "
                    "(connectors of one gender): ignored"
                )
            return False
        self._misdocked.discard(r.at)
        self.engine.link_up(r.at, r.remote)
        return True

    def _record(self, arrivals: list[Arrival], sent: list[Emission], faults: list[str]) -> dict[str, Any]:
        """This cycle in the trace format of :mod:`dh2rt.records`, plus ``t``: the clock when
        the cycle began (after whatever it received had been sent)."""
        record = cycle_json(self.engine, self.cycle, self.module, self.name, arrivals, sent, faults)
        record["t"] = self._started
        return record

    # ------------------------------------------------------------ running

    def run(
        self,
        cycles: int | None = None,
        stop_event: threading.Event | None = None,
        on_cycle: Callable[[ModuleRuntime], None] | None = None,
        sleep: Callable[[float], None] | None = None,
        until: float | None = None,
        before_cycle: Callable[[ModuleRuntime], None] | None = None,
        start: float | None = None,
    ) -> int:
        """Cycle every ``cycle_period`` s until ``cycles`` more ran, ``stop_event`` is set, or
        the next cycle would start at or after ``until`` (a reading of this runtime's clock:
        modules told to stop at one instant stop together, however many cycles each managed).
        The first cycle is due at ``start`` (default: now): modules told to start at one
        instant wait for it, and one that comes to it late counts the periods it lost.

        Between cycles the loop takes frames in as they arrive, or on a transport that says not
        to (a shared bus: ``Transport.read_between_cycles``) sleeps and reads them at the next
        cycle's start.
        A cycle that starts more than LATE_TOLERANCE periods after its deadline counts as
        late; the schedule then restarts from now rather than bursting to catch up.
        ``before_cycle`` runs just before each cycle (the host takes its commands there, so
        that what arrived while the loop waited counts in the very next cycle; it may set
        ``stop_event``, and then that cycle does not run); ``on_cycle`` runs after each
        cycle. Returns cycles run.
        """
        period = self.cycle_period
        done = 0
        deadline = self.clock() if start is None else start
        self._wait_until(deadline, sleep)
        last_start = None if until is None else until - period / 2
        while (cycles is None or done < cycles) and not (stop_event is not None and stop_event.is_set()):
            if last_start is not None and deadline >= last_start:
                break
            if before_cycle is not None:
                before_cycle(self)
                if stop_event is not None and stop_event.is_set():
                    break
            now = self.clock()
            cpu = self.cpu_clock()
            if self._cpu_at is not None:
                self.work.append(cpu - self._cpu_at)
            self._cpu_at = cpu
            late = now - deadline
            self.lateness.append(late)
            self.lateness_counts[bisect.bisect_left(_LATENESS_EDGES_S, late)] += 1
            if self.first_cycle_at is None:
                self.first_cycle_at = now
            if late > LATE_TOLERANCE * period:
                # the schedule restarts from now: it moved by all of ``late``, fractions too
                # (three starts 0.7 of a period late lose two cycles, not none)
                self.stats.late_cycles += 1
                self._shifted_s += late
                self.stats.cycles_skipped = int(self._shifted_s / period)
                deadline = now
            self.step()
            done += 1
            if on_cycle is not None:
                on_cycle(self)
            deadline += period
            self._wait_until(deadline, sleep)
        return done

    def drain(self, quiet: float, most: float) -> int:
        """After the last cycle: take in what the neighbours sent in their last cycles, without
        acting on it, so that every frame sent is counted received (or corrupted, dropped,
        unhandled) by someone. It reads until nothing has come for ``quiet`` seconds, and for
        ``most`` seconds at the most: a medium that delivers late (a relay or an adapter the
        machine held for a moment) is waited for, not counted short. A fixed window of three
        periods left 24 of 780 frames unread on slcan adapters with one core kept busy.
        Returns how many frames came in, of every family."""
        start = self.clock()
        taken = self._taken()
        first, last_came = taken, start
        while (left := min(start + most, last_came + quiet) - self.clock()) > 0:
            self.transport.poll(left)
            now = self._taken()
            if now != taken:
                taken, last_came = now, self.clock()
        return taken - first

    def _taken(self) -> int:
        """Frames the transport has taken in so far, of every family and outcome."""
        c = self.transport.counters
        return c.received + c.corrupted + c.dropped + c.unhandled

    def _wait_until(self, deadline: float, sleep: Callable[[float], None] | None) -> None:
        """Until ``deadline``: take frames in as they come (the transport's
        ``read_between_cycles``), or sleep, leaving them in the medium for the next cycle."""
        if sleep is None and not self.transport.read_between_cycles:
            sleep = time.sleep
        while True:
            left = deadline - self.clock()
            if left <= 0:
                return
            if sleep is not None:
                sleep(left)
                return
            self._absorb(self.transport.poll(left))

    # ------------------------------------------------------------ reading

    @property
    def counters(self) -> dict[str, int]:
        """Transport frame counts, the engine's hormone counts and the runtime's own."""
        link = self.transport.counters
        s = self.stats
        lv = self.liveness.counters
        return {
            "cycles": s.cycles,
            "frames_sent": link.sent,
            "frames_received": link.received,
            "frames_dropped": link.dropped,
            "frames_corrupted": link.corrupted,
            "frames_send_failed": link.send_failed,
            "frames_unhandled": link.unhandled,
            "keepalives_sent": s.keepalives_sent,
            "hellos_sent": s.hellos_sent,
            "refused": lv.refused,
            "ignored": lv.ignored,
            "links_lost": lv.links_lost,
            "beacons_missed": lv.beacons_missed,
            "late_cycles": s.late_cycles,
            "cycles_skipped": s.cycles_skipped,
            "lost_in_flight": s.lost_in_flight,
            "hormones_sent": s.hormones_sent,
            "hormones_received": s.hormones_received,
            "sensor_faults": self.sensing.faults,
            **{f"engine_{k}": v for k, v in self.engine.counters.items()},
        }

    def lateness_ms(self) -> dict[str, float] | None:
        """How late the last LATENESS_WINDOW cycles started after their deadline, in ms:
        median, 99th percentile (nearest rank) and worst; None before the first cycle."""
        return _percentiles_ms(self.lateness)

    def work_ms(self) -> dict[str, float] | None:
        """The module's own work (CPU time of its process, or thread) between the last LATENESS_WINDOW
        cycle starts, in ms: median, 99th percentile and worst; None before the second cycle.
        Beside :meth:`lateness_ms` it tells who held a late cycle: the module, or the machine."""
        return _percentiles_ms(self.work)

    def status(self) -> dict[str, Any]:
        """A status line: type, T, DOF1/DOF2, ConnectorStatus, counters."""
        e = self.engine
        t = e.topo_type
        return {
            "module": self.module,
            "name": self.name,
            "cycle": self.cycle,
            "type": t.name,
            "T": t.alias,
            "DOF1": e.dof[0],
            "DOF2": e.dof[1],
            "status": list(e.status),
            "lateness_ms": self.lateness_ms(),
            "work_ms": self.work_ms(),
            "lateness_hist": {"edges_ms": list(LATENESS_EDGES_MS), "counts": list(self.lateness_counts)},
            "first_cycle_at": self.first_cycle_at,
            "counters": self.counters,
            "actuator_fault": self.actuator_fault,
            "last_fault": self.last_fault,
            "sensors": e.named_sensors(),
            "variables": e.variables(),
            "paused": self.paused,
            "last_sensor_fault": self.sensing.last_fault,
        }

    @property
    def log(self) -> list[str]:
        return self.stats.log

    def _log(self, message: str) -> None:
        self.stats.log.append(f"cycle {self.cycle}: {message}")
        del self.stats.log[:-50]

    def _cname(self, connector: int) -> str:
        return self.engine.profile.connector_name(connector)

    def close(self) -> None:
        self.transport.close()


def _percentiles_ms(values: Iterable[float]) -> dict[str, float] | None:
    """Median, 99th percentile (nearest rank) and worst of ``values`` (s), in ms; None if empty."""
    ordered = sorted(values)
    n = len(ordered)
    if not n:
        return None

    def rank(q: float) -> float:
        return round(ordered[min(n - 1, max(0, math.ceil(q * n) - 1))] * 1000, 3)

    return {"p50": rank(0.50), "p99": rank(0.99), "max": round(ordered[-1] * 1000, 3)}


def _by_connector(a: Arrival) -> int:
    return a.at
