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
tolerance, and is undone otherwise. The docking sequence itself is not here: it is
:class:`firmware.motion.docking.Docking` (:attr:`PhysicsRun.docking`), written once for this
runner and the loop (``hil.reach_loop``), sans-IO; this runner answers what it asks (each
cycle's readings, :class:`sim.motion_readings.MotionSensors`; the latch, :meth:`PhysicsRun.latch`;
the records, :meth:`PhysicsRun.ended`) and writes the joint targets it returns to the joints.
A native action's ``reach_dock`` (dock my connector to a connector of the module a route
leads to) is carried out by the modules' own motion (:class:`firmware.motion.reach.Reach`):
the chain of modules along the route bends,
aligns and approaches, its joints owned by the motion until the latch closes (the motion asks
for it when the asking connector's infrared pair sees the target within the tolerance below;
the latch closes when physics has the faces aligned within it) or the motion gives up. Every link
formed so is recorded in :attr:`PhysicsRun.contacts` with both faces' world poses and errors
at that moment. ``release`` cuts a module's link at one of its connectors. ``reach_and_dock``
(legs to snake's ``dock_tail_to_foot``) is carried out by motion as well
(:meth:`firmware.motion.docking.Docking.assimilate`): the foot lets go of the body, comes to the asking face by its
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
from firmware.motion.docking import DOCK_TOLERANCE_DEG as DOCK_TOLERANCE_DEG
from firmware.motion.docking import DOCK_TOLERANCE_M as DOCK_TOLERANCE_M
from firmware.motion.docking import Docking
from firmware.motion.readings import Readings
from firmware.motion.underway import Motion, Needs
from sim.module_motions import ModuleMotions
from sim.motion_readings import Contact, MotionSensors, Verdicts
from sim.record import Sample
from sim.sensors import PhysicsSensors
from sim.tracker import OverheadTracker
from sim.world import World

#: Physics steps per DH2 control cycle: 12 steps at 240 Hz = 50 ms per cycle.
STEPS_PER_CYCLE = 12
#: The overhead tracker's sensors (dh2rt.profile's table), filled from sim.tracker.
FLOOR_SENSORS = ("floor_x", "floor_y", "floor_heading")


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
        modules_move: bool = False,
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
        robot.effect_handlers["reach_dock"] = lambda _r, m, args: self._reach_dock_effect(m, args)
        robot.effect_handlers["release"] = lambda _r, m, args: self.release(m, *args)
        #: What the docking motions read: the chain's joint angles, the infrared pairs (every
        #: connector's), and the overhead tracker (exact unless ``tracker`` says otherwise).
        self.motion_sensors = MotionSensors(self.world, tracker)
        #: The docking sequence (reaches, feet's trips, crawls clear) under way, sans-IO: this
        #: run answers its reads, latches and records. Its options say how it plans
        #: (``trip_diagonal_m``, ``free_distance``, ``closed_by_tracker``: each a measured choice;
        #: benchmarks/bench_trips.py and bench_legs_to_snake.py compare them).
        self.docking = Docking(self, self, self.world.model, profile, robot.topology.names)
        #: ORACLE, for measuring only: the docking motions read their faces' relative pose from
        #: the world's exact state (as before they were sans-IO) instead of the chain's
        #: kinematics of its measured angles and the tracker (firmware.motion.readings.Readings.oracle).
        self.oracle_poses = False
        #: How each docking motion ended (:attr:`contacts`, :attr:`failed`).
        self.verdicts = Verdicts()
        #: Every link formed by a docking motion, and every motion that gave up (the verdicts').
        self.contacts: list[Contact] = self.verdicts.contacts
        self.failed: list[Contact] = self.verdicts.failed
        #: (name, the engine's slot, its spec) of each overhead tracker sensor the program reads
        self._floor_slots = [
            (n, program.sensor_names.index(n), profile.sensor(n))
            for n in FLOOR_SENSORS
            if n in program.sensor_names and n in profile.sensor_names
        ]
        #: With ``modules_move`` the modules carry out their docking natives themselves, each
        #: its own firmware.motion.host.MotionHost (sim.module_motions): this run then plans
        #: nothing and holds no joint; :attr:`docking` stays idle.
        self.module_motions: ModuleMotions | None = None
        if modules_move:
            self.module_motions = ModuleMotions(self)
            robot.effect_handlers["reach_dock"] = lambda _r, m, args: self._own_native(m, "reach_dock", args)
            robot.effect_handlers["reach_and_dock"] = lambda _r, m, args: self._own_native(m, "reach_and_dock", args)
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

    @property
    def now(self) -> int:
        """The control cycle now (:class:`firmware.motion.docking.DockingOwner`)."""
        return self.robot.cycle

    def latch(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        """A docking motion's latch (:class:`firmware.motion.docking.LatchWorld`): both faces
        still free, the link, then the latch in physics (:meth:`dock`); whether they linked."""
        if self.peer_of((a, a_conn)) is not None or self.peer_of((b, b_conn)) is not None:
            return False
        self.dock(a, a_conn, b, b_conn)
        return self.peer_of((a, a_conn)) == (b, b_conn)

    def ended(self, motion: Motion, linked: bool, readings: Readings) -> None:
        """A docking motion ended (in the cycle just run): its record and log line."""
        took = f"{motion.reach.cycles} cycles"
        self.note(self.verdicts.record(self.world, self.robot.cycle - 1, motion, linked, readings, self.where, took))

    def sense(self, cycle: int, needs: Needs) -> Readings:
        """What the motions sense (:class:`sim.motion_readings.MotionSensors`); with
        :attr:`oracle_poses`, the exact relative pose of every motion's faces as well."""
        oracle = (
            [(m.reach.chain.asking, m.reach.chain.target) for m in self.docking.motions] if self.oracle_poses else []
        )
        return self.motion_sensors.read(
            cycle, needs.joints, needs.infrared, floor=needs.floor, oracle=oracle, attitude=needs.attitude
        )

    def bring_home(self, foot: int, target: End, route: tuple[int, ...], budget: int) -> int:
        """One round of legs to snake driven from Python: ``foot`` lets go of the body at its
        front (:meth:`release`) and is brought to ``target``
        (:meth:`firmware.motion.docking.Docking.bring`); the world runs until no trip and no
        docking motion is left, at most ``budget`` cycles. How many ran. Raises ValueError
        (with the refusal's note) if the bring is refused."""
        self.release(foot, self.robot.profile.connector_index("front"))
        if not self.docking.bring(foot, target, route):
            raise ValueError(self.robot.log[-1])
        cycles = 0
        while cycles < budget and (self.docking.trips or self.docking.motions):
            self.cycle()
            cycles += 1
        return cycles

    def _reach_dock_effect(self, module: int, args: tuple[object, ...]) -> None:
        connector, route, target_conn = args
        assert isinstance(connector, int) and isinstance(route, tuple) and isinstance(target_conn, int)
        self.docking.start_reach(module, connector, route, target_conn)

    def _assimilate_effect(self, module: int, args: tuple[object, ...]) -> None:
        connector, route = args
        assert isinstance(connector, int) and isinstance(route, tuple)
        self.docking.assimilate(module, connector, route)

    @property
    def moving(self) -> bool:
        """A reach or a foot's trip is under way: the run's sequence's, or a module's own."""
        if self.docking.trips or self.docking.motions:
            return True
        motions = self.module_motions
        return motions is not None and any(h.busy for m, h in enumerate(motions.hosts) if self.robot.alive(m))

    def _own_native(self, module: int, kind: str, args: tuple[object, ...]) -> None:
        """A docking native the module carries out itself (``modules_move``)."""
        assert self.module_motions is not None
        self.module_motions.start(module, kind, args)

    def release(self, module: int, connector: int) -> None:
        """A module lets go of its link at ``connector`` (nothing if there is none)."""
        docking.release(self, module, connector)

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
            busy = self.docking.docking_modules()
            if self.module_motions is not None:
                busy |= self.module_motions.docking()
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
        robot = self.robot
        self.world.unpowered = {m for m in range(robot.topology.size) if not robot.alive(m)}
        self.fill_sensors()
        motions = self.module_motions
        if motions is not None:
            motions.before_cycle()
        self.robot.step()
        held = self.docking.step(self.robot.cycle) if self.docking.busy else {}
        if motions is not None:
            held = motions.joints()
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
