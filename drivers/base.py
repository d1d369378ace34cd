"""The one joint interface every servo driver implements.

A CONRO module has two joints: DOF1 (pitch) and DOF2 (yaw). A :class:`ModuleDriver` drives
both for one module, in degrees, so the runtime never sees ticks, radians or vendor codes.
"""

from __future__ import annotations

import abc
import enum
from dataclasses import dataclass, field

from dh2rt.closing import Closing


class Joint(enum.IntEnum):
    """A module's joints, in the order every driver uses."""

    DOF1 = 0  # pitch
    DOF2 = 1  # yaw


@dataclass(frozen=True, slots=True)
class JointLimits:
    """Angle range (degrees), speed (degrees/s) and torque (N*m) of one joint."""

    min_deg: float = -90.0
    max_deg: float = 90.0
    max_speed_dps: float = 360.0
    max_torque_nm: float = 1.5

    def clamp(self, deg: float) -> float:
        return min(self.max_deg, max(self.min_deg, deg))


@dataclass(frozen=True, slots=True)
class Health:
    """What a driver knows of its servos: ``faults`` is empty when all is well."""

    faults: tuple[str, ...] = ()
    details: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.faults


class ModuleDriver(Closing, abc.ABC):
    """Both joints of one module. Every driver is a context manager."""

    limits: tuple[JointLimits, JointLimits] = (JointLimits(), JointLimits())

    @abc.abstractmethod
    def set_targets(self, dof1_deg: float, dof2_deg: float) -> None:
        """Command both joints' goal angles (degrees), clamped to the limits."""

    @abc.abstractmethod
    def read_positions(self) -> tuple[float, float]:
        """Present angles of DOF1 and DOF2 (degrees)."""

    @abc.abstractmethod
    def set_torque(self, enabled: bool) -> None:
        """Torque on (hold and move) or off (limp) for both joints."""

    def health(self) -> Health:
        return Health()

    def close(self) -> None:
        """Release the hardware or the simulation handle (nothing by default)."""
