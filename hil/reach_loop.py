"""Docking by motion in the loop: a ``reach_dock`` carried out by the modules' own motion.

The docking sequence is :class:`firmware.motion.docking.Docking`, the same the physics runner
drives (``sim.runner.PhysicsRun.docking``); :class:`LoopReaches` keeps only the loop's side of
it: the readings, read from the stand-in's world under its lock; the targets, sent as holds;
the ``docking`` readings pushed; the records. The world answers the latch
(:meth:`hil.world.World.latch`).

With the PyBullet stand-in, the hardware-in-the-loop world carries a native's ``reach_dock``
(dock my connector to a connector of the module a route leads to) out as the physics runner
does (``firmware.motion.docking.Docking.start_reach``): the chain of modules along the route bends,
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
runner does it (``firmware.motion.docking.Docking.assimilate``): the foot at the end of the route lets go of the
body at its front, :class:`firmware.motion.crawl.Trip` takes it by its own gaits to just behind
the asking face (the tail's back), steering by the overhead tracker's poses, each step's joint
targets held by the foot's own servos through ``Hold`` as above; once it is there the last two
modules up the asking module's robot square their face by a :class:`firmware.motion.reach.Reach`
while the foot creeps (:class:`firmware.motion.crawl.Creep`,
held the same way); a dock that gives up sends the foot round again, up to
``firmware.motion.docking.BRING_ATTEMPTS`` docks. While a module's motion (a trip to its face, or a
reach it asked for) is under way, the world pushes it ``docking`` = 1 (if its program
declares the sensor; firmware.control.Readings), and 0 once it ended.

With ``World.modules_move`` the modules carry a ``reach_dock`` out themselves
(firmware.motion.asking, over motion frames on their links): this computes nothing for it
and sends no hold; it pushes the asking module its infrared pairs and the tracker's report
each world cycle (:meth:`LoopReaches.own_started`) and answers its latch
(:meth:`LoopReaches.own_latch`). docs/hil.md, "The motion in the module".

Every latch is recorded in :attr:`LoopReaches.contacts` (a :class:`sim.motion_readings.Contact`: both
faces' world poses, distance, attitude error and the infrared reading at that moment) and
logged with the cycles it took; every motion that gave up, in :attr:`LoopReaches.failed`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Protocol

from dh2rt.docking import DockingWorld, End, route_end
from dh2rt.profile import Profile
from dh2rt.program import CompiledProgram
from dh2rt.topology import Topology
from firmware.control import Floor, Readings
from firmware.motion.docking import Docking
from firmware.motion.readings import Readings as MotionReadings
from firmware.motion.underway import Motion, Needs
from hil.physics_stand_in import PhysicsStandIn
from hil.tracker_udp import TrackerPublisher
from sim.motion_readings import Contact, MotionSensors, Verdicts, contact
from sim.tracker import OverheadTracker


class LoopWorld(DockingWorld, Protocol):
    """What the docking motions need of the loop's world (:class:`hil.world.World` offers it;
    the world imports this module, not the other way round)."""

    program: CompiledProgram
    topology: Topology
    profile: Profile
    #: the sensor values ``sense`` events forced on each module
    sensed: dict[int, dict[str, int]]
    #: the overhead tracker sent over UDP to the modules (``--tracker-udp``), or None
    tracker: TrackerPublisher | None

    @property
    def cycle(self) -> int: ...

    def latch(self, a: int, a_conn: int, b: int, b_conn: int) -> bool: ...

    def hold(self, module: int, targets: Mapping[int, float]) -> None: ...

    def send_readings(self, module: int, readings: Readings | Floor) -> None: ...


class LoopReaches:
    """The docking sequence (:class:`firmware.motion.docking.Docking`) of a loop world whose
    body is the PyBullet stand-in: this answers its reads (under the stand-in's lock) and
    keeps its records, and sends the targets as holds; the world answers its latches
    (:meth:`hil.world.World.latch`)."""

    def __init__(self, world: LoopWorld, physics: PhysicsStandIn, tracker: OverheadTracker | None = None) -> None:
        self.world = world
        self.physics = physics
        with physics.lock:
            #: What the motions read (the chain's joint angles, every connector's infrared pair,
            #: the overhead tracker), as PhysicsRun's.
            self.sensors = MotionSensors(physics.world, tracker)
        #: The sequence itself; the plan's seconds by this process's clock.
        self.docking = Docking(
            world, self, physics.world.model, world.profile, world.topology.names, clock=time.perf_counter
        )
        #: How each motion ended (:attr:`contacts`, :attr:`failed`).
        self.verdicts = Verdicts()
        #: Every link formed by a docking motion, and every motion that gave up (the verdicts').
        self.contacts: list[Contact] = self.verdicts.contacts
        self.failed: list[Contact] = self.verdicts.failed
        #: What each module was last told to hold (absent: its joints are its program's).
        self.holding: dict[int, dict[int, float]] = {}
        #: The ``docking`` reading last pushed to each module, if the program declares it.
        program, profile = world.program, world.profile
        self.docking_declared = "docking" in program.sensor_names and "docking" in profile.sensor_names
        self.docking_sent: dict[int, int] = {}
        #: reaches the modules carry out themselves (World.modules_move): asking module ->
        #: (its connector, the world cycle it asked at, the target module)
        self.own: dict[int, tuple[int, int, int | None]] = {}
        #: of those, the ones carrying out a ``reach_and_dock`` (firmware.motion.assimilating):
        #: they read the tracker's whole report (the body up, the modules off the path, the foot)
        self.own_assimilating: set[int] = set()
        #: released feet running their own trip and creep (firmware.motion.foot): each world
        #: cycle their infrared pairs and the tracker's whole report, as a module on a robot
        #: reads its own pairs and hears the tracker's broadcast
        self.feet: set[int] = set()
        self._pushed_own = -1

    # ------------------------------------------------------------ what the sequence asks of the world

    @property
    def now(self) -> int:
        return self.world.cycle

    def sense(self, cycle: int, needs: Needs) -> MotionReadings:
        """What the motions sense at world cycle ``cycle``, read under the stand-in's lock."""
        with self.physics.lock:
            return self.sensors.read(cycle, needs.joints, needs.infrared, floor=needs.floor, attitude=needs.attitude)

    def ended(self, motion: Motion, linked: bool, readings: MotionReadings) -> None:
        """A motion ended: its record (:attr:`contacts` or :attr:`failed`) and log line."""
        w = self.world
        took = f"{motion.reach.cycles} steps, world cycles {motion.asked}-{motion.last}, {motion.missed} missed"
        with self.physics.lock:
            line = self.verdicts.record(self.physics.world, w.cycle, motion, linked, readings, w.where, took)
        w.note(line)

    # ------------------------------------------------------------ requests

    def start(self, module: int, connector: int, route: Sequence[int], target_conn: int) -> bool:
        """``reach_dock`` (:meth:`firmware.motion.docking.Docking.start_reach`)."""
        started = self.docking.start_reach(module, connector, route, target_conn)
        self.sync_docking()
        return started

    def assimilate(self, module: int, connector: int, route: Sequence[int]) -> bool:
        """``reach_and_dock`` (:meth:`firmware.motion.docking.Docking.assimilate`); while it
        lasts, ``module``'s ``docking`` sensor reads 1."""
        started = self.docking.assimilate(module, connector, route)
        self.sync_docking()
        return started

    def spot_taken(self, face: End, foot: int) -> int | None:
        """:meth:`firmware.motion.docking.Docking.spot_taken` (takes the stand-in's lock)."""
        return self.docking.spot_taken(face, foot)

    def sync_docking(self, modules: Sequence[int] | None = None) -> None:
        """Push the ``docking`` reading (1 while the module's docking is under way) to every
        module (or those of ``modules``) whose reading changed since it was last sent, if the
        program declares the sensor; a ``sense`` event's value for it holds instead."""
        w = self.world
        if not self.docking_declared:
            return
        busy = self.docking.docking_modules() | set(self.own)
        for m in range(w.topology.size) if modules is None else modules:
            value = int(m in busy)
            if not w.running(m) or "docking" in w.sensed.get(m, {}) or self.docking_sent.get(m) == value:
                continue
            self.docking_sent[m] = value
            w.send_readings(m, Readings({"docking": value}))

    # ------------------------------------------------------------ each world cycle

    @property
    def busy(self) -> bool:
        """A docking motion or a foot's trip is under way."""
        return self.docking.busy

    def stepped_in(self, cycle: int) -> bool:
        """Every motion and trip under way has made its step of world cycle ``cycle``."""
        return self.docking.stepped_in(cycle)

    def step(self, cycle: int, due: bool = True) -> None:
        """Once per world cycle (``due``: the world's tick is in the moment of the cycle for it;
        :meth:`firmware.motion.docking.Docking.step`): step the sequence, send the modules it
        moves the targets to hold, and push the ``docking`` readings."""
        if self.docking.busy:
            self._send_holds(self.docking.step(cycle, due))
        if (self.own or self.feet) and cycle != self._pushed_own:
            self._pushed_own = cycle
            self._push_own(cycle)
        self.sync_docking()

    def _send_holds(self, holds: dict[int, dict[int, float]]) -> None:
        """Tell the moving modules what to hold; modules no motion or trip holds any more get
        their joints back (an empty hold); those of one not stepped this time keep theirs."""
        owned = self.docking.owned()
        for m in [m for m in self.holding if m not in holds and m not in owned]:
            del self.holding[m]
            self.world.hold(m, {})
        for m, dofs in holds.items():
            rounded = {dof: round(v, 2) for dof, v in dofs.items()}
            if self.holding.get(m) != rounded:
                self.holding[m] = rounded
                self.world.hold(m, rounded)

    # ------------------------------------------------------------ reaches the modules run

    def own_started(self, module: int, connector: int, route: Sequence[int], target_conn: int) -> None:
        """``module`` carries out its ``reach_dock`` itself (firmware.motion.asking): the world
        computes nothing for it; it pushes the module its infrared pairs each world cycle and
        answers its latch (:meth:`own_latch`) until it reports the end (:meth:`own_ended`)."""
        w = self.world
        end = route_end(w.peer_of, module, route)
        self.own[module] = (connector, w.cycle, None if end is None else end[0])
        w.note(f"reach_dock {w.where(module, connector)} along {list(route)}: carried out by the module")
        self.sync_docking([module])

    def own_assimilate(self, module: int, connector: int, route: Sequence[int]) -> None:
        """``module`` carries out its ``reach_and_dock`` itself (firmware.motion.assimilating),
        the foot its own trip (firmware.motion.foot, once it reports its SET_OFF:
        :meth:`foot_event`): the world computes nothing for either; it pushes them their
        infrared pairs and the tracker's whole report each world cycle and answers the asking
        module's latch, until it reports the end."""
        w = self.world
        self.own[module] = (connector, w.cycle, None)
        self.own_assimilating.add(module)
        w.note(f"reach_and_dock {w.where(module, connector)} along {list(route)}: carried out by the modules")
        self.sync_docking([module])

    def foot_event(self, module: int, kind: str) -> None:
        """A released foot's ``foot`` effect: from its ``set_off`` until it is ``docked`` or
        ``gave_up`` it hears the tracker and its pairs are pushed."""
        if kind == "set_off":
            self.feet.add(module)
        elif kind in ("docked", "gave_up"):
            self.feet.discard(module)

    def _push_own(self, cycle: int) -> None:
        """The asking modules' and the feet's infrared pairs as physics has them, whole
        millimetres and degrees (what the module's pair reads; its program may not declare
        them), and the overhead tracker's report: of the asking and target modules for a
        ``reach_dock``, of every module for a ``reach_and_dock`` and a foot. With the
        tracker over UDP (``--tracker-udp``) the report goes as a datagram to every module's
        port instead, and ``Floor`` carries the module's own IMU only."""
        for m in [m for m in self.own if not self.world.running(m)]:
            del self.own[m]
            self.own_assimilating.discard(m)
        self.feet = {m for m in self.feet if self.world.running(m)}
        readers = sorted(set(self.own) | self.feet)
        if not readers:
            return
        # the target of a reach_dock answers the asker with its own IMU (in its ANGLES): it is
        # pushed its own roll and pitch, as every module would read its own
        targets = {t for _, _, t in self.own.values() if t is not None and self.world.running(t)} - set(readers)
        every = tuple(range(self.world.topology.size))
        with self.physics.lock:
            readings = self.sensors.read(cycle, frozenset(), tuple(readers), floor=True, attitude=every)
        for t in sorted(targets):
            if t in readings.attitude:
                self.world.send_readings(t, Floor({}, {t: readings.attitude[t]}))
        parts = {
            k: tuple((p.x, p.y, p.heading) for p in (pose.centre, pose.front, pose.back))
            for k, pose in readings.floor.modules.items()
        }
        udp = self.world.tracker
        if udp is not None:  # the modules hear the tracker themselves (hil.tracker_udp): every module's parts
            udp.publish(readings.floor, [udp.ports[m] for m in every if self.world.running(m)])
            parts = {}
        for m in readers:
            pairs = readings.infrared.get(m, {})
            self.world.send_readings(m, Readings({name: round(v) for name, v in pairs.items()}))
            target = self.own.get(m, (0, 0, None))[2]
            seen = every if m in self.feet or m in self.own_assimilating else (m,) if target is None else (m, target)
            own = {m: readings.attitude[m]} if m in readings.attitude else {}
            self.world.send_readings(m, Floor({k: v for k, v in parts.items() if k in seen}, own))

    def own_latch(self, module: int, connector: int, target: int, target_conn: int) -> bool:
        """The module asks its latch to close: closed in physics and linked, or refused
        (:meth:`hil.world.World.latch`); a latch is recorded as :attr:`contacts` are."""
        w = self.world
        faces = range(1, w.profile.connector_count + 1)
        if not (0 <= target < w.topology.size and connector in faces and target_conn in faces):
            w.note(f"{w.topology.names[module]}: a latch to module {target} connector {target_conn}: no such face")
            return False
        pair = self.pair(module, connector)
        closed = w.latch(module, connector, target, target_conn)
        if closed:
            self.record_latch(module, connector, target, target_conn, how="by motion, the module's own", pair=pair)
        return closed

    def pair(self, module: int, connector: int) -> tuple[float, float]:
        """``module``'s infrared pair at ``connector`` now (distance mm, alignment degrees)."""
        with self.physics.lock:
            ir = self.sensors.read(self.world.cycle, frozenset(), (module,), floor=False, attitude=())
        name = self.world.profile.connector_name(connector)
        pairs = ir.infrared.get(module, {})
        return pairs.get(f"ir_{name}", 0.0), pairs.get(f"ir_{name}_align", 180.0)

    def record_latch(
        self,
        module: int,
        connector: int,
        target: int,
        target_conn: int,
        *,
        how: str,
        pair: tuple[float, float],
    ) -> None:
        """A latch that closed (the world docked it): recorded in :attr:`contacts` and logged,
        with ``pair``, the infrared pair read before the dock (:meth:`pair`)."""
        w = self.world
        with self.physics.lock:
            record = contact(self.physics.world, w.cycle, (module, connector), (target, target_conn), pair)
        self.contacts.append(record)
        asked = self.own[module][1] if module in self.own else w.cycle
        w.note(
            f"{w.where(module, connector)} docked to {w.where(target, target_conn)} {how} "
            f"(asked at world cycle {asked}; {record.distance_m * 1000:.1f} mm, {record.attitude_deg:.1f} deg "
            f"apart; infrared {pair[0]:.1f} mm, {pair[1]:.1f} deg)"
        )

    def own_ended(self, module: int, connector: int, verdict: str) -> None:
        """The module's reach ended (its ``reach_ended`` effect)."""
        w = self.world
        self.own.pop(module, None)
        kind = "reach_and_dock" if module in self.own_assimilating else "reach_dock"
        self.own_assimilating.discard(module)
        w.note(f"{kind} {w.where(module, connector)}: {verdict} (the module's own)")
        self.sync_docking([module])
