"""Docking by motion in the loop: a ``reach_dock`` carried out by the modules' own motion.

With the PyBullet stand-in, the hardware-in-the-loop world carries a native's ``reach_dock``
(dock my connector to a connector of the module a route leads to) out as the physics runner
does (``sim.runner.PhysicsRun.start_reach``): the chain of modules along the route bends,
aligns and approaches by :class:`firmware.motion.reach.Reach`, one step per world cycle, fed
what the modules sense of the stand-in's PyBullet world (their joint angles, the asking
connector's infrared pair, the overhead tracker: :class:`sim.motion_readings.MotionSensors`).
The motion asks for the latch when its infrared pair sees the target within
``DOCK_TOLERANCE_M`` / ``DOCK_TOLERANCE_DEG``; the latch closes only if the world says the
faces are aligned within them. Then the world docks the link as for a ``dock`` event (the
emulated serial link or the link map, the contact emulator on a bus), after the latch in
physics; a motion that gives up (``firmware.motion.reach.DEFAULT_TIMEOUT`` steps) links
nothing.

The modules move themselves: each world cycle the world sends every module of the chain a
:class:`firmware.control.Hold` with the joint targets the motion wants of it; the module writes
them to its own servos through its own driver (dynamixel-sdk over its pty) in place of its
program's DOF1/DOF2 from its next cycle on, and an empty ``Hold`` gives the joints back to
its program when the motion ends. The world never writes a joint itself. docs/hil.md
("Docking by motion in the loop") says why and what it costs.

``reach_and_dock`` (legs_to_snake's ``dock_tail_to_foot``) is carried out as the physics
runner's ``PhysicsRun.assimilate`` does it: the foot at the end of the route lets go of the
body at its front, :class:`firmware.motion.crawl.Trip` takes it by its own gaits to just behind
the asking face (the tail's back), steering by the overhead tracker's poses, each step's joint
targets held by the foot's own servos through ``Hold`` as above; once it is there the last two
modules up the asking module's robot square their face by a :class:`firmware.motion.reach.Reach`
while the foot creeps (:class:`firmware.motion.crawl.Creep`,
held the same way); a dock that gives up sends the foot round again, up to
``sim.runner.BRING_ATTEMPTS`` docks. While a module's motion (a trip to its face, or a
reach it asked for) is under way, the world pushes it ``docking`` = 1 (if its program
declares the sensor; firmware.control.Readings), and 0 once it ended.

Every latch is recorded in :attr:`LoopReaches.contacts` (a :class:`sim.motion_readings.Contact`: both
faces' world poses, distance, attitude error and the infrared reading at that moment) and
logged with the cycles it took; every motion that gave up, in :attr:`LoopReaches.failed`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

from dh2rt import docking
from dh2rt.docking import DockingWorld, End
from dh2rt.profile import Profile
from dh2rt.program import CompiledProgram
from dh2rt.topology import Topology
from firmware.control import Readings
from firmware.motion.clearing import Clearing, spot_taken
from firmware.motion.crawl import Creep, Trip
from firmware.motion.kinematics import Chain
from firmware.motion.reach import Reach
from firmware.motion.readings import Readings as MotionReadings
from hil.physics_stand_in import PhysicsStandIn
from sim.motion_readings import Contact, MotionSensors, contact
from sim.runner import BRING_ATTEMPTS, DOCK_TOLERANCE_DEG, DOCK_TOLERANCE_M
from sim.tracker import OverheadTracker


class LoopWorld(DockingWorld, Protocol):
    """What the docking motions need of the loop's world (:class:`hil.world.World` offers it;
    the world imports this module, not the other way round)."""

    program: CompiledProgram
    topology: Topology
    profile: Profile
    #: the sensor values ``sense`` events forced on each module
    sensed: dict[int, dict[str, int]]

    @property
    def cycle(self) -> int: ...

    def latch(self, a: int, a_conn: int, b: int, b_conn: int) -> bool: ...

    def hold(self, module: int, targets: Mapping[int, float]) -> None: ...

    def send_readings(self, module: int, readings: Readings) -> None: ...


@dataclass
class Motion:
    """One docking motion under way in the loop."""

    reach: Reach
    #: ``asking -> target`` in words
    where: str
    #: the world cycle it was asked at, and the one its plan was ready at
    asked: int
    planned: int
    #: seconds the plan took (firmware.motion.kinematics.plan, in the world's thread)
    plan_s: float
    #: the world cycle it was last stepped at, and the world cycles since its plan was ready
    #: that went by without a step (the world's thread came too late for them)
    last: int = -1
    missed: int = 0
    #: the lone module (a foot that came, :class:`Bringing`) creeping towards the asking face
    #: meanwhile, if any
    creep: Creep | None = None
    #: where the faces were when it ended (the trace's record, read from the world)
    contact: Contact | None = None

    @property
    def modules(self) -> set[int]:
        """The modules whose joints the motion holds (the creeping foot's included)."""
        return self.reach.modules | ({self.creep.module} if self.creep is not None else set())


@dataclass
class Bringing:
    """A released foot on its way, by its own gaits, to a free face (``reach_and_dock``)."""

    trip: Trip
    #: the route up the target's robot whose joints square its face once the foot is there
    route: tuple[int, ...]
    #: the world cycle it set off at, and the one it was last stepped at
    asked: int
    last: int
    missed: int = 0


@dataclass
class CrawlingClear:
    """A robot crawling clear of a module lying on the spot behind ``face`` before ``foot``
    (the foot's end that still hangs on the body) lets go (:class:`firmware.motion.clearing.Clearing`)."""

    clearing: Clearing
    face: End
    foot: End
    #: the world cycle it was asked at, and the one it was last stepped at
    asked: int
    last: int
    missed: int = 0


@dataclass(frozen=True)
class Arrival:
    """A foot's trip that got to its spot: the foot, the face, world cycles (set off, arrived),
    the trip's steps and the world cycles it missed."""

    foot: int
    target: End
    asked: int
    arrived: int
    steps: int
    missed: int


@dataclass(frozen=True)
class Outcome:
    """How a motion ended: world cycles (asked, plan ready, latched or given up), its steps,
    the world cycles it missed, the plan's seconds."""

    asked: int
    planned: int
    ended: int
    steps: int
    missed: int
    plan_s: float
    latched: bool


class LoopReaches:
    """The docking motions of a loop world whose body is the PyBullet stand-in."""

    def __init__(self, world: LoopWorld, physics: PhysicsStandIn, tracker: OverheadTracker | None = None) -> None:
        self.world = world
        self.physics = physics
        with physics.lock:
            #: What the motions read (the chain's joint angles, every connector's infrared pair,
            #: the overhead tracker), as PhysicsRun's.
            self.sensors = MotionSensors(physics.world, tracker)
        self.motions: list[Motion] = []
        #: Every link formed by a motion, and every motion that gave up.
        self.contacts: list[Contact] = []
        self.failed: list[Contact] = []
        #: How each motion ended (those abandoned because a module stopped are only logged).
        self.outcomes: list[Outcome] = []
        #: What each module was last told to hold (absent: its joints are its program's).
        self.holding: dict[int, dict[int, float]] = {}
        #: Released feet on their way to a face (``reach_and_dock``), and every arrival.
        self.trips: list[Bringing] = []
        self.arrivals: list[Arrival] = []
        #: Robots crawling clear of a module on the spot before a foot sets off.
        self.clearings: list[CrawlingClear] = []
        #: Docks each foot brought so far has tried (see ``BRING_ATTEMPTS``).
        self.attempts: dict[int, int] = {}
        #: The ``docking`` reading last pushed to each module, if the program declares it.
        program, profile = world.program, world.profile
        self.docking_declared = "docking" in program.sensor_names and "docking" in profile.sensor_names
        self.docking_sent: dict[int, int] = {}

    def start(self, module: int, connector: int, route: Sequence[int], target_conn: int) -> bool:
        """Begin bending ``module``'s ``connector`` to ``target_conn`` of the module at the end
        of ``route``; False (logged) if the rules say no or a motion already holds one of the
        chain's joints."""
        w = self.world
        target = docking.reach_dock_target(w, module, connector, route, target_conn)
        if target is None:
            return False
        _, where = target
        if not w.profile.can_link(connector, target_conn):
            w.note(f"reach_dock {where}: both connectors are {w.profile.gender(connector)}")
            return False
        chain = Chain.along(self.physics.world.model, (module, connector), tuple(route), w.peer_of, target_conn)
        if any(m in motion.modules for motion in self.motions for m, _ in chain.joints):
            w.note(f"reach_dock {where}: another docking motion owns part of the chain")
            return False
        cycle, started = w.cycle, time.perf_counter()
        with self.physics.lock:  # the readings; not the plan (pure kinematics), which takes a while
            readings = self._read({m for m, _ in chain.joints}, {module})
        reach = Reach(chain, readings, DOCK_TOLERANCE_M, DOCK_TOLERANCE_DEG, start_cycle=cycle)
        plan_s, planned = time.perf_counter() - started, w.cycle
        self.motions.append(Motion(reach, where, cycle, planned, plan_s, last=planned - 1))
        modules = sorted({m for m, _ in chain.joints})
        w.note(
            f"reach_dock {where}: bending ({len(chain.joints)} joints of modules {modules}; asked at world cycle "
            f"{cycle}, planned in {plan_s:.2f} s)"
        )
        return True

    # ------------------------------------------------------------ reach_and_dock: the foot comes

    def assimilate(self, module: int, connector: int, route: Sequence[int]) -> bool:
        """``reach_and_dock(connector, route)`` by motion, as ``sim.runner.PhysicsRun.assimilate``
        does (legs_to_snake's ``dock_tail_to_foot``): the foot at the end of ``route`` lets go
        of the body at its front and comes to ``module``'s ``connector`` by its own gaits
        (:class:`firmware.motion.crawl.Trip`, its joints held through :class:`firmware.control.Hold`), then the
        last two modules up ``module``'s robot square their face while the foot creeps
        (:meth:`reach_other`); a dock that gives up sends the foot round again, up to
        ``BRING_ATTEMPTS`` docks. False (logged) if the rules say no: the route leads nowhere,
        the foot does not hang by its front, or a foot is already on its way to that face.
        While it lasts, ``module``'s ``docking`` sensor reads 1."""
        w = self.world
        target = docking.reach_target(w, module, connector, route)
        if target is None:
            return False
        foot, at = target
        front = w.profile.connector_index("front")
        where = f"{w.where(module, connector)} -> {w.where(foot, at)}"
        if at != front:
            w.note(f"assimilate {where}: the foot does not hang by its front")
            return False
        face = (module, connector)
        if (
            any(b.trip.target == face for b in self.trips)
            or any(m.reach.chain.asking == face for m in self.motions)
            or any(c.face == face for c in self.clearings)
        ):
            w.note(f"assimilate {where}: a foot is already on its way there")
            return False
        with self.physics.lock:
            lying = self.spot_taken(face, foot)
        if lying is not None:
            body = self.body_up(module)[::-1]
            clearing = Clearing(body, lambda: self.spot_taken(face, foot) is not None)  # stepped under the lock
            cycle = w.cycle
            self.clearings.append(CrawlingClear(clearing, face, target, cycle, cycle - 1))
            w.note(
                f"assimilate {where}: {w.topology.names[lying]} lies behind {w.where(*face)}; "
                "the robot crawls clear first"
            )
            self.sync_docking()
            return True
        return self._let_go(face, target)

    def _let_go(self, face: End, foot_end: End) -> bool:
        """The foot lets go of the body at ``foot_end`` and comes to ``face`` (:meth:`bring`)."""
        docking.release(self.world, *foot_end)
        return self.bring(foot_end[0], face, self.squaring_route(face[0]))

    def spot_taken(self, face: End, foot: int) -> int | None:
        """:func:`firmware.motion.clearing.spot_taken` by the overhead tracker (the caller holds
        the physics lock)."""
        w = self.world
        floor = self.sensors.tracker.reading(w.cycle)
        return spot_taken(floor, self.physics.world.model, w.peer_of, w.profile, w.topology.size, face, foot)

    def bring(self, foot: int, target: End, route: tuple[int, ...]) -> bool:
        """A released ``foot`` (a lone module) sets off to ``target``, a free face of another
        body (``PhysicsRun.bring``). False (logged) if the foot is not lone or the face is
        not free or of the foot's front's gender."""
        w = self.world
        front = w.profile.connector_index("front")
        b, bc = target
        where = f"{w.where(foot, front)} -> {w.where(b, bc)}"
        if any(w.peer_of((foot, c)) is not None for c in range(1, w.profile.connector_count + 1)):
            w.note(f"bring {where}: the foot is not lone")
            return False
        if w.peer_of(target) is not None or not w.profile.can_link(front, bc):
            w.note(f"bring {where}: the target is not a free face of the other gender")
            return False
        self._set_off(foot, target, route)
        w.note(f"bring {where}: the foot sets off")
        return True

    def _set_off(self, foot: int, target: End, route: tuple[int, ...]) -> None:
        b = target[0]
        cycle = self.world.cycle
        with self.physics.lock:  # the trip reads where the foot and the face are
            floor = self.sensors.tracker.reading(cycle)
        trip = Trip(
            floor,
            foot,
            target,
            model=self.physics.world.model,
            body=lambda: self.body_up(b),
            others=lambda: self.off_path(b, foot),
        )
        self.trips.append(Bringing(trip, route, cycle, cycle - 1))
        self.sync_docking()

    def squaring_route(self, module: int) -> tuple[int, ...]:
        """:func:`dh2rt.docking.squaring_route` in this world."""
        return docking.squaring_route(self.world.peer_of, self.world.profile, module)

    def body_up(self, module: int) -> list[int]:
        """:func:`dh2rt.docking.body_up` in this world."""
        return docking.body_up(self.world.peer_of, self.world.profile, module)

    def off_path(self, module: int, foot: int) -> list[int]:
        """:func:`dh2rt.docking.off_path` in this world."""
        return docking.off_path(self.world.peer_of, self.world.profile, module, self.world.topology.size, foot)

    def reach_other(self, module: int, connector: int, route: tuple[int, ...], foot: int) -> bool:
        """Begin bending ``module``'s ``connector`` to the front of ``foot``, a lone module that
        creeps towards it meanwhile (``PhysicsRun.reach_other`` with ``creep``); the joints
        that bend are those along ``route`` up ``module``'s robot. False (logged) if a
        connector is not free or the genders do not match."""
        w = self.world
        front = w.profile.connector_index("front")
        where = f"{w.where(module, connector)} -> {w.where(foot, front)}"
        if w.peer_of((module, connector)) is not None or w.peer_of((foot, front)) is not None:
            w.note(f"reach_dock {where}: a connector is not free")
            return False
        if not w.profile.can_link(connector, front):
            w.note(f"reach_dock {where}: both connectors are {w.profile.gender(connector)}")
            return False
        model = self.physics.world.model
        chain = Chain.to_other(model, (module, connector), route, w.peer_of, (foot, front), free_distance=True)
        cycle, started = w.cycle, time.perf_counter()
        with self.physics.lock:
            readings = self._read({m for m, _ in chain.joints}, {module}, floor=True)
        reach = Reach(chain, readings, DOCK_TOLERANCE_M, DOCK_TOLERANCE_DEG, start_cycle=cycle)
        plan_s, planned = time.perf_counter() - started, w.cycle
        creep = Creep(foot, model.connector(front).name)
        self.motions.append(Motion(reach, where, cycle, planned, plan_s, last=planned - 1, creep=creep))
        w.note(f"reach_dock {where}: bending; {w.where(foot, front)} creeps towards it")
        return True

    def _bring_again(self, foot: int, target: End) -> None:
        """A trip or a dock with a foot that came gave up: the foot sets off again from where it
        is, up to ``BRING_ATTEMPTS`` times in all (``PhysicsRun._bring_again``)."""
        tries = self.attempts.get(foot, 1)
        w = self.world
        if tries >= BRING_ATTEMPTS or not (w.running(foot) and w.running(target[0])):
            return
        self.attempts[foot] = tries + 1
        self._set_off(foot, target, self.squaring_route(target[0]))
        w.note(f"bring {w.where(foot, 1)} -> {w.where(*target)}: the foot tries again ({tries + 1})")

    def docking_modules(self) -> set[int]:
        """The modules whose docking motion is under way: what their ``docking`` sensor reads
        (``PhysicsRun.docking_modules``)."""
        return (
            {m.reach.chain.asking[0] for m in self.motions}
            | {b.trip.target[0] for b in self.trips}
            | {c.face[0] for c in self.clearings}
        )

    def sync_docking(self, modules: Sequence[int] | None = None) -> None:
        """Push the ``docking`` reading (1 while the module's docking motion is under way) to
        every module (or those of ``modules``) whose reading changed since it was last sent, if
        the program declares the sensor; a ``sense`` event's value for it holds instead."""
        w = self.world
        if not self.docking_declared:
            return
        busy = self.docking_modules()
        for m in range(w.topology.size) if modules is None else modules:
            value = int(m in busy)
            if not w.running(m) or "docking" in w.sensed.get(m, {}) or self.docking_sent.get(m) == value:
                continue
            self.docking_sent[m] = value
            w.send_readings(m, Readings({"docking": value}))

    def _read(
        self,
        joints: Iterable[int],
        infrared: Iterable[int],
        *,
        floor: bool = False,
        cycle: int | None = None,
        attitude: Iterable[int] = (),
    ) -> MotionReadings:
        """What the motions sense at world cycle ``cycle`` (default: now; the caller holds the
        physics lock)."""
        now = self.world.cycle if cycle is None else cycle
        return self.sensors.read(now, joints, infrared, floor=floor, attitude=attitude)

    # ------------------------------------------------------------ each world cycle

    def stepped_in(self, cycle: int) -> bool:
        """Every motion and trip under way has made its step of world cycle ``cycle``."""
        return (
            all(m.last >= cycle for m in self.motions)
            and all(b.last >= cycle for b in self.trips)
            and all(c.last >= cycle for c in self.clearings)
        )

    def step(self, cycle: int, due: bool = True) -> None:
        """Once per world cycle (``due``: the world's tick is in the moment of the cycle for it,
        just before the next cycle begins; a cycle whose moment the tick missed is stepped as
        soon as the next one has begun): advance every motion and every foot's trip by one
        step, send the modules they move the targets to hold, latch (or give up) the motions
        that are done, start the dock of every foot that arrived, and push the ``docking``
        readings."""

        def ready(last: int) -> bool:
            return cycle > last and (due or cycle > last + 1)

        moving = [motion for motion in self.motions if ready(motion.last)]
        trips = [b for b in self.trips if ready(b.last)]
        crawls = [c for c in self.clearings if ready(c.last)]
        if not moving and not trips and not crawls:
            self.sync_docking()
            return
        w = self.world
        holds: dict[int, dict[int, float]] = {}
        done: list[Motion] = []
        arrived: list[Bringing] = []
        cleared: list[CrawlingClear] = []
        front = w.profile.connector_index("front")
        world = self.physics.world
        # the IMUs of the modules whose faces a loop along the robot closes on (Reach.relative)
        tilted = [e[0] for m in moving if m.reach.tracked for e in (m.reach.chain.asking, m.reach.chain.target)]
        with self.physics.lock:
            readings = self._read(
                {m for motion in moving for m in motion.reach.modules},
                [m.reach.chain.asking[0] for m in moving] + [m.creep.module for m in moving if m.creep is not None],
                floor=bool(trips) or any(m.reach.chain.anchor is not None or m.reach.tracked for m in moving),
                cycle=cycle,
                attitude=tilted,
            )
            for motion in moving:
                motion.missed += cycle - motion.last - 1
                motion.last = cycle
                reach = motion.reach
                (a, ac), (b, bc) = reach.chain.asking, reach.chain.target
                if not all(w.running(m) for m in {a, b} | motion.modules):
                    self.motions.remove(motion)
                    w.note(f"reach_dock {motion.where}: a module of the chain stopped; motion abandoned")
                    continue
                if reach.asks_latch(readings) and world.aligned(a, ac, b, bc, DOCK_TOLERANCE_M, DOCK_TOLERANCE_DEG):
                    targets = reach.latch()
                else:
                    targets = reach.step(readings)
                if reach.done:
                    motion.contact = contact(world, cycle, (a, ac), (b, bc), reach.infrared(readings))
                    self.motions.remove(motion)
                    done.append(motion)
                    continue
                for m, dofs in targets.items():
                    holds.setdefault(m, {}).update(dofs)
                if motion.creep is not None:
                    d1, d2 = motion.creep.step(readings)
                    holds.setdefault(motion.creep.module, {}).update({0: d1, 1: d2})
            for bringing in trips:
                bringing.missed += cycle - bringing.last - 1
                bringing.last = cycle
                trip = bringing.trip
                b, _ = trip.target
                if not (w.running(trip.module) and w.running(b)):
                    self.trips.remove(bringing)
                    w.note(f"bring {w.where(trip.module, front)}: a module stopped; trip abandoned")
                    continue
                d1, d2 = trip.step(readings.floor)
                if not trip.done:
                    holds.setdefault(trip.module, {}).update({0: d1, 1: d2})
                    continue
                self.trips.remove(bringing)
                if not trip.arrived:
                    w.note(
                        f"bring {w.where(trip.module, front)}: the trip gave up after {trip.cycles} steps "
                        f"({trip.account()})"
                    )
                    self._bring_again(trip.module, trip.target)
                    continue
                arrived.append(bringing)
            for crawl in crawls:
                crawl.missed += cycle - crawl.last - 1
                crawl.last = cycle
                if not (w.running(crawl.face[0]) and w.running(crawl.foot[0])):
                    self.clearings.remove(crawl)
                    where = f"{w.where(*crawl.foot)} -> {w.where(*crawl.face)}"
                    w.note(f"assimilate {where}: a module stopped; crawl abandoned")
                    continue
                for m, dof1 in crawl.clearing.step().items():
                    holds.setdefault(m, {})[0] = dof1
                if crawl.clearing.done:
                    self.clearings.remove(crawl)
                    cleared.append(crawl)
        for motion in done:  # outside the lock: the latch takes it
            self._finish(motion, cycle)
        for bringing in arrived:  # outside the lock: the dock's Reach takes it around its reads
            self._arrived(bringing, cycle)
        for crawl in cleared:  # outside the lock: the trip takes it
            c = crawl.clearing
            outcome = "clear" if c.cleared else "still taken; the foot sets off anyway"
            w.note(
                f"{w.where(*crawl.face)}: crawled {c.gait_cycles} gait cycles ({crawl.missed} world cycles "
                f"missed), the spot {outcome}"
            )
            self._let_go(crawl.face, crawl.foot)
        self._send_holds(holds)
        self.sync_docking()

    def _arrived(self, bringing: Bringing, cycle: int) -> None:
        w, trip = self.world, bringing.trip
        front = w.profile.connector_index("front")
        s, lat, heading = trip.state()
        self.arrivals.append(Arrival(trip.module, trip.target, bringing.asked, cycle, trip.cycles, bringing.missed))
        w.note(
            f"bring {w.where(trip.module, front)}: arrived after {trip.cycles} steps, world cycles "
            f"{bringing.asked}-{cycle}, {bringing.missed} missed ({s * 100:+.1f} cm along, {lat * 100:+.1f} cm "
            f"aside, {math.degrees(heading):+.0f} deg; {trip.account()})"
        )
        b, bc = trip.target
        self.reach_other(b, bc, bringing.route, trip.module)

    def _finish(self, motion: Motion, cycle: int) -> None:
        w, reach = self.world, motion.reach
        (a, ac), (b, bc) = reach.chain.asking, reach.chain.target
        contact = motion.contact
        assert contact is not None
        how = (
            f"{contact.distance_m * 1000:.1f} mm, {contact.attitude_deg:.1f} deg apart; infrared "
            f"{contact.ir_mm:.1f} mm, {contact.ir_align_deg:.1f} deg"
        )
        took = f"{reach.cycles} steps, world cycles {motion.asked}-{cycle}, {motion.missed} missed"
        latched = reach.latched and w.latch(a, ac, b, bc)
        outcome = Outcome(motion.asked, motion.planned, cycle, reach.cycles, motion.missed, motion.plan_s, latched)
        self.outcomes.append(outcome)
        if latched:
            self.contacts.append(contact)
            w.note(f"{w.where(a, ac)} docked to {w.where(b, bc)} by motion after {took} ({how})")
            return
        self.failed.append(contact)
        w.note(f"reach_dock {motion.where} gave up after {took} ({how})")
        if motion.creep is not None:
            self._bring_again(b, (a, ac))

    @property
    def busy(self) -> bool:
        """A docking motion or a foot's trip is under way."""
        return bool(self.motions or self.trips or self.clearings)

    def owned(self) -> set[int]:
        """The modules whose joints a motion or a trip under way holds."""
        return (
            {m for motion in self.motions for m in motion.modules}
            | {b.trip.module for b in self.trips}
            | {m for c in self.clearings for m in c.clearing.body}
        )

    def _send_holds(self, holds: dict[int, dict[int, float]]) -> None:
        """Tell the moving modules what to hold; modules no motion or trip holds any more get
        their joints back (an empty hold); those of one not stepped this time keep theirs."""
        owned = self.owned()
        for m in [m for m in self.holding if m not in holds and m not in owned]:
            del self.holding[m]
            self.world.hold(m, {})
        for m, dofs in holds.items():
            rounded = {dof: round(v, 2) for dof, v in dofs.items()}
            if self.holding.get(m) != rounded:
                self.holding[m] = rounded
                self.world.hold(m, rounded)
