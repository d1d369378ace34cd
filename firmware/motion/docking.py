"""The docking sequence, written once: who moves, in what order, and what comes of it.

The motions themselves are :class:`firmware.motion.reach.Reach` (a chain bends its face onto
another), :class:`firmware.motion.crawl.Trip` and :class:`~firmware.motion.crawl.Creep` (a
released foot walks to a face, then creeps the last centimetres) and
:class:`firmware.motion.clearing.Clearing` (a robot crawls clear of a module lying on the spot
behind a face). :class:`Docking` carries the sequence around them for every docking under way
in one robot, the same for every owner (the physics runner ``sim.runner.PhysicsRun``, the
loop's ``hil.reach_loop.LoopReaches``):

- ``reach_dock`` (:meth:`Docking.start_reach`): a chain along a route bends its face onto a
  face of the module the route leads to;
- ``reach_and_dock`` (:meth:`Docking.assimilate`): [crawl clear] -> the foot lets go
  (``release``) -> it comes by its own gaits (:meth:`Docking.bring`) -> the last modules up the
  asking robot square its face while the foot creeps (:meth:`Docking.reach_other`) -> the
  latch is asked and closes, or is refused -> linked, or the foot sets off again, up to
  :data:`BRING_ATTEMPTS` times in all, then gives up;
- a module that dies under way ends what it was part of (abandoned, logged).

On a robot of modules the sequence splits between two modules (docs/hil.md, *`reach_and_dock`
in the modules*): the asker runs everything here but the foot's trip and creep, which the
released foot, having no link, runs itself (:class:`firmware.motion.foot.Foot`, told its trip by
a SET_OFF frame); both build the trip with :func:`firmware.motion.foot.trip_to` and count
attempts by one rule. In one process (and in the world's loop) this class steps both parts.

Sans-IO: no simulator, socket, clock or file. What it reads and asks for goes through its
world (:class:`LatchWorld`: the links and who runs, :class:`dh2rt.docking.DockingWorld`; the
latch: ``aligned``, does it close now, and :meth:`LatchWorld.latch`, closed and the link
negotiated, or refused) and its owner (:class:`DockingOwner`: the readings a module has on a
robot, :meth:`DockingOwner.sense` given the :class:`Needs`: joint angles, infrared pairs, the
overhead tracker, the IMU, :mod:`firmware.motion.readings`; and what became of each motion,
:meth:`DockingOwner.ended`, for the owner's records and log). :meth:`Docking.step`, once a
control cycle, returns the joint targets the moving modules hold (module -> {DOF index:
degrees}); the owner writes them (to the joints, or as :class:`firmware.control.Hold`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from dh2rt import docking
from dh2rt.docking import DockingWorld, End
from dh2rt.profile import Profile
from firmware.motion.body import ConroModel
from firmware.motion.clearing import Clearing, spot_taken
from firmware.motion.crawl import DIAGONAL_M, Creep, Trip
from firmware.motion.foot import ATTEMPTS, trip_to
from firmware.motion.kinematics import Chain
from firmware.motion.reach import DEFAULT_TIMEOUT, Reach
from firmware.motion.readings import Readings
from firmware.motion.underway import Arrival, Bringing, CrawlingClear, Motion, Needs, Outcome, Targets

#: How many times a foot that comes to a face (:meth:`Docking.bring`) sets off before it gives
#: up: a trip or a dock that gives up sends it round again from where it is. A foot left lying
#: apart cannot ask again (it has no link to send RCT through), so without the retry a foot
#: whose trip gave up was lost and the snake never formed (seed 1, the first winner killed on
#: its trip: the next foot pressed against the dead one for 1,700 cycles, before the trip
#: steered round a module lying beside the robot).
BRING_ATTEMPTS = ATTEMPTS
#: How far apart two connectors may be for the latch to close.
DOCK_TOLERANCE_M = 0.02
DOCK_TOLERANCE_DEG = 20.0


class LatchWorld(DockingWorld, Protocol):
    """The world the sequence docks in: its links and who runs (:class:`DockingWorld`;
    ``aligned``: whether a latch asked for closes now) and the latch itself."""

    def latch(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        """Close the latch and link the two faces; False (logged) if either is refused."""
        ...


class DockingOwner(Protocol):
    """Who steps the sequence: the cycle, the readings, the records."""

    @property
    def now(self) -> int:
        """The control cycle now."""
        ...

    def sense(self, cycle: int, needs: Needs) -> Readings:
        """The readings of control cycle ``cycle`` that ``needs`` names."""
        ...

    def ended(self, motion: Motion, linked: bool, readings: Readings) -> None:
        """A reach ended, linked or not (``readings``: its last cycle's): the owner's record."""
        ...


@dataclass
class Options:
    """How the sequence plans (each a measured choice; the benchmarks compare them)."""

    tolerance_m: float = DOCK_TOLERANCE_M
    tolerance_deg: float = DOCK_TOLERANCE_DEG
    #: How far before its line's end a foot's trip starts across (firmware.motion.crawl.DIAGONAL_M;
    #: 0: at the end; benchmarks/bench_trips.py compares the two).
    trip_diagonal_m: float = DIAGONAL_M
    #: Whether a dock with a creeping foot leaves the distance to the foot
    #: (firmware.motion.kinematics.Chain.free_distance; False: STANDOFF_M in front of it).
    free_distance: bool = True
    #: Whether a chain along the robot closes its loop on the tracker's view of both faces'
    #: modules (firmware.motion.reach.Reach.tracked).
    closed_by_tracker: bool = True
    attempts: int = BRING_ATTEMPTS


@dataclass
class Docking:
    """Every docking under way in one robot, stepped once a control cycle (module docs)."""

    world: LatchWorld
    owner: DockingOwner
    model: ConroModel
    profile: Profile
    #: every module's name, by index (a foot's trip steers round those off its path)
    names: Sequence[str]
    options: Options = field(default_factory=Options)
    #: The owner's clock (seconds), for :attr:`Motion.plan_s` only; the motions never read it.
    clock: Callable[[], float] = lambda: 0.0
    motions: list[Motion] = field(default_factory=list)
    trips: list[Bringing] = field(default_factory=list)
    clearings: list[CrawlingClear] = field(default_factory=list)
    #: Trips that ended, arrived or not (their ``spent`` and ``turning`` say where the cycles went).
    trips_done: list[Trip] = field(default_factory=list)
    arrivals: list[Arrival] = field(default_factory=list)
    outcomes: list[Outcome] = field(default_factory=list)
    #: Times each foot brought so far has set off (see :attr:`Options.attempts`).
    attempts: dict[int, int] = field(default_factory=dict)

    @property
    def size(self) -> int:
        """Modules in the world."""
        return len(self.names)

    # ------------------------------------------------------------ what is under way

    @property
    def busy(self) -> bool:
        """A reach, a trip or a crawl is under way."""
        return bool(self.motions or self.trips or self.clearings)

    def docking_modules(self) -> set[int]:
        """The modules whose docking is under way: what their ``docking`` sensor reads."""
        return (
            {m.reach.chain.asking[0] for m in self.motions}
            | {b.trip.target[0] for b in self.trips}
            | {c.face[0] for c in self.clearings}
        )

    def owned(self) -> set[int]:
        """The modules whose joints a motion, a trip or a crawl under way holds."""
        return (
            {m for motion in self.motions for m in motion.modules}
            | {b.trip.module for b in self.trips}
            | {m for c in self.clearings for m in c.clearing.body}
        )

    def stepped_in(self, cycle: int) -> bool:
        """Everything under way has made its step of control cycle ``cycle``."""
        entries: list[Motion | Bringing | CrawlingClear] = [*self.motions, *self.trips, *self.clearings]
        return all(e.last >= cycle for e in entries)

    # ------------------------------------------------------------ the rules of the world

    def _front(self) -> int:
        return self.profile.connector_index("front")

    def body_up(self, module: int) -> list[int]:
        """:func:`dh2rt.docking.body_up` in the world's links."""
        return docking.body_up(self.world.peer_of, self.profile, module)

    def off_path(self, module: int, foot: int) -> list[int]:
        """:func:`dh2rt.docking.off_path` in the world's links."""
        return docking.off_path(self.world.peer_of, self.profile, module, self.size, foot)

    def squaring_route(self, module: int) -> tuple[int, ...]:
        """:func:`dh2rt.docking.squaring_route` in the world's links."""
        return docking.squaring_route(self.world.peer_of, self.profile, module)

    def spot_taken(self, face: End, foot: int) -> int | None:
        """:func:`firmware.motion.clearing.spot_taken` by the overhead tracker now."""
        o = self.world
        floor = self.owner.sense(self.owner.now, Needs(floor=True)).floor
        return spot_taken(floor, self.model, o.peer_of, self.profile, self.size, face, foot)

    # ------------------------------------------------------------ requests

    def start_reach(self, module: int, connector: int, route: Sequence[int], target_conn: int) -> bool:
        """``reach_dock``: begin bending ``module``'s ``connector`` to ``target_conn`` of the
        module at the end of ``route``; False (logged) if the rules say no or a motion already
        holds one of the chain's joints."""
        o = self.world
        target = docking.reach_dock_target(o, module, connector, route, target_conn)
        if target is None:
            return False
        _, where = target
        if not self.profile.can_link(connector, target_conn):
            o.note(f"reach_dock {where}: both connectors are {self.profile.gender(connector)}")
            return False
        chain = Chain.along(self.model, (module, connector), tuple(route), o.peer_of, target_conn)
        if any(m in motion.modules for motion in self.motions for m, _ in chain.joints):
            o.note(f"reach_dock {where}: another docking motion owns part of the chain")
            return False
        motion = self._plan(chain, where, Needs(frozenset(m for m, _ in chain.joints), (module,)), DEFAULT_TIMEOUT)
        modules = sorted(motion.reach.modules)
        o.note(
            f"reach_dock {where}: bending ({len(chain.joints)} joints of modules {modules}; asked at cycle "
            f"{motion.asked}, planned in {motion.plan_s:.2f} s)"
        )
        return True

    def _plan(self, chain: Chain, where: str, needs: Needs, timeout: int, creep: Creep | None = None) -> Motion:
        asked, started = self.owner.now, self.clock()
        readings = self.owner.sense(asked, needs)
        opts = self.options
        reach = Reach(
            chain,
            readings,
            opts.tolerance_m,
            opts.tolerance_deg,
            timeout=timeout,
            start_cycle=asked,
            tracked=opts.closed_by_tracker,
        )
        plan_s, planned = self.clock() - started, self.owner.now
        motion = Motion(reach, where, asked, planned, plan_s, last=planned - 1, creep=creep)
        self.motions.append(motion)
        return motion

    def reach_other(
        self,
        module: int,
        connector: int,
        route: Sequence[int],
        target: End,
        *,
        timeout: int = DEFAULT_TIMEOUT,
        creep: bool = False,
        creeps_itself: bool = False,
    ) -> bool:
        """Begin bending ``module``'s ``connector`` to ``target``, a face on a body no route
        reaches (a module lying apart); the joints that bend are those along ``route`` up
        ``module``'s own robot. With ``creep`` the target is a lone module whose face is its
        front: it creeps towards the asking face meanwhile, stepped here; with
        ``creeps_itself`` it creeps on its own (a released foot running its own part,
        firmware.motion.foot): planned the same, nothing stepped for it. False (logged) if a
        connector is not free or the genders do not match."""
        o = self.world
        b, bc = target
        where = f"{o.where(module, connector)} -> {o.where(b, bc)}"
        if o.peer_of((module, connector)) is not None or o.peer_of(target) is not None:
            o.note(f"reach_dock {where}: a connector is not free")
            return False
        if not self.profile.can_link(connector, bc):
            o.note(f"reach_dock {where}: both connectors are {self.profile.gender(connector)}")
            return False
        free = (creep or creeps_itself) and self.options.free_distance  # the creeping foot closes the distance
        chain = Chain.to_other(self.model, (module, connector), tuple(route), o.peer_of, target, free_distance=free)
        crept = Creep(b, self.model.connector(bc).name) if creep else None
        needs = Needs(frozenset(m for m, _ in chain.joints), (module,), floor=True)
        self._plan(chain, where, needs, timeout, crept)
        o.note(
            f"reach_dock {where}: bending" + (f"; {o.where(b, bc)} creeps towards it" if creep or creeps_itself else "")
        )
        return True

    def assimilate(self, module: int, connector: int, route: Sequence[int]) -> bool:
        """``reach_and_dock(connector, route)`` (legs to snake's ``dock_tail_to_foot``): the
        foot at the end of ``route`` lets go of the body at its front and comes to ``module``'s
        ``connector`` by its own gaits (:meth:`bring`), after the robot crawled clear of a
        module lying on the spot behind the face. False (logged) if the rules say no: the route
        leads nowhere, the foot does not hang by its front, or a foot is already on its way."""
        o = self.world
        target = docking.reach_target(o, module, connector, route)
        if target is None:
            return False
        foot, at = target
        where = f"{o.where(module, connector)} -> {o.where(foot, at)}"
        if at != self._front():
            o.note(f"assimilate {where}: the foot does not hang by its front")
            return False
        face = (module, connector)
        if (
            any(b.trip.target == face for b in self.trips)
            or any(m.reach.chain.asking == face for m in self.motions)
            or any(c.face == face for c in self.clearings)
        ):
            o.note(f"assimilate {where}: a foot is already on its way there")
            return False
        lying = self.spot_taken(face, foot)
        if lying is None:
            return self._let_go(face, target)
        body = self.body_up(module)[::-1]
        clearing = Clearing(body, lambda: self.spot_taken(face, foot) is not None)
        self.clearings.append(CrawlingClear(clearing, face, target, self.owner.now, self.owner.now - 1))
        o.note(f"assimilate {where}: {self.names[lying]} lies behind {o.where(*face)}; the robot crawls clear first")
        return True

    def _let_go(self, face: End, foot_end: End) -> bool:
        """The foot lets go of the body at ``foot_end`` and comes to ``face`` (:meth:`bring`)."""
        docking.release(self.world, *foot_end)
        return self.bring(foot_end[0], face, self.squaring_route(face[0]))

    def bring(self, foot: int, target: End, route: tuple[int, ...]) -> bool:
        """A released ``foot`` (a lone module) comes to ``target``, a free face of another body:
        a :class:`firmware.motion.crawl.Trip` to just behind it, then ``target``'s module bends
        along ``route`` up its robot while the foot creeps (:meth:`reach_other`). False (logged)
        if the foot is not lone or the face not free or of the front's gender."""
        o, front = self.world, self._front()
        b, bc = target
        where = f"{o.where(foot, front)} -> {o.where(b, bc)}"
        if any(o.peer_of((foot, c)) is not None for c in range(1, self.profile.connector_count + 1)):
            o.note(f"bring {where}: the foot is not lone")
            return False
        if o.peer_of(target) is not None or not self.profile.can_link(front, bc):
            o.note(f"bring {where}: the target is not a free face of the other gender")
            return False
        self._set_off(foot, target, route)
        self.attempts[foot] = 1
        o.note(f"bring {where}: the foot sets off")
        return True

    def _set_off(self, foot: int, target: End, route: tuple[int, ...]) -> None:
        b, cycle = target[0], self.owner.now
        trip = trip_to(
            self.owner.sense(cycle, Needs(floor=True)).floor,
            foot,
            target,
            model=self.model,
            body=lambda: self.body_up(b),
            others=lambda: self.off_path(b, foot),
            diagonal_m=self.options.trip_diagonal_m,
        )
        self.trips.append(Bringing(trip, route, cycle, cycle - 1))

    def _bring_again(self, foot: int, target: End) -> None:
        """A trip or a dock with a foot that came gave up: the foot sets off again from where it
        is, up to :attr:`Options.attempts` times in all."""
        o = self.world
        tries = self.attempts.get(foot)
        if tries is None or tries >= self.options.attempts or not (o.running(foot) and o.running(target[0])):
            return  # not a foot that came, or its last try
        self.attempts[foot] = tries + 1
        self._set_off(foot, target, self.squaring_route(target[0]))
        o.note(f"bring {o.where(foot, self._front())} -> {o.where(*target)}: the foot tries again ({tries + 1})")

    # ------------------------------------------------------------ each control cycle

    def step(self, cycle: int, due: bool = True) -> Targets:
        """Advance everything under way by its step of control cycle ``cycle``; the joint
        targets the modules they move hold. ``due``: the owner is in the moment for ``cycle``
        (an owner that came late steps a cycle it missed as soon as the next one began)."""

        def ready(last: int) -> bool:
            return cycle > last and (due or cycle > last + 1)

        held: Targets = {}
        moving = [m for m in self.motions if ready(m.last)]
        if moving:
            self._step_reaches(cycle, moving, held)
        trips = [b for b in self.trips if ready(b.last)]
        if trips:
            self._step_trips(cycle, trips, held)
        crawls = [c for c in self.clearings if ready(c.last)]
        if crawls:
            self._step_clearings(cycle, crawls, held)
        return held

    def _needs(self, moving: Iterable[Motion]) -> Needs:
        moving = list(moving)
        return Needs(
            frozenset(m for motion in moving for m in motion.reach.modules),
            tuple(m.reach.chain.asking[0] for m in moving) + tuple(m.creep.module for m in moving if m.creep),
            floor=any(m.reach.chain.anchor is not None or m.reach.tracked for m in moving),
            attitude=tuple(
                e[0] for m in moving if m.reach.tracked for e in (m.reach.chain.asking, m.reach.chain.target)
            ),
        )

    def _step_reaches(self, cycle: int, moving: list[Motion], held: Targets) -> None:
        o = self.world
        readings = self.owner.sense(cycle, self._needs(moving))
        for motion in moving:
            motion.missed += cycle - motion.last - 1
            motion.last = cycle
            reach = motion.reach
            (a, ac), (b, bc) = reach.chain.asking, reach.chain.target
            if not all(o.running(m) for m in {a, b} | motion.modules):
                self.motions.remove(motion)
                o.note(f"reach_dock {motion.where}: a module of the chain stopped; motion abandoned")
                continue
            closes = reach.asks_latch(readings) and o.aligned(a, ac, b, bc)  # the latch closes now
            targets = reach.latch() if closes else reach.step(readings)
            if reach.done:
                self.motions.remove(motion)
                self._finish(motion, cycle, readings)
                continue
            for m, dofs in targets.items():
                held.setdefault(m, {}).update(dofs)
            if motion.creep is not None:
                d1, d2 = motion.creep.step(readings)
                held.setdefault(motion.creep.module, {}).update({0: d1, 1: d2})

    def _finish(self, motion: Motion, cycle: int, readings: Readings) -> None:
        o, reach = self.world, motion.reach
        (a, ac), (b, bc) = reach.chain.asking, reach.chain.target
        linked = reach.latched and o.latch(a, ac, b, bc)
        self.outcomes.append(
            Outcome(motion.asked, motion.planned, cycle, reach.cycles, motion.missed, motion.plan_s, linked)
        )
        self.owner.ended(motion, linked, readings)
        if not linked and motion.creep is not None:
            self._bring_again(b, (a, ac))

    def _step_trips(self, cycle: int, trips: list[Bringing], held: Targets) -> None:
        o, front = self.world, self._front()
        floor = self.owner.sense(cycle, Needs(floor=True)).floor
        for bringing in trips:
            bringing.missed += cycle - bringing.last - 1
            bringing.last = cycle
            trip = bringing.trip
            b, bc = trip.target
            if not (o.running(trip.module) and o.running(b)):
                self.trips.remove(bringing)
                o.note(f"bring {o.where(trip.module, front)}: a module stopped; trip abandoned")
                continue
            d1, d2 = trip.step(floor)
            if not trip.done:
                held.setdefault(trip.module, {}).update({0: d1, 1: d2})
                continue
            self.trips.remove(bringing)
            self.trips_done.append(trip)
            if not trip.arrived:
                o.note(
                    f"bring {o.where(trip.module, front)}: the trip gave up after {trip.cycles} cycles "
                    f"({trip.account()})"
                )
                self._bring_again(trip.module, trip.target)
                continue
            self.arrivals.append(Arrival(trip.module, trip.target, bringing.asked, cycle, trip.cycles, bringing.missed))
            s, lat, heading = trip.state()
            o.note(
                f"bring {o.where(trip.module, front)}: arrived after {trip.cycles} cycles (cycles {bringing.asked}-"
                f"{cycle}, {bringing.missed} missed; {s * 100:+.1f} cm along, {lat * 100:+.1f} cm aside, "
                f"{math.degrees(heading):+.0f} deg; {trip.account()})"
            )
            self.reach_other(b, bc, bringing.route, (trip.module, front), creep=True)

    def _step_clearings(self, cycle: int, crawls: list[CrawlingClear], held: Targets) -> None:
        o = self.world
        for crawl in crawls:
            crawl.missed += cycle - crawl.last - 1
            crawl.last = cycle
            if not (o.running(crawl.face[0]) and o.running(crawl.foot[0])):
                self.clearings.remove(crawl)
                o.note(
                    f"assimilate {o.where(*crawl.foot)} -> {o.where(*crawl.face)}: a module stopped; crawl abandoned"
                )
                continue
            for m, dof1 in crawl.clearing.step().items():
                held.setdefault(m, {})[0] = dof1
            if not crawl.clearing.done:
                continue
            self.clearings.remove(crawl)
            c = crawl.clearing
            outcome = "clear" if c.cleared else "still taken; the foot sets off anyway"
            o.note(
                f"{o.where(*crawl.face)}: crawled {c.gait_cycles} gait cycles ({crawl.missed} world cycles "
                f"missed), the spot {outcome}"
            )
            self._let_go(crawl.face, crawl.foot)
