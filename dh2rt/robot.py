"""A whole robot in one process: N module engines over an in-process bus, in lockstep.

The robot plays the physical world: it knows which connectors are docked (the topology),
delivers every hormone a module sends through a docked connector to the neighbour's
connector one cycle later, tells modules about docking and undocking (presence sensing),
and carries out the effects native actions ask for. Modules know none of this: no module
ever sees an index.

Determinism: a run depends only on the program, the topology and the seed. LocalTimers start
at phases drawn from the seed; everything a module receives in one cycle is ordered by the
connector it arrived at (and send order within a link), never by module numbering.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from dh2rt import docking
from dh2rt.docking import End
from dh2rt.engine import Engine, Native
from dh2rt.errors import EventError, TopologyError
from dh2rt.events import Event
from dh2rt.hormone import Arrival, Emission, Hormone
from dh2rt.natives import STANDARD_NATIVES
from dh2rt.profile import undeclared_sensor
from dh2rt.program import CompiledProgram
from dh2rt.skew import DEFAULT_BLOCK, DEFAULT_DEPTH, SkewPlan, make_plan
from dh2rt.topology import Link, Topology

EffectHandler = Callable[["Robot", int, tuple[Any, ...]], None]
#: What the robot keeps of receptor faults (the engines count them all).
MAX_FAULT_RECORDS = 1000


@dataclass(frozen=True, slots=True)
class Fault:
    """A receptor's action failed (see dh2rt.engine.ACTION_FAULTS)."""

    cycle: int
    module: int
    source: str  # "receptor NAME" or "periodic NAME"
    message: str

    def describe(self, names: Sequence[str]) -> str:
        return f"cycle {self.cycle}: {names[self.module]}: {self.source}: {self.message}"


@dataclass(slots=True)
class CycleRecord:
    """What one module did in one cycle (the trace's line)."""

    cycle: int
    module: int
    received: list[Arrival]
    sent: list[Emission]
    faults: list[str]  # "receptor NAME: message" for each fault of this cycle


class PhaseDraw:
    """Where LocalTimer phases come from when none is given: the one rule of the in-process
    robot and of the HIL world (hil.world), so that a seed gives the same phases in both.
    Phases are drawn from ``Random(seed)`` in boot order: every module at the start, in the
    order the topology lists them, then each restart as it happens.

    This order is the one thing in a run that depends on how modules are listed: the same
    robot listed in another order gives its modules other phases, as another seed would
    (programs never see a module's index or name). Drawing each phase from the seed and the
    module's name instead was built and measured (snake to quadruped in physics formed and
    separated at 3 of seeds 0-5 with it, 6 of 6 with this draw), and is not used yet."""

    def __init__(self, seed: int) -> None:
        self._rng = random.Random(seed)

    def next(self, clock_cycle: int) -> int:
        """The next module's phase: 0 .. ``clock_cycle`` - 1."""
        return self._rng.randrange(clock_cycle)


class Robot:
    """Modules of ``topology`` running ``program``; call :meth:`step` or :meth:`run`."""

    def __init__(
        self,
        program: CompiledProgram,
        topology: Topology,
        *,
        seed: int = 0,
        natives: Mapping[str, Native] | None = None,
        record: bool = False,
        timer_phases: Sequence[int] | None = None,
        skip_quiet: bool = True,
    ) -> None:
        self.program = program
        self.topology = topology
        self.profile = topology.profile
        self.seed = seed
        self.phase_draw = PhaseDraw(seed)
        self.natives = dict(STANDARD_NATIVES)
        self.natives.update(natives or {})
        used = {n: self.natives[n] for n in program.natives if n in self.natives}
        self._natives_used = used
        self.cycle = 0
        self.size = topology.size
        if timer_phases is not None and len(timer_phases) != self.size:
            raise TopologyError(f"timer_phases has {len(timer_phases)} entries for {self.size} modules")
        self.engines: list[Engine | None] = [
            self._boot(m, None if timer_phases is None else timer_phases[m]) for m in range(self.size)
        ]
        #: The order modules are stepped in; results never depend on it (tested).
        self.step_order: list[int] = list(range(self.size))
        #: Event-driven lockstep: a module whose next cycles are quiet (Engine.quiet_cycles)
        #: sleeps until mail, a link change or its next due LocalTimer value, then catches
        #: up its timer with Engine.skip. Identical results; off while recording traces.
        self.skip_quiet = skip_quiet
        self._slept_at: list[int] = [-1] * self.size  # cycle it fell asleep, -1 awake
        self._wake_at: dict[int, list[int]] = {}
        #: advance() steps windows of up to skew_depth cycles over blocks of skew_block modules
        self.skew_block = DEFAULT_BLOCK
        self.skew_depth = DEFAULT_DEPTH
        self._skew_plan: SkewPlan | None = None
        self.peer: dict[tuple[int, int], tuple[int, int]] = {}
        # the same links per module, indexed by connector: the hot path's lookup
        self._adjacent: list[list[tuple[int, int] | None]] = [
            [None] * (self.profile.connector_count + 1) for _ in range(self.size)
        ]
        #: What each module will find in its mailbox next cycle (only modules that have mail).
        self.inbox: dict[int, list[Arrival]] = {}
        self.record = record
        self.records: list[CycleRecord] = []
        self.pending: list[tuple[int, Callable[[], None]]] = []
        self.effect_handlers: dict[str, EffectHandler] = {
            "reach_and_dock": _reach_and_dock,
            "reach_dock": lambda r, m, a: docking.reach_and_dock_to(r, m, a[0], a[1], a[2]),
            "release": lambda r, m, a: docking.release(r, m, a[0]),
            "assist": lambda _r, _m, _a: None,
        }
        #: Receptor faults in the order they happened (the last MAX_FAULT_RECORDS).
        self.faults: list[Fault] = []
        self.log: list[str] = []
        #: Hormones that were on their way across a link when it was cut or its sender or
        #: receiver was killed: never delivered (dh2rt.docking.without_in_flight).
        self.lost_in_flight = 0
        #: Sensor values set by sense events (:meth:`sense`), per module: they hold until the
        #: next one, across restarts, and whatever else fills sensors (the physics) leaves them.
        self.sensed: dict[int, dict[str, int]] = {}
        for link in topology.links:
            self.dock(link.a, link.a_conn, link.b, link.b_conn)

    def _boot(self, module: int, phase: int | None = None) -> Engine:
        if phase is None:
            phase = self.phase_draw.next(self.program.clock_cycle)
        return Engine(self.program, timer_phase=phase, natives=self._natives_used)

    # ------------------------------------------------------------ the physical world

    def links(self) -> list[Link]:
        """The docked links now, each once."""
        return [Link(a, ac, b, bc) for (a, ac), (b, bc) in sorted(self.peer.items()) if (a, ac) < (b, bc)]

    def engine(self, module: int) -> Engine:
        """A running module's engine, its LocalTimer brought up to date."""
        e = self.engines[module]
        if e is None:
            raise TopologyError(f"module {self.topology.names[module]} is not running")
        slept = self._slept_at[module]
        if slept >= 0 and slept != self.cycle:
            e.skip(self.cycle - slept)
            self._slept_at[module] = self.cycle
        return e

    def _wake(self, module: int) -> None:
        slept = self._slept_at[module]
        if slept >= 0:
            e = self.engines[module]
            if e is not None and self.cycle > slept:
                e.skip(self.cycle - slept)
            self._slept_at[module] = -1

    def alive(self, module: int) -> bool:
        return self.engines[module] is not None

    def asleep(self) -> list[int]:
        """The modules asleep now (``skip_quiet``): quiet until mail, a link change or their
        timer's next due value wakes them."""
        return [m for m, slept in enumerate(self._slept_at) if slept >= 0]

    @property
    def skew_plan(self) -> SkewPlan | None:
        """How :meth:`advance` steps its skewed windows; None until it first skews, and again
        after a link changes."""
        return self._skew_plan

    # the docking world (dh2rt.docking.DockingWorld): nothing to align in one process

    def peer_of(self, end: End) -> End | None:
        return self.peer.get(end)

    def running(self, module: int) -> bool:
        return self.alive(module)

    def aligned(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        return True

    def note(self, message: str) -> None:
        self.log.append(f"cycle {self.cycle}: {message}")

    def dock(self, a: int, a_conn: int, b: int, b_conn: int) -> None:
        """Dock two free connectors of different gender; both modules sense it."""
        docking.check_dock(self.profile, self.peer.__contains__, self.where, a, a_conn, b, b_conn)
        self._wake(a)
        self._wake(b)
        self.peer[(a, a_conn)] = (b, b_conn)
        self.peer[(b, b_conn)] = (a, a_conn)
        self._adjacent[a][a_conn] = (b, b_conn)
        self._adjacent[b][b_conn] = (a, a_conn)
        self._skew_plan = None  # the links changed
        for m, c, rc in ((a, a_conn, b_conn), (b, b_conn, a_conn)):
            e = self.engines[m]
            other = self.engines[b if m == a else a]
            if e is not None and other is not None:
                e.link_up(c, rc)

    def cut(self, module: int, connector: int) -> None:
        """Break the link at a connector (live surgery); both modules sense it."""
        other = docking.check_cut(self.peer.get((module, connector)), self.where(module, connector))
        del self.peer[(module, connector)]
        del self.peer[other]
        self._adjacent[module][connector] = None
        self._adjacent[other[0]][other[1]] = None
        self._skew_plan = None  # the links changed
        self._wake(module)
        self._wake(other[0])
        for m, c in ((module, connector), other):
            self._drop_in_flight(m, c)
            e = self.engines[m]
            if e is not None:
                e.link_down(c)

    def _drop_in_flight(self, module: int, connector: int) -> None:
        """What is waiting in ``module``'s mailbox at ``connector`` crossed a link that is gone."""
        mail = self.inbox.get(module)
        if mail:
            kept, lost = docking.without_in_flight(mail, connector)
            if lost:
                self.inbox[module] = kept
                self.lost_in_flight += lost

    def kill(self, module: int) -> None:
        """The module stops; its neighbours sense a silent connector."""
        if self.engines[module] is None:
            return
        self._wake(module)
        self.engines[module] = None
        self.lost_in_flight += len(self.inbox.pop(module, ()))
        for _c, other, other_c, e in self._running_neighbours(module):
            self._drop_in_flight(other, other_c)  # what it sent in its last cycle dies with it
            e.link_down(other_c)

    def restart(self, module: int) -> None:
        """The module boots again with a fresh state; it and its neighbours sense the links."""
        self.kill(module)
        e = self._boot(module)
        self.engines[module] = e
        for name, value in self.sensed.get(module, {}).items():
            e.set_sensor(name, value)  # the module's surroundings did not restart
        for c, _other, other_c, oe in self._running_neighbours(module):
            e.link_up(c, other_c)
            oe.link_up(other_c, c)

    def _running_neighbours(self, module: int) -> Iterator[tuple[int, int, int, Engine]]:
        """(my connector, neighbour, its connector, its engine) for each running neighbour,
        woken so that it senses what happens next."""
        for c in range(1, self.profile.connector_count + 1):
            other = self.peer.get((module, c))
            if other is not None:
                e = self.engines[other[0]]
                if e is not None:
                    self._wake(other[0])
                    yield c, other[0], other[1], e

    def inject(self, module: int, hormone: Hormone) -> None:
        """Place a hormone in a module's mailbox, as if it had been sensed or created there."""
        self.program.vocabulary.check(hormone)
        self.engine(module)
        # An injected hormone arrives at no connector (0): it is bound here or flooded everywhere.
        self.inbox.setdefault(module, []).append(Arrival(0, 0, hormone))

    def sense(self, module: int, name: str, value: int) -> None:
        """Sensor ``name`` of a running module reads ``value`` from now on (a ``sense`` event);
        TopologyError if the module is stopped or its program declares no such sensor."""
        e = self.engine(module)
        if name not in self.program.sensor_names:
            raise TopologyError(undeclared_sensor(name))
        e.set_sensor(name, value)
        self.sensed.setdefault(module, {})[name] = value

    def apply(self, event: Event) -> None:
        """Carry out an event now; an event the robot's links or modules do not allow now
        raises EventError naming it (check_events refuses most of them before a run)."""
        try:
            self._apply(event)
        except TopologyError as exc:
            raise EventError(f"event {event.text or event.kind!r} at cycle {self.cycle}: {exc}") from None

    def _apply(self, event: Event) -> None:
        if event.kind == "cut":
            self.cut(event.module, event.connector)
        elif event.kind == "dock":
            self.dock(event.module, event.connector, event.other, event.other_connector)
        elif event.kind == "inject" and event.hormone is not None:
            self.inject(event.module, event.hormone)
        elif event.kind == "kill":
            self.kill(event.module)
        elif event.kind == "restart":
            self.restart(event.module)
        elif event.kind == "sense":
            self.sense(event.module, event.sensor, event.value)
        self.log.append(f"cycle {self.cycle}: {event.text or event.kind}")

    def schedule(self, cycles_from_now: int, action: Callable[[], None]) -> None:
        self.pending.append((self.cycle + cycles_from_now, action))

    def where(self, m: int, c: int) -> str:
        """``name.connector`` of a module's connector, for messages."""
        return f"{self.topology.names[m]}.{self.profile.connector_name(c)}"

    # ------------------------------------------------------------ running

    def step(self) -> None:
        """One lockstep cycle of every running module."""
        if self.pending:
            due = [a for when, a in self.pending if when <= self.cycle]
            self.pending = [(w, a) for w, a in self.pending if w > self.cycle]
            for action in due:
                action()
        if (not self.skip_quiet or self.record) and any(s >= 0 for s in self._slept_at):
            for m in range(self.size):
                self._wake(m)
        nxt: dict[int, list[Arrival]] = {}
        boxes = [self.inbox, nxt]
        self._due_in(boxes, self.cycle)
        effects = self._sweep(((0, self.step_order),), self.cycle, boxes)
        self.inbox = nxt
        self._carry_out(effects)
        self.cycle += 1

    def advance(self, cycles: int) -> None:
        """Run ``cycles`` cycles with no events: exactly what calling :meth:`step` that many
        times does, done in time-skewed windows (:mod:`dh2rt.skew`) whenever the world holds
        still over one: nothing scheduled, no native actions, no trace being recorded, and
        more modules than one block."""
        end = self.cycle + cycles
        while self.cycle < end:
            left = end - self.cycle
            if left > 1 and self._can_skew(min(left, self.skew_depth)):
                window = min(left, self._plan().depth)
                if window > 1:
                    self._skewed(window)
                    continue
            self.step()

    def _plan(self) -> SkewPlan:
        plan = self._skew_plan
        if plan is None or (plan.block, plan.requested) != (self.skew_block, self.skew_depth):
            neighbours = [sorted({t[0] for t in adj if t is not None}) for adj in self._adjacent]
            plan = self._skew_plan = make_plan(neighbours, block=self.skew_block, depth=self.skew_depth)
        return plan

    def _can_skew(self, window: int) -> bool:
        return (
            self.size > self.skew_block  # a robot within one block stays in cache anyway
            and self.skip_quiet
            and not self.record
            and not self.program.natives
            and all(when >= self.cycle + window for when, _ in self.pending)
        )

    def _skewed(self, window: int) -> None:
        """Cycles ``cycle .. cycle+window-1`` in the two phases of :mod:`dh2rt.skew`."""
        plan = self._plan()
        t0 = self.cycle
        boxes: list[dict[int, list[Arrival]]] = [self.inbox] + [{} for _ in range(window)]
        self._due_in(boxes, t0)
        effects: list[tuple[int, int, str, tuple[Any, ...]]] = []
        for sweep in plan.sweeps:
            effects += self._sweep(sweep.rounds(window), t0, boxes)
        self.inbox = boxes[window]
        self.cycle = t0 + window - 1
        self._carry_out(effects)  # faults only: programs with native actions never run in windows
        self.cycle += 1

    def _due_in(self, boxes: list[dict[int, list[Arrival]]], t0: int) -> None:
        """Give each sleeping module due at cycle t0+i a (maybe empty) mailbox in ``boxes[i]``:
        a sleeping module steps when it has a mailbox, and sleeps on otherwise."""
        for i, box in enumerate(boxes[:-1]):
            for m in self._wake_at.pop(t0 + i, ()):
                box.setdefault(m, [])

    def _sweep(
        self, rounds: Iterable[tuple[int, Sequence[int]]], t0: int, boxes: list[dict[int, list[Arrival]]]
    ) -> list[tuple[int, int, str, tuple[Any, ...]]]:
        """Step cycle ``t0+i`` of each listed module, for each round ``(i, modules)``.

        ``boxes[i]`` holds the mailboxes for cycle t0+i (what is sent goes to ``boxes[i+1]``);
        the caller guarantees each listed module's neighbours have done cycle t0+i-1 and
        none has done t0+i+1.
        """
        engines = self.engines
        adjacent = self._adjacent
        slept_at = self._slept_at
        record = self.record
        sleep = self.skip_quiet and not record
        window = len(boxes) - 1
        effects: list[tuple[int, int, str, tuple[Any, ...]]] = []
        nothing: list[Arrival] = []
        for i, members in rounds:
            cycle = t0 + i
            box = boxes[i]
            nxt = boxes[i + 1]
            for m in members:
                slept = slept_at[m]
                if slept >= 0:
                    if m not in box:
                        continue  # asleep: this cycle would only advance its LocalTimer
                    e = engines[m]
                    if e is None:
                        continue
                    if cycle > slept:
                        e.skip(cycle - slept)
                    slept_at[m] = -1
                else:
                    e = engines[m]
                    if e is None:
                        continue
                arrivals = box.pop(m, nothing)  # freed after this step, while in cache
                if len(arrivals) > 1:
                    arrivals.sort(key=_by_connector)
                out = e.step(arrivals)
                for through, h in out:
                    target = adjacent[m][through]
                    if target is None or engines[target[0]] is None:
                        e.send_failed(through)
                    else:
                        mail = nxt.get(target[0])
                        if mail is None:
                            nxt[target[0]] = [Arrival(target[1], through, h)]
                        else:
                            mail.append(Arrival(target[1], through, h))
                if e.effects:
                    effects.extend((m, cycle, kind, args) for kind, args in e.effects)
                if record:
                    faults = [f"{a[0]}: {a[1]}" for kind, a in e.effects if kind == "fault"] if e.effects else []
                    self.records.append(CycleRecord(cycle, m, list(arrivals), list(out), faults))
                elif sleep:
                    quiet = e.quiet_cycles()
                    if quiet is None:
                        slept_at[m] = cycle + 1
                    elif quiet > 0:
                        slept_at[m] = cycle + 1
                        due = i + 1 + quiet
                        if due < window:
                            boxes[due].setdefault(m, [])
                        else:
                            self._wake_at.setdefault(t0 + due, []).append(m)
        return effects

    def _carry_out(self, effects: list[tuple[int, int, str, tuple[Any, ...]]]) -> None:
        for m, cycle, kind, args in effects:
            if kind == "fault":
                self.faults.append(Fault(cycle, m, *args))
                del self.faults[:-MAX_FAULT_RECORDS]
                continue
            handler = self.effect_handlers.get(kind)
            if handler is not None:
                handler(self, m, args)

    def run(self, cycles: int, events: Iterable[Event] = ()) -> None:
        """Run ``cycles`` cycles, applying events at their cycles (the quiet stretches between
        them in time-skewed windows, :meth:`advance`)."""
        for _ in self.iter_cycles(cycles, events, every_cycle=False):
            pass

    def iter_cycles(self, cycles: int, events: Iterable[Event] = (), *, every_cycle: bool = True) -> Iterator[int]:
        """Run ``cycles`` cycles applying events at their cycles; yields each finished cycle,
        so that the caller can look at the robot between cycles (traces, progress, Ctrl-C).

        With ``every_cycle=False`` the cycles between events go through :meth:`advance`
        (time-skewed windows) and only the last cycle of each window is yielded: the same
        run, faster on large robots, for callers that do not look at every cycle.
        """
        by_cycle: dict[int, list[Event]] = {}
        for ev in events:
            by_cycle.setdefault(ev.cycle, []).append(ev)
        end = self.cycle + cycles
        while self.cycle < end:
            for ev in by_cycle.pop(self.cycle, []):
                self.apply(ev)
            if every_cycle:
                self.step()
            else:
                later = [c for c in by_cycle if c > self.cycle]
                self.advance(min([end, self.skew_depth + self.cycle, *later]) - self.cycle)
            yield self.cycle - 1

    def summary(self) -> list[dict[str, Any]]:
        """Per-module state: type, actuators, counters, the module's last fault (as
        ``cycle N: receptor R: message``, or None), and its variables and sensors by name."""
        last = {f.module: f for f in self.faults}
        rows = []
        for m, e in enumerate(self.engines):
            if e is None:
                rows.append({"module": m, "name": self.topology.names[m], "alive": False})
                continue
            t = e.topo_type
            rows.append(
                {
                    "module": m,
                    "name": self.topology.names[m],
                    "alive": True,
                    "type": t.name,
                    "T": t.alias,
                    "DOF1": e.dof[0],
                    "DOF2": e.dof[1],
                    **e.counters,
                    "last_fault": last[m].describe(self.topology.names) if m in last else None,
                    "variables": e.variables(),
                    "sensors": e.named_sensors(),
                }
            )
        return rows


def _by_connector(a: Arrival) -> int:
    return a.at


def _reach_and_dock(robot: Robot, module: int, args: tuple[Any, ...]) -> None:
    connector, route = args
    docking.reach_and_dock(robot, module, connector, route)
