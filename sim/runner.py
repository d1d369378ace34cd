"""DH2 robots in physics: the in-process engines drive the PyBullet world's joints.

Each control cycle: every running module's sensors are filled from its body, the robot takes
one lockstep cycle (hormones cross one link), every module whose DOF1/DOF2 changed commands
its driver, and the world advances ``steps_per_cycle`` physics steps.

Sensors: the sensors a program declares that the profile lists and physics provides
(:mod:`sim.sensors`: IMU, infrared, ground contact, joints) are read once a cycle, rounded
and clamped to the profile's range; the others are left alone. A ``sense`` event holds its
value for that module's sensor: physics no longer fills it.

The drivers are the PyBullet stand-ins by default; any :class:`drivers.base.ModuleDriver`
can take their place (the Dynamixel driver talking to a servo emulator whose joints are these
same PyBullet joints runs the full firmware path).

Docking follows the world: a ``cut`` undocks both the logical link and the physical latch;
a ``dock`` event stays logical only if the two connectors are physically aligned within
tolerance, and is undone otherwise. A native action's ``reach_dock`` (dock my connector to a
connector of the module a route leads to) is carried out by the modules' own motion
(:class:`firmware.motion.reach.Reach`, fed each cycle with what the modules sense:
:class:`sim.motion_readings.MotionSensors`): the chain of modules along the route bends,
aligns and approaches, its joints owned by the motion until the latch closes (the motion asks
for it when the asking connector's infrared pair sees the target within the tolerance below;
the latch closes when physics has the faces aligned within it) or the motion gives up. Every link
formed so is recorded in :attr:`PhysicsRun.contacts` with both faces' world poses and errors
at that moment. ``release`` cuts a module's link at one of its connectors. ``reach_and_dock``
(legs to snake's ``dock_tail_to_foot``) is carried out by motion as well
(:meth:`PhysicsRun.assimilate`): the foot lets go of the body, comes to the asking face by its
own gaits (:class:`firmware.motion.crawl.Trip`, steering by the overhead tracker:
:class:`sim.tracker.OverheadTracker`) and the two dock while it creeps; the asking module's
``docking`` sensor reads 1 meanwhile. If a module lies apart on the spot behind the face (a
foot that died docking; the tracker says where it lies), the robot crawls clear of it first
(:class:`firmware.motion.clearing.Clearing`).

``dh2rt run PROGRAM --sim pybullet`` runs it through :mod:`sim.command`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence

from dh2rt import docking
from dh2rt.docking import End
from dh2rt.events import Event
from dh2rt.robot import Robot
from drivers.base import ModuleDriver
from firmware.motion.clearing import Clearing, spot_taken
from firmware.motion.crawl import DIAGONAL_M, Creep, Trip
from firmware.motion.kinematics import Chain
from firmware.motion.reach import Reach
from firmware.motion.readings import Readings
from sim.motion_readings import Contact, MotionSensors, contact
from sim.record import Sample
from sim.sensors import PhysicsSensors
from sim.tracker import OverheadTracker
from sim.world import World

#: Physics steps per DH2 control cycle: 12 steps at 240 Hz = 50 ms per cycle.
STEPS_PER_CYCLE = 12
#: How many times a foot that comes to a face (PhysicsRun.bring) sets off before it gives up:
#: a trip or a dock that gives up sends it round again from where it is. A foot left lying
#: apart cannot ask again (it has no link to send RCT through), so without the trip's
#: retry a foot whose trip gave up was lost and the snake never formed (seed 1, the first
#: winner killed on its trip: the next foot pressed against the dead one for 1,700 cycles,
#: before the trip steered round a module lying beside the robot).
BRING_ATTEMPTS = 3
#: The overhead tracker's sensors (dh2rt.profile's table), filled from sim.tracker.
FLOOR_SENSORS = ("floor_x", "floor_y", "floor_heading")
#: How far apart two connectors may be for a logical dock to hold physically.
DOCK_TOLERANCE_M = 0.02
DOCK_TOLERANCE_DEG = 20.0


class PhysicsRun:
    """A robot whose modules' joints live in a PyBullet world."""

    def __init__(
        self,
        robot: Robot,
        *,
        world: World | None = None,
        drivers: Sequence[ModuleDriver] | None = None,
        steps_per_cycle: int = STEPS_PER_CYCLE,
        gui: bool = False,
        settle: Callable[[], None] | None = None,
        tracker: OverheadTracker | None = None,
    ) -> None:
        self.robot = robot
        self.world = world or World(robot.topology, gui=gui, seed=robot.seed)
        self.drivers: list[ModuleDriver] = (
            list(drivers) if drivers else [self.world.driver(m) for m in range(robot.size)]
        )
        self.steps_per_cycle = steps_per_cycle
        #: Called after the joints are commanded and before physics steps: a driver whose
        #: writes are not acknowledged (Dynamixel SYNC_WRITE) can make sure they landed.
        self.settle = settle
        self._sent: list[tuple[float, float] | None] = [None] * robot.size
        program, profile = robot.program, robot.profile
        filled = [n for n in program.sensor_names if n in profile.sensor_names]
        #: The physics sensors this run fills: those the program reads.
        self.sensors = PhysicsSensors(self.world, filled)
        #: (name, the engine's sensor slot, its spec) of each filled sensor
        self._sensor_slots = [(n, program.sensor_names.index(n), profile.sensor(n)) for n in self.sensors.names]
        self.start = self.world.centroid()
        self.samples: list[Sample] = []
        self.log = robot.log
        # reach_and_dock (legs to snake's dock_tail_to_foot): the foot lets go of the body and
        # comes to the tail by its own gaits, and they dock by motion (see docs/physics.md,
        # Docking by motion, for why the tail cannot bend to a foot with this profile's genders)
        robot.effect_handlers["reach_and_dock"] = lambda _r, m, args: self._assimilate_effect(m, args)
        robot.effect_handlers["reach_dock"] = lambda _r, m, args: self.start_reach(m, *args)
        robot.effect_handlers["release"] = lambda _r, m, args: self.release(m, *args)
        #: What the docking motions read: the chain's joint angles, the infrared pairs (every
        #: connector's), and the overhead tracker (exact unless ``tracker`` says otherwise).
        self.motion_sensors = MotionSensors(self.world, tracker)
        #: Docking motions under way.
        self.reaches: list[Reach] = []
        #: The lone modules that creep towards a docking motion's face, by the motion's id.
        self.creeps: dict[int, Creep] = {}
        #: Released feet on their way to a face, each with the route the dock will bend.
        self.trips: list[tuple[Trip, tuple[int, ...]]] = []
        #: Trips that ended, arrived or not (their ``spent`` and ``turning`` say where the
        #: cycles went).
        self.trips_done: list[Trip] = []
        #: Robots crawling clear of a body on the spot before a foot sets off: each with the
        #: face the foot will come to and the foot (still on the body) with its connector.
        self.clearings: list[tuple[Clearing, End, End]] = []
        #: Times each foot brought so far has set off (see BRING_ATTEMPTS).
        self.attempts: dict[int, int] = {}
        #: How far before its line's end a foot's trip starts across (firmware.motion.crawl.DIAGONAL_M; 0:
        #: at the end, the trip before; benchmarks/bench_trips.py compares the two).
        self.trip_diagonal_m = DIAGONAL_M
        #: Whether a dock with a creeping foot leaves the distance to the foot
        #: (firmware.motion.kinematics.Chain.free_distance; False: the plan puts the face STANDOFF_M in front
        #: of the foot, the dock before; benchmarks/bench_legs_to_snake.py compares the two).
        self.dock_free_distance = True
        #: ORACLE, for measuring only: the docking motions read their faces' relative pose from
        #: the world's exact state (as before they were sans-IO) instead of the chain's
        #: kinematics of its measured angles and the tracker (firmware.motion.readings.Readings.oracle).
        self.oracle_poses = False
        #: Whether a docking chain along the robot closes its loop on the overhead tracker's
        #: view of both faces' modules (firmware.motion.reach.Reach.tracked; False: on the
        #: chain's kinematics of its measured angles alone, which the docks' give defeats:
        #: docs/physics.md, *What each step reads*).
        self.closed_by_tracker = True
        #: Every link formed by a docking motion, and every motion that gave up.
        self.contacts: list[Contact] = []
        self.failed: list[Contact] = []
        #: (name, the engine's slot, its spec) of each overhead tracker sensor the program reads
        self._floor_slots = [
            (n, program.sensor_names.index(n), profile.sensor(n))
            for n in FLOOR_SENSORS
            if n in program.sensor_names and n in profile.sensor_names
        ]
        #: The engines' slot of the ``docking`` sensor, if the program declares it.
        self._docking_slot = (
            program.sensor_names.index("docking")
            if "docking" in program.sensor_names and "docking" in profile.sensor_names
            else None
        )

    # ------------------------------------------------------------ the docking world

    def peer_of(self, end: End) -> End | None:
        return self.robot.peer_of(end)

    def running(self, module: int) -> bool:
        return self.robot.alive(module)

    def aligned(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        return self.world.aligned(a, a_conn, b, b_conn, DOCK_TOLERANCE_M, DOCK_TOLERANCE_DEG)

    def schedule(self, cycles_from_now: int, action: Callable[[], None]) -> None:
        self.robot.schedule(cycles_from_now, action)

    def where(self, module: int, connector: int) -> str:
        return self.robot.where(module, connector)

    def note(self, message: str) -> None:
        self.robot.note(message)

    def cut(self, module: int, connector: int) -> None:
        """Undock the latch and the logical link."""
        self.robot.cut(module, connector)
        self.world.undock(module, connector)

    def dock(self, a: int, a_conn: int, b: int, b_conn: int) -> None:
        """Dock logically, then latch; a latch physics refuses (not aligned) undoes the link."""
        self.robot.dock(a, a_conn, b, b_conn)
        if not self.world.dock(a, a_conn, b, b_conn, tolerance_m=DOCK_TOLERANCE_M, tolerance_deg=DOCK_TOLERANCE_DEG):
            self.robot.cut(a, a_conn)
            self.note("dock refused by physics: connectors not aligned")

    # ------------------------------------------------------------ docking by motion

    def start_reach(self, module: int, connector: int, route: tuple[int, ...], target_conn: int) -> None:
        """Begin bending ``module``'s ``connector`` to ``target_conn`` of the module at the
        end of ``route`` (refused, logged, if the rules say no or a motion already owns one
        of the chain's joints)."""
        target = docking.reach_dock_target(self, module, connector, route, target_conn)
        if target is None:
            return
        _, where = target
        if not self.robot.profile.can_link(connector, target_conn):
            self.note(f"reach_dock {where}: both connectors are {self.robot.profile.gender(connector)}")
            return
        chain = Chain.along(self.world.model, (module, connector), route, self.peer_of, target_conn)
        busy = {m for r in self.reaches for m, _ in r.chain.joints}
        if busy & {m for m, _ in chain.joints}:
            self.note(f"reach_dock {where}: another docking motion owns part of the chain")
            return
        readings = self._readings(joints={m for m, _ in chain.joints}, infrared={module})
        cycle, tracked = self.robot.cycle, self.closed_by_tracker
        self.reaches.append(
            Reach(chain, readings, DOCK_TOLERANCE_M, DOCK_TOLERANCE_DEG, start_cycle=cycle, tracked=tracked)
        )
        self.note(f"reach_dock {where}: bending")

    def reach_other(
        self,
        module: int,
        connector: int,
        route: tuple[int, ...],
        target: End,
        timeout: int = 400,
        *,
        creep: bool = False,
    ) -> bool:
        """Begin bending ``module``'s ``connector`` to ``target`` (module, connector), a face on
        a body that no route reaches (a module lying apart); the joints that move are those
        along ``route`` from ``module`` up its own robot. With ``creep`` the target is a lone
        module whose face is the front: it creeps towards the asking face meanwhile
        (:class:`firmware.motion.crawl.Creep`, for a face beyond the straight chain's reach). False
        (logged) if the rules say no."""
        b, bc = target
        where = f"{self.where(module, connector)} -> {self.where(b, bc)}"
        if self.peer_of((module, connector)) is not None or self.peer_of((b, bc)) is not None:
            self.note(f"reach_dock {where}: a connector is not free")
            return False
        if not self.robot.profile.can_link(connector, bc):
            self.note(f"reach_dock {where}: both connectors are {self.robot.profile.gender(connector)}")
            return False
        free = creep and self.dock_free_distance  # the creeping foot closes the distance
        chain = Chain.to_other(self.world.model, (module, connector), route, self.peer_of, target, free_distance=free)
        readings = self._readings(joints={m for m, _ in chain.joints}, infrared={module}, floor=True)
        reach = Reach(
            chain, readings, DOCK_TOLERANCE_M, DOCK_TOLERANCE_DEG, timeout=timeout, start_cycle=self.robot.cycle
        )
        self.reaches.append(reach)
        if creep:
            self.creeps[id(reach)] = Creep(b, self.world.model.connector(bc).name)
        self.note(f"reach_dock {where}: bending" + (f"; {self.robot.where(b, bc)} creeps towards it" if creep else ""))
        return True

    def bring(self, foot: int, target: End, route: tuple[int, ...]) -> bool:
        """A released ``foot`` (a lone module) comes to ``target``, a free face of another body
        (the tail's back), and the two dock: :class:`firmware.motion.crawl.Trip` takes the foot to just
        behind the face, then ``target``'s module bends along ``route`` up its own robot while
        the foot creeps (:meth:`reach_other` with ``creep``). False (logged) if the rules say
        no."""
        front = self.robot.profile.connector_index("front")
        b, bc = target
        where = f"{self.where(foot, front)} -> {self.where(b, bc)}"
        if any(self.peer_of((foot, c)) is not None for c in range(1, len(self.robot.profile.connectors) + 1)):
            self.note(f"bring {where}: the foot is not lone")
            return False
        if self.peer_of(target) is not None or not self.robot.profile.can_link(front, bc):
            self.note(f"bring {where}: the target is not a free face of the other gender")
            return False
        self.trips.append((self._trip(foot, target), route))
        self.attempts[foot] = 1
        self.note(f"bring {where}: the foot sets off")
        return True

    def bring_home(self, foot: int, target: End, route: tuple[int, ...], budget: int) -> int:
        """One round of legs to snake driven from Python: ``foot`` lets go of the body at its
        front (:meth:`release`) and is brought to ``target`` (:meth:`bring`); the world runs
        until no trip and no docking motion is left, at most ``budget`` cycles. How many ran.
        Raises ValueError (with the refusal's note) if :meth:`bring` says no."""
        self.release(foot, self.robot.profile.connector_index("front"))
        if not self.bring(foot, target, route):
            raise ValueError(self.robot.log[-1])
        cycles = 0
        while cycles < budget and (self.trips or self.reaches):
            self.cycle()
            cycles += 1
        return cycles

    def assimilate(self, module: int, connector: int, route: Sequence[int]) -> bool:
        """``dock_tail_to_foot`` in physics (the effect ``reach_and_dock``): the foot at the end
        of ``route`` lets go of the body at its front and comes to ``module``'s ``connector``
        by its own gaits, then the two dock by motion (:meth:`bring`; the last two modules up
        ``module``'s robot square its face). False (logged) if the rules say no: the route
        leads nowhere, the foot does not hang by its front, or a foot is already on its way to
        that face. While it lasts, ``module``'s ``docking`` sensor reads 1."""
        target = docking.reach_target(self, module, connector, route)
        if target is None:
            return False
        foot, at = target
        front = self.robot.profile.connector_index("front")
        where = f"{self.where(module, connector)} -> {self.where(foot, at)}"
        if at != front:
            self.note(f"assimilate {where}: the foot does not hang by its front")
            return False
        face = (module, connector)
        if (
            any(trip.target == face for trip, _ in self.trips)
            or any(r.chain.asking == face for r in self.reaches)
            or any(f == face for _, f, _ in self.clearings)
        ):
            self.note(f"assimilate {where}: a foot is already on its way there")
            return False
        lying = self.spot_taken(face, foot)
        if lying is not None:
            body = self.body_up(module)[::-1]
            self.clearings.append((Clearing(body, lambda: self.spot_taken(face, foot) is not None), face, target))
            name = self.robot.topology.names[lying]
            self.note(f"assimilate {where}: {name} lies behind {self.where(*face)}; the robot crawls clear first")
            return True
        return self._let_go(face, target)

    def _let_go(self, face: End, foot_end: End) -> bool:
        """The foot lets go of the body and comes to ``face`` (:meth:`bring`)."""
        self.release(*foot_end)
        return self.bring(foot_end[0], face, self.squaring_route(face[0]))

    def spot_taken(self, face: End, foot: int) -> int | None:
        """:func:`firmware.motion.clearing.spot_taken` by the overhead tracker's poses."""
        floor = self.motion_sensors.tracker.reading(self.robot.cycle)
        return spot_taken(floor, self.world.model, self.peer_of, self.robot.profile, self.robot.size, face, foot)

    def _step_clearings(self, held: dict[int, dict[int, float]]) -> None:
        for entry in list(self.clearings):
            clearing, face, foot_end = entry
            if not (self.running(face[0]) and self.running(foot_end[0])):
                self.clearings.remove(entry)
                where = f"{self.where(*foot_end)} -> {self.where(*face)}"
                self.note(f"assimilate {where}: a module stopped; crawl abandoned")
                continue
            for m, dof1 in clearing.step().items():
                held.setdefault(m, {})[0] = dof1
            if not clearing.done:
                continue
            self.clearings.remove(entry)
            outcome = "clear" if clearing.cleared else "still taken; the foot sets off anyway"
            self.note(f"{self.where(*face)}: crawled {clearing.gait_cycles} gait cycles, the spot {outcome}")
            self._let_go(face, foot_end)

    def squaring_route(self, module: int) -> tuple[int, ...]:
        """:func:`dh2rt.docking.squaring_route` in this world."""
        return docking.squaring_route(self.peer_of, self.robot.profile, module)

    def _assimilate_effect(self, module: int, args: tuple[object, ...]) -> None:
        connector, route = args
        assert isinstance(connector, int) and isinstance(route, tuple)
        self.assimilate(module, connector, route)

    def docking_modules(self) -> set[int]:
        """The modules whose docking motion is under way (what their ``docking`` sensor reads)."""
        return (
            {r.chain.asking[0] for r in self.reaches}
            | {trip.target[0] for trip, _ in self.trips}
            | {face[0] for _, face, _ in self.clearings}
        )

    def _bring_again(self, foot: int, target: End) -> None:
        """A trip or a dock with a foot that came (:meth:`bring`) gave up: the foot sets off
        again from where it is (backing off, then round to the spot), up to
        :data:`BRING_ATTEMPTS` times in all."""
        tries = self.attempts.get(foot)
        if tries is None or tries >= BRING_ATTEMPTS or not (self.running(foot) and self.running(target[0])):
            return  # not a foot that came, or its last try
        self.attempts[foot] = tries + 1
        self.trips.append((self._trip(foot, target), self.squaring_route(target[0])))
        front = self.robot.profile.connector_index("front")
        self.note(f"bring {self.where(foot, front)} -> {self.where(*target)}: the foot tries again ({tries + 1})")

    def _trip(self, foot: int, target: End) -> Trip:
        """A foot's trip to just behind ``target``, along ``target``'s robot as it lies."""
        b = target[0]
        return Trip(
            self.motion_sensors.tracker.reading(self.robot.cycle),
            foot,
            target,
            model=self.world.model,
            body=lambda: self.body_up(b),
            others=lambda: self.off_path(b, foot),
            diagonal_m=self.trip_diagonal_m,
        )

    def body_up(self, module: int) -> list[int]:
        """:func:`dh2rt.docking.body_up` in this world."""
        return docking.body_up(self.peer_of, self.robot.profile, module)

    def off_path(self, module: int, foot: int) -> list[int]:
        """:func:`dh2rt.docking.off_path` in this world."""
        return docking.off_path(self.peer_of, self.robot.profile, module, len(self.robot.engines), foot)

    def _step_trips(self, held: dict[int, dict[int, float]]) -> None:
        floor = self.motion_sensors.tracker.reading(self.robot.cycle)
        for entry in list(self.trips):
            trip, route = entry
            b, bc = trip.target
            if not (self.running(trip.module) and self.running(b)):
                self.trips.remove(entry)
                front = self.robot.profile.connector_index("front")
                self.note(f"bring {self.where(trip.module, front)}: a module stopped; trip abandoned")
                continue
            dofs = trip.step(floor)
            if not trip.done:
                held.setdefault(trip.module, {}).update({0: dofs[0], 1: dofs[1]})
                continue
            self.trips.remove(entry)
            self.trips_done.append(trip)
            front = self.robot.profile.connector_index("front")
            if not trip.arrived:
                self.note(
                    f"bring {self.where(trip.module, front)}: the trip gave up after {trip.cycles} cycles "
                    f"({trip.account()})"
                )
                self._bring_again(trip.module, trip.target)
                continue
            s, lat, heading = trip.state()
            self.note(
                f"bring {self.where(trip.module, front)}: arrived after {trip.cycles} cycles "
                f"({s * 100:+.1f} cm along, {lat * 100:+.1f} cm aside, {math.degrees(heading):+.0f} deg; "
                f"{trip.account()})"
            )
            self.reach_other(b, bc, route, (trip.module, front), creep=True)

    def release(self, module: int, connector: int) -> None:
        """A module lets go of its link at ``connector`` (nothing if there is none)."""
        if self.peer_of((module, connector)) is None:
            self.note(f"release {self.where(module, connector)}: nothing docked there")
            return
        self.cut(module, connector)
        self.note(f"{self.where(module, connector)} released")

    def _readings(
        self,
        joints: Iterable[int] = (),
        infrared: Iterable[int] = (),
        *,
        floor: bool = False,
        attitude: Iterable[int] = (),
    ) -> Readings:
        """What the motions sense this cycle (:class:`sim.motion_readings.MotionSensors`); with
        :attr:`oracle_poses`, the exact relative pose of every motion's faces as well."""
        oracle = [(r.chain.asking, r.chain.target) for r in self.reaches] if self.oracle_poses else []
        return self.motion_sensors.read(
            self.robot.cycle, joints, infrared, floor=floor, oracle=oracle, attitude=attitude
        )

    def _step_reaches(self) -> dict[int, dict[int, float]]:
        """Advance every docking motion; the joint targets they hold, per module. A motion that
        asks for the latch gets it when physics has the faces aligned (:meth:`aligned`)."""
        held: dict[int, dict[int, float]] = {}
        creeping = [c.module for c in self.creeps.values()]
        readings = self._readings(
            joints={m for r in self.reaches for m in r.modules},
            infrared=[r.chain.asking[0] for r in self.reaches] + creeping,
            floor=any(r.chain.anchor is not None or r.tracked for r in self.reaches),
            attitude=[m for r in self.reaches if r.tracked for m in (r.chain.asking[0], r.chain.target[0])],
        )
        for reach in list(self.reaches):
            a, ac = reach.chain.asking
            b, bc = reach.chain.target
            alive = self.running(a) and self.running(b)
            targets: dict[int, dict[int, float]] = {}
            if alive:
                if reach.asks_latch(readings) and self.aligned(a, ac, b, bc):
                    targets = reach.latch()
                else:
                    targets = reach.step(readings)
            creep = self.creeps.get(id(reach))
            if not alive:
                self.note(f"reach_dock {self.where(a, ac)}: a module of the chain stopped; motion abandoned")
                self.reaches.remove(reach)
                self.creeps.pop(id(reach), None)
                continue
            if reach.done:
                self.reaches.remove(reach)
                self.creeps.pop(id(reach), None)
                # the cycle just run
                contact = self._contact(reach.chain.asking, reach.chain.target, reach.infrared(readings))
                free = self.peer_of((a, ac)) is None and self.peer_of((b, bc)) is None
                if reach.latched and free:
                    self.dock(a, ac, b, bc)
                    if self.peer_of((a, ac)) == (b, bc):
                        self.contacts.append(contact)
                        self.note(
                            f"{self.where(a, ac)} docked to {self.where(b, bc)} by motion after {reach.cycles} cycles "
                            f"({contact.distance_m * 1000:.1f} mm, {contact.attitude_deg:.1f} deg)"
                        )
                        continue
                self.failed.append(contact)
                self.note(
                    f"reach_dock {self.where(a, ac)} -> {self.where(b, bc)} gave up after {reach.cycles} cycles "
                    f"({contact.distance_m * 1000:.1f} mm, {contact.attitude_deg:.1f} deg)"
                )
                if creep is not None:
                    self._bring_again(b, (a, ac))
                continue
            for m, dofs in targets.items():
                held.setdefault(m, {}).update(dofs)
            if creep is not None:
                d1, d2 = creep.step(readings)
                held.setdefault(creep.module, {}).update({0: d1, 1: d2})
        return held

    def _contact(self, asking: End, target: End, infrared: tuple[float, float]) -> Contact:
        """The trace's record of a latch or a give-up in the cycle just run."""
        return contact(self.world, self.robot.cycle - 1, asking, target, infrared)

    # ------------------------------------------------------------ events

    def apply(self, event: Event) -> None:
        # sense events go to the robot, which keeps their values (Robot.sensed): fill_sensors
        # leaves those alone
        if event.kind == "cut":
            self.cut(event.module, event.connector)
        elif event.kind == "dock":
            self.dock(event.module, event.connector, event.other, event.other_connector)
        else:
            self.robot.apply(event)
            return
        self.note(event.text or event.kind)

    # ------------------------------------------------------------ running

    def fill_sensors(self) -> None:
        """Every running module's sensors from its body, except those sense events set."""
        engines = self.robot.engines
        sensed = self.robot.sensed
        slot = self._docking_slot
        if slot is not None:
            busy = self.docking_modules()
            for m, e in enumerate(engines):
                if e is not None and "docking" not in sensed.get(m, {}):
                    e.sensors[slot] = int(m in busy)
        if self._floor_slots:
            self._fill_floor()
        if not self._sensor_slots:
            return
        running = [m for m, e in enumerate(engines) if e is not None]
        for m, values in self.sensors.read(running).items():
            e = engines[m]
            assert e is not None
            held = sensed.get(m, {})
            for name, slot, spec in self._sensor_slots:
                if name not in held:
                    e.sensors[slot] = spec.reading(values[name])

    def _fill_floor(self) -> None:
        """``floor_x``, ``floor_y`` (mm), ``floor_heading`` (degrees) of every running module
        from the overhead tracker, except those sense events set."""
        floor = self.motion_sensors.tracker.reading(self.robot.cycle)
        for m, e in enumerate(self.robot.engines):
            if e is None:
                continue
            pose = floor.pose(m).centre
            values = {"floor_x": pose.x * 1000, "floor_y": pose.y * 1000, "floor_heading": math.degrees(pose.heading)}
            held = self.robot.sensed.get(m, {})
            for name, slot, spec in self._floor_slots:
                if name not in held:
                    e.sensors[slot] = spec.reading(values[name])

    def cycle(self) -> None:
        """One control cycle: sensors, engines, then joints, then physics."""
        self.fill_sensors()
        self.robot.step()
        held = self._step_reaches() if self.reaches else {}
        if self.trips:
            self._step_trips(held)
        if self.clearings:
            self._step_clearings(held)
        for m, e in enumerate(self.robot.engines):
            if e is None:
                continue
            target = (e.dof[0], e.dof[1])
            if m in held:
                dofs = held[m]
                target = (dofs.get(0, target[0]), dofs.get(1, target[1]))
            if target != self._sent[m]:
                self.drivers[m].set_targets(*target)
                self._sent[m] = target
        if self.settle is not None:
            self.settle()
        self.world.step(self.steps_per_cycle)

    def run(
        self,
        cycles: int,
        events: Iterable[Event] = (),
        on_cycle: Callable[[int], None] | None = None,
        sample: bool = False,
    ) -> None:
        by_cycle: dict[int, list[Event]] = {}
        for ev in events:
            by_cycle.setdefault(ev.cycle, []).append(ev)
        end = self.robot.cycle + cycles
        while self.robot.cycle < end:
            for ev in by_cycle.pop(self.robot.cycle, []):
                self.apply(ev)
            self.cycle()
            if sample:
                n = self.robot.size
                self.samples.append(
                    (self.world.time, [self.world.joint_angles(m) for m in range(n)], self.world.centroid())
                )
            if on_cycle is not None:
                on_cycle(self.robot.cycle - 1)

    def displacement(self) -> float:
        """Metres the robot's centroid moved along the direction its head faced at the start."""
        return self.world.travel(self.start)

    def close(self) -> None:
        self.world.close()
