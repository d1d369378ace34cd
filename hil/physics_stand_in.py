"""The PyBullet world as the body of a hardware-in-the-loop robot: the full firmware path.

Each module process drives its DOF1/DOF2 servos with dynamixel-sdk on a serial port, as it
would on a physical CONRO-like module; the port is a pty whose far end is a Dynamixel
Protocol 2.0 emulator (``hil.servo_emulator``) whose joints are that module's joints in one
PyBullet world. The world steps physics in real time as the launcher ticks.

The world also measures what the modules' other sensors would (:meth:`PhysicsStandIn.readings`:
the IMU, each connector's infrared pair and ground contact, by ``sim.sensors``); the HIL
world pushes those readings to the module processes, while the joints' present position and
load reach each module through its own servos.

With ``latches`` (the launcher's ``--latch-emulator``) each module's bus also has a latch servo
(:class:`hil.latch_emulator.LatchJoint`, id :data:`LATCH_ID`) on its female face
(:data:`LATCH_CONNECTOR`, CONRO's ``front``, the only one): its horn passes the pins only if
that face is aligned within the docking tolerance with the nearest free male face of another
module (:meth:`PhysicsStandIn.mate`); the world docks and undocks on the horn
(:meth:`PhysicsStandIn.horn_closed`, ``hil.world.World``). A latch on a face docked at the start
starts closed.

PyBullet is not thread-safe: one lock serialises the emulators' joint reads and writes (each
in its own thread) with the stepping. A latch's horn is read under its bus's lock, which
then takes the world's (never the other way round).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from dh2rt.closing import Closing
from dh2rt.topology import Topology
from drivers.base import Health, Joint, ModuleDriver
from hil.latch_emulator import LATCH_CONNECTOR, LATCH_ID, LATCH_SETTINGS, LatchJoint, emulate
from hil.servo_emulator import ServoEmulator
from hil.servo_joints import ModuleJointAdapter
from sim.runner import DOCK_TOLERANCE_DEG, DOCK_TOLERANCE_M
from sim.sensors import JOINT_SENSORS, PhysicsSensors
from sim.world import World as PhysicsWorld

#: A long hiccup (a slow start, a paused process) is not caught up: physics never runs more
#: than this many seconds of simulated time in one advance.
MAX_CATCH_UP_S = 0.25


@dataclass
class _LockedDriver(ModuleDriver):
    """A driver whose every call holds the world's lock."""

    inner: ModuleDriver
    lock: threading.Lock

    def __post_init__(self) -> None:
        self.limits = self.inner.limits

    def set_targets(self, dof1_deg: float, dof2_deg: float) -> None:
        with self.lock:
            self.inner.set_targets(dof1_deg, dof2_deg)

    def read_positions(self) -> tuple[float, float]:
        with self.lock:
            return self.inner.read_positions()

    def read_loads(self) -> tuple[float, float]:
        with self.lock:
            return self.inner.read_loads()

    def set_torque(self, enabled: bool) -> None:
        with self.lock:
            self.inner.set_torque(enabled)

    def health(self) -> Health:
        with self.lock:
            return self.inner.health()


class PhysicsStandIn(Closing):
    """One PyBullet world and one servo emulator (a pty) per module of ``topology``; with
    ``latches``, a latch servo on each bus (see the module docstring)."""

    def __init__(self, topology: Topology, *, seed: int = 0, gui: bool = False, latches: bool = False) -> None:
        # everything close() reads exists before anything can fail (or be interrupted)
        self.lock = threading.Lock()
        self.emulators: list[ServoEmulator] = []
        #: module -> its latch's horn (``latches``), and the face it mated with when it passed the pins
        self.latches: dict[int, LatchJoint] = {}
        self.mated: dict[int, tuple[int, int] | None] = {}
        self._t0: float | None = None
        self._steps = 0
        self._final: tuple[float, float] | None = None  # (displacement, simulated s) once closed
        self.world = PhysicsWorld(topology, seed=seed, gui=gui)
        try:
            for m in range(topology.size):
                driver = _LockedDriver(self.world.driver(m), self.lock)
                emulator = self._latched_bus(m, driver) if latches else ServoEmulator.for_module(driver)
                emulator.start()
                self.emulators.append(emulator)
        except BaseException:
            self.close()
            raise
        self.start_centroid = self.world.centroid()
        self._sensors: PhysicsSensors | None = None

    def _latched_bus(self, module: int, driver: ModuleDriver) -> ServoEmulator:
        adapter = ModuleJointAdapter(driver)
        docked = any((module, LATCH_CONNECTOR) in link.ends() for link in self.world.links())
        closed = float(LATCH_SETTINGS["closed_deg"])
        horn = LatchJoint(
            float(LATCH_SETTINGS["open_deg"]), closed, lambda: self._can_close(module),
            start_deg=closed if docked else None,
        )  # fmt: skip
        self.latches[module] = horn
        self.mated[module] = None
        return emulate(LATCH_ID, horn, {1: adapter.joint(Joint.DOF1), 2: adapter.joint(Joint.DOF2)})

    def _can_close(self, module: int) -> bool:
        """The latch's hook (its bus's thread): the pins pass if the face is aligned with a mate."""
        self.mated[module] = self.mate(module, LATCH_CONNECTOR)
        return self.mated[module] is not None

    def mate(self, module: int, connector: int) -> tuple[int, int] | None:
        """The free face of another module nearest ``module``'s free ``connector`` that can link
        with it, if the two are aligned within the docking tolerance; else None."""
        with self.lock:
            w = self.world
            docked = {end for link in w.links() for end in link.ends()}
            if (module, connector) in docked:
                return None
            here = w.connector_pose(module, connector)[0]
            faces = range(1, w.topology.profile.connector_count + 1)
            free = [
                (m, c)
                for m in range(w.size)
                for c in faces
                if m != module and (m, c) not in docked and w.topology.profile.can_link(connector, c)
            ]
            if not free:
                return None
            m, c = min(free, key=lambda end: math.dist(here, w.connector_pose(*end)[0]))
            aligned = w.aligned(module, connector, m, c, DOCK_TOLERANCE_M, DOCK_TOLERANCE_DEG)
            return (m, c) if aligned else None

    def horn_closed(self, module: int) -> bool:
        """Whether ``module``'s latch holds now (its horn past the pins): read under its bus's lock."""
        with self.emulators[module].lock:
            return self.latches[module].is_past_the_pins

    def measure(self, names: Iterable[str]) -> tuple[str, ...]:
        """From now on :meth:`readings` computes those of ``names`` that physics provides
        other than the joints' (the modules read those from their servos); returns them."""
        self._sensors = PhysicsSensors(self.world, [n for n in names if n not in JOINT_SENSORS])
        return self._sensors.names

    def readings(self, modules: Sequence[int]) -> dict[int, dict[str, float]]:
        """What each listed module's IMU, infrared pairs and ground contact read now (the
        sensors :meth:`measure` chose), in the profile's units."""
        if self._sensors is None or not self._sensors.names:
            return {m: {} for m in modules}
        with self.lock:
            return self._sensors.read(modules)

    def port(self, module: int) -> str:
        """The serial port module ``module``'s servos answer on."""
        return self.emulators[module].port_path

    def advance(self, now: float | None = None) -> None:
        """Step physics up to wall-clock ``now`` (monotonic seconds)."""
        now = time.monotonic() if now is None else now
        if self._t0 is None:
            self._t0 = now
        due = int((now - self._t0) * self.world.physics_hz) - self._steps
        if due <= 0:
            return
        limit = int(MAX_CATCH_UP_S * self.world.physics_hz)
        if due > limit:  # do not try to catch up a long stall: let simulated time slip
            self._t0 += (due - limit) / self.world.physics_hz
            due = limit
        with self.lock:
            self.world.step(due)
        self._steps += due

    def undock(self, module: int, connector: int) -> None:
        with self.lock:
            self.world.undock(module, connector)

    def aligned(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        with self.lock:
            return self.world.aligned(a, a_conn, b, b_conn, DOCK_TOLERANCE_M, DOCK_TOLERANCE_DEG)

    def dock(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        with self.lock:
            return self.world.dock(a, a_conn, b, b_conn, tolerance_m=DOCK_TOLERANCE_M, tolerance_deg=DOCK_TOLERANCE_DEG)

    def sample(self) -> tuple[float, list[tuple[float, float]], tuple[float, float, float]]:
        """(simulated s, each module's (DOF1, DOF2) in degrees, the centroid): a plot's sample."""
        with self.lock:
            w = self.world
            return w.time, [w.joint_angles(m) for m in range(w.topology.size)], w.centroid()

    def displacement(self) -> float:
        """Metres the robot moved along the direction its head faced at the start."""
        if self._final is not None:
            return self._final[0]
        with self.lock:
            return self.world.travel(self.start_centroid)

    @property
    def simulated_s(self) -> float:
        return self._final[1] if self._final is not None else self.world.time

    def close(self) -> None:
        """Stop the emulators and the world; the last figures stay readable."""
        for emulator in self.emulators:
            emulator.stop()
        self.emulators.clear()
        if self._final is None and self.world.client >= 0 and hasattr(self, "start_centroid"):
            self._final = (self.displacement(), self.world.time)
        with self.lock:
            self.world.close()
