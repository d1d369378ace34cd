"""The horn of an emulated servo: what moves when a goal position is written.

A :class:`JointBackend` is what an :class:`~hil.servo_table.EmulatedServo` drives: by default
a :class:`KinematicJoint` (first-order servo with a speed limit, advancing in real time), or
one joint of any :class:`drivers.base.ModuleDriver` through :class:`ModuleJointAdapter` (DOF1
and DOF2 of one module on two ids), e.g. the PyBullet stand-in, whose present position and
load are then the PyBullet joint's. Backends are called from the emulator's thread.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Protocol

from dh2rt.errors import EmulatorError
from drivers import dxl_table as dxt
from drivers.base import Joint, ModuleDriver


class JointBackend(Protocol):
    """What moves one servo's horn. Positions are ticks (4096/rev, 2048 = 0 degrees)."""

    def set_goal_ticks(self, ticks: float) -> None:
        """New goal position; called only while torque is on."""

    def present_ticks(self) -> float:
        """Where the horn is now."""

    def set_torque(self, enabled: bool) -> None:
        """Torque on (hold and move to the goal) or off (limp)."""

    def set_speed_limit(self, ticks_per_s: float) -> None:
        """Largest speed the horn may move at."""

    def present_load_percent(self) -> float:
        """The torque the horn is applying, in percent of the servo's maximum, signed."""


DEFAULT_SPEED_TPS = dxt.velocity_units_to_dps(200) / dxt.DEG_PER_TICK  # X-series velocity limit 200


class KinematicJoint:
    """First-order servo with a speed limit, advancing in real time (no load, no gravity).

    The horn approaches the goal exponentially with ``time_constant_s`` but never faster than the
    speed limit; with torque off it stays where it is.
    """

    def __init__(
        self,
        start_ticks: float = dxt.CENTER_TICKS,
        speed_limit_tps: float = DEFAULT_SPEED_TPS,
        time_constant_s: float = 0.02,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if time_constant_s <= 0 or speed_limit_tps <= 0:
            raise EmulatorError(
                f"time_constant_s and speed_limit_tps must be > 0, got {time_constant_s}, {speed_limit_tps}"
            )
        self._clock = clock
        self._t = clock()
        self.position = float(start_ticks)
        self.goal = float(start_ticks)
        self.torque = False
        self.speed_limit_tps = speed_limit_tps
        self.time_constant_s = time_constant_s

    def _advance(self) -> None:
        now = self._clock()
        dt, self._t = now - self._t, now
        if not self.torque or dt <= 0:
            return
        err = self.goal - self.position
        vmax, tau = self.speed_limit_tps, self.time_constant_s
        # Saturated (speed-limited) phase while |err|/tau > vmax, then exponential decay.
        t_sat = max(0.0, (abs(err) - vmax * tau) / vmax)
        step = math.copysign(vmax * min(dt, t_sat), err)
        self.position += step
        err -= step
        if dt > t_sat:
            err *= math.exp(-(dt - t_sat) / tau)
        self.position = self.goal - err

    def set_goal_ticks(self, ticks: float) -> None:
        self._advance()
        self.goal = float(ticks)

    def present_ticks(self) -> float:
        self._advance()
        return self.position

    def set_torque(self, enabled: bool) -> None:
        self._advance()
        self.torque = enabled
        if enabled:
            self.goal = self.position

    def set_speed_limit(self, ticks_per_s: float) -> None:
        self._advance()
        self.speed_limit_tps = max(ticks_per_s, 1e-6)

    def present_load_percent(self) -> float:
        """Nothing loads a kinematic horn."""
        return 0.0


class ModuleJointAdapter:
    """Expose a :class:`ModuleDriver`'s two joints as two :class:`JointBackend` objects.

    The driver has one torque switch for both joints, so torque is on while either emulated
    servo has it on. The driver's own limits (angles, speed) govern motion, so the speed limit
    from the control table is not forwarded.
    """

    def __init__(self, driver: ModuleDriver) -> None:
        self.driver = driver
        self._goals = list(driver.read_positions())
        self._torque = [False, False]
        driver.set_torque(False)

    def joint(self, joint: Joint) -> JointBackend:
        return _AdaptedJoint(self, joint)

    def _set_goal(self, joint: Joint, deg: float) -> None:
        self._goals[joint] = deg
        self.driver.set_targets(self._goals[0], self._goals[1])

    def _set_torque(self, joint: Joint, enabled: bool) -> None:
        self._torque[joint] = enabled
        if enabled:
            # Torque on holds where the horn is: as the servo does, the goal becomes the present.
            self._goals[joint] = self.driver.read_positions()[joint]
            self.driver.set_targets(self._goals[0], self._goals[1])
        self.driver.set_torque(any(self._torque))


class _AdaptedJoint:
    def __init__(self, adapter: ModuleJointAdapter, joint: Joint) -> None:
        self._adapter = adapter
        self._joint = joint

    def set_goal_ticks(self, ticks: float) -> None:
        self._adapter._set_goal(self._joint, dxt.ticks_to_deg(ticks))

    def present_ticks(self) -> float:
        deg = self._adapter.driver.read_positions()[self._joint]
        return dxt.CENTER_TICKS + deg / dxt.DEG_PER_TICK

    def set_torque(self, enabled: bool) -> None:
        self._adapter._set_torque(self._joint, enabled)

    def set_speed_limit(self, ticks_per_s: float) -> None:
        pass

    def present_load_percent(self) -> float:
        return self._adapter.driver.read_loads()[self._joint]
