"""The PyBullet stand-in driver: one simulated CONRO module's two joints.

PyBullet is imported when a driver is constructed, never when ``drivers`` is imported, so the
runtime and the hardware drivers do not need the ``[sim]`` extra.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from dh2rt.errors import DriverError
from drivers.base import Health, JointLimits, ModuleDriver


class PyBulletDriver(ModuleDriver):
    """Drives DOF1 and DOF2 of one multibody through one physics client.

    ``set_targets`` uses position control bounded by each joint's servo torque and speed;
    targets are sent to the engine only when they change, so a control loop may call it
    every cycle. ``set_torque(False)`` makes both joints limp (a velocity motor with zero
    force); ``set_torque(True)`` holds the present angles until the next target.
    """

    def __init__(
        self,
        client_id: int,
        body_id: int,
        joint_indices: Sequence[int] = (0, 1),
        limits: tuple[JointLimits, JointLimits] | None = None,
    ) -> None:
        import pybullet  # lazy: drivers must import without the [sim] extra

        if len(joint_indices) != 2:
            raise DriverError(f"PyBulletDriver: joint_indices must name 2 joints, got {list(joint_indices)}")
        self._p: Any = pybullet
        self.client_id = client_id
        self.body_id = body_id
        self.joints = (int(joint_indices[0]), int(joint_indices[1]))
        if limits is not None:
            self.limits = limits
        self._targets: tuple[float, float] | None = None
        self._torque = True
        self._closed = False
        try:
            count = self._p.getNumJoints(body_id, physicsClientId=client_id)
        except self._p.error as exc:
            raise DriverError(f"PyBulletDriver: client {client_id} body {body_id}: {exc}") from None
        for j in self.joints:
            if not 0 <= j < count:
                raise DriverError(f"PyBulletDriver: body {body_id} has no joint {j} (it has {count})")

    @property
    def targets(self) -> tuple[float, float] | None:
        """The last commanded angles (degrees, after clamping), or None before the first."""
        return self._targets

    @property
    def torque_enabled(self) -> bool:
        return self._torque

    def set_targets(self, dof1_deg: float, dof2_deg: float) -> None:
        targets = (self.limits[0].clamp(dof1_deg), self.limits[1].clamp(dof2_deg))
        if targets == self._targets:
            return
        self._targets = targets
        if self._torque:
            self._send(targets)

    def _send(self, targets: tuple[float, float]) -> None:
        p = self._p
        self._check_open()
        try:
            for joint, deg, lim in zip(self.joints, targets, self.limits, strict=True):
                # setJointMotorControlArray has no per-joint maxVelocity; the servo speed
                # limit matters for the gait, so use the per-joint call.
                p.setJointMotorControl2(
                    self.body_id,
                    joint,
                    p.POSITION_CONTROL,
                    targetPosition=math.radians(deg),
                    force=lim.max_torque_nm,
                    maxVelocity=math.radians(lim.max_speed_dps),
                    physicsClientId=self.client_id,
                )
        except p.error as exc:
            raise DriverError(f"PyBulletDriver body {self.body_id}: {exc}") from None

    def read_positions(self) -> tuple[float, float]:
        self._check_open()
        p = self._p
        try:
            states = p.getJointStates(self.body_id, self.joints, physicsClientId=self.client_id)
        except p.error as exc:
            raise DriverError(f"PyBulletDriver body {self.body_id}: {exc}") from None
        return (math.degrees(states[0][0]), math.degrees(states[1][0]))

    def read_loads(self) -> tuple[float, float]:
        """The torque each joint motor applied in the last physics step, in percent of the
        joint's ``max_torque_nm`` (0 while limp)."""
        self._check_open()
        p = self._p
        try:
            states = p.getJointStates(self.body_id, self.joints, physicsClientId=self.client_id)
        except p.error as exc:
            raise DriverError(f"PyBulletDriver body {self.body_id}: {exc}") from None
        return (
            100.0 * states[0][3] / self.limits[0].max_torque_nm,
            100.0 * states[1][3] / self.limits[1].max_torque_nm,
        )

    def set_torque(self, enabled: bool) -> None:
        self._check_open()
        p = self._p
        if enabled == self._torque:
            return
        self._torque = enabled
        if enabled:
            # Hold where the joints are now unless a target is pending.
            self._targets = self._targets if self._targets is not None else self.read_positions()
            self._send(self._targets)
            return
        try:
            p.setJointMotorControlArray(
                self.body_id,
                list(self.joints),
                p.VELOCITY_CONTROL,
                targetVelocities=[0.0, 0.0],
                forces=[0.0, 0.0],
                physicsClientId=self.client_id,
            )
        except p.error as exc:
            raise DriverError(f"PyBulletDriver body {self.body_id}: {exc}") from None

    def health(self) -> Health:
        """No faults unless closed; ``details`` holds each joint's applied motor torque (N*m)."""
        if self._closed:
            return Health(faults=("closed",))
        p = self._p
        try:
            states = p.getJointStates(self.body_id, self.joints, physicsClientId=self.client_id)
        except p.error as exc:
            return Health(faults=(f"simulation: {exc}",))
        return Health(details={"dof1_torque_nm": float(states[0][3]), "dof2_torque_nm": float(states[1][3])})

    def close(self) -> None:
        # The World owns the body and the client; the driver only stops using them.
        self._closed = True

    def _check_open(self) -> None:
        if self._closed:
            raise DriverError(f"PyBulletDriver body {self.body_id}: driver is closed")
