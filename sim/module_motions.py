"""The docking motions run in the modules of a one-process physics robot: each module's own
:class:`firmware.motion.host.MotionHost` (the same code a module process runs), its motion
frames carried over the robot's links, a hop a cycle.

With this, :class:`sim.runner.PhysicsRun` (``modules_move=True``) plans no motion and holds no
joint of its own: it plays physics, links and sensors. What each module's motions read is
what that module senses (:class:`sim.motion_readings.MotionSensors`): its own joints, its own
infrared pairs, its own IMU and the overhead tracker's report of every module (a broadcast,
as ``dh2rt tracker``'s over UDP). The latch closes if physics has the faces aligned now, and
the link is made, as the loop's world answers a module's latch.

A frame is carried at once, passed on and answered along its route within the cycle it was
sent in (a motion frame of some 30 bytes crosses a 115,200-baud infrared link in under 3 ms,
a small part of a 50 ms cycle; in the loop a 5-hop chain was learnt in 4 to 5 cycles), so a
chain of k hops is learnt in k cycles, a hop a cycle; a frame into a connector with no link
is lost (counted in :attr:`ModuleMotions.lost`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Protocol

from dh2rt.docking import End
from dh2rt.robot import Robot
from firmware.motion.host import NATIVES, MotionHost
from firmware.motion.readings import FloorPoses, Readings
from firmware.outbound import Out
from sim.motion_readings import Contact, MotionSensors, contact
from sim.world import World


class PhysicsRun(Protocol):
    """What the motions need of the run (sim.runner.PhysicsRun offers it; the runner
    imports this module, not the other way round)."""

    robot: Robot
    world: World
    motion_sensors: MotionSensors
    contacts: list[Contact]

    def peer_of(self, end: End) -> End | None: ...

    def aligned(self, a: int, a_conn: int, b: int, b_conn: int) -> bool: ...

    def latch(self, a: int, a_conn: int, b: int, b_conn: int) -> bool: ...

    def release(self, module: int, connector: int) -> None: ...

    def where(self, module: int, connector: int) -> str: ...

    def note(self, message: str) -> None: ...


class ModuleMotions:
    """Every module's :class:`MotionHost` in a :class:`sim.runner.PhysicsRun` (module docs)."""

    def __init__(self, run: PhysicsRun) -> None:
        self.run = run
        robot = run.robot
        profile = robot.profile
        self.hosts = [
            MotionHost(
                m, profile, _Body(self, m), _Senses(self, m), _Latch(self, m), self._logger(m), model=run.world.model
            )
            for m in range(robot.size)
        ]
        self.lost = 0
        self._readings: tuple[int, Readings] | None = None

    def _logger(self, module: int) -> Callable[[str], None]:
        name = self.run.robot.topology.names[module]
        return lambda line: self.run.robot.log.append(f"{name}: cycle {self.run.robot.cycle}: {line}")

    # ------------------------------------------------------------ what the modules sense

    def readings(self) -> Readings:
        """This cycle's readings of every module (read once a cycle, for all)."""
        cycle = self.run.robot.cycle
        if self._readings is None or self._readings[0] != cycle:
            every = range(self.run.robot.size)
            reads = self.run.motion_sensors.read(cycle, every, every, floor=True, attitude=every)
            self._readings = (cycle, reads)
        return self._readings[1]

    def links(self, module: int) -> tuple[int, ...]:
        """The module's ConnectorStatus (the peer's connector at each of its connectors)."""
        engine = self.run.robot.engines[module]
        return () if engine is None else tuple(engine.status)

    # ------------------------------------------------------------ each cycle

    def start(self, module: int, kind: str, args: tuple[object, ...]) -> None:
        """The program of ``module`` asked a docking native (one of NATIVES)."""
        assert kind in NATIVES
        self.hosts[module].start(kind, args, self.links(module), self.run.robot.cycle)

    def before_cycle(self) -> None:
        """Every running module's motions make their step; their frames go out."""
        robot = self.run.robot
        for m, host in enumerate(self.hosts):
            if not robot.alive(m):
                continue
            self._send(m, host.before_cycle(robot.cycle))
            effects, host.effects = host.effects, []
            for kind, args in effects:
                self._effect(m, kind, args)

    def _send(self, module: int, outs: list[Out]) -> None:
        """Carry ``module``'s frames, and whatever they make other modules send, at once."""
        robot = self.run.robot
        queue = [(module, out) for out in outs]
        while queue:
            at, out = queue.pop(0)
            peer = self.run.peer_of((at, out.connector))
            if peer is None or not robot.alive(peer[0]):
                self.lost += 1
                continue
            to, connector = peer
            queue.extend((to, o) for o in self.hosts[to].received(connector, out.frame, robot.cycle))

    def _effect(self, module: int, kind: str, args: list[Any]) -> None:
        name = self.run.robot.topology.names[module]
        if kind == "release":
            self.run.release(module, int(args[0]))
        elif kind == "foot":
            self.run.robot.log.append(f"{name}: foot {' '.join(map(str, args))}")
        elif kind == "reach_ended":
            connector = self.run.robot.profile.connector_name(int(args[0]))
            self.run.note(f"{name}.{connector}: {args[1]} (the module's own)")

    def joints(self) -> dict[int, dict[int, float]]:
        """What each module's motions hold on its joints this cycle (absent: its program's)."""
        return {m: dict(h.joints) for m, h in enumerate(self.hosts) if h.joints and self.run.robot.alive(m)}

    def given_up(self) -> int:
        """Reaches the modules ran that gave up (each says so in its log line)."""
        return sum(": reach_dock m" in line and " gave up after " in line for line in self.run.robot.log)

    def docking(self) -> set[int]:
        """The modules whose own reach is under way: what their ``docking`` sensor reads."""
        return {m for m, h in enumerate(self.hosts) if h.reach is not None and not h.reach.done}


class _Body:
    """A module's joints and links as its motion frames report them (firmware.motion.member.Body)."""

    def __init__(self, motions: ModuleMotions, module: int) -> None:
        self.motions, self.module = motions, module

    def angles(self) -> tuple[float, ...]:
        return tuple(self.motions.readings().joints[self.module])

    def links(self) -> tuple[int, ...]:
        return self.motions.links(self.module)


class _Senses:
    """What a module senses for its motions (firmware.motion.asking.OwnSenses)."""

    def __init__(self, motions: ModuleMotions, module: int) -> None:
        self.motions, self.module = motions, module

    def angles(self) -> tuple[float, ...]:
        return tuple(self.motions.readings().joints[self.module])

    def infrared(self) -> Mapping[str, float]:
        return self.motions.readings().infrared.get(self.module, {})

    def floor(self) -> FloorPoses:
        return self.motions.readings().floor

    def attitude(self) -> Mapping[int, tuple[float, float]]:
        """Its own IMU only: another module's tilt is not its to read."""
        own = self.motions.readings().attitude.get(self.module)
        return {} if own is None else {self.module: own}


class _Latch:
    """The latch of a reach a module runs (firmware.motion.asking.LatchAsk): it closes if
    physics has the faces aligned now; then the link is made (PhysicsRun.latch) and recorded."""

    def __init__(self, motions: ModuleMotions, module: int) -> None:
        self.motions, self.module = motions, module

    def aligned(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        return self.motions.run.aligned(a, a_conn, b, b_conn)

    def latch(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        run = self.motions.run
        pairs = self.motions.readings().infrared.get(a, {})
        name = run.robot.profile.connector_name(a_conn)
        pair = (pairs.get(f"ir_{name}", 0.0), pairs.get(f"ir_{name}_align", 180.0))
        linked = run.latch(a, a_conn, b, b_conn)
        if linked:
            record = contact(run.world, run.robot.cycle, (a, a_conn), (b, b_conn), pair)
            run.contacts.append(record)
            run.note(
                f"{run.where(a, a_conn)} docked to {run.where(b, b_conn)} by motion, the module's own "
                f"({record.distance_m * 1000:.1f} mm, {record.attitude_deg:.1f} deg apart)"
            )
        return linked
