"""The one joint interface every servo driver implements, and the one sensor interface.

A CONRO module has two joints: DOF1 (pitch) and DOF2 (yaw). A :class:`ModuleDriver` drives
both for one module, in degrees, so the runtime never sees ticks, radians or vendor codes.

A :class:`SensorSource` is anything a module reads its sensors (``S.name``) from each cycle:
:class:`ServoSensors` gives the servos' present positions and loads through a driver; an IMU
on I2C or an infrared board would be another source (in simulation, ``sim.sensors`` has the
physics behind one); :class:`SensorSources` reads several as one. A source hands back raw
values in the units of the profile's sensor table (``dh2rt.profile``); whoever stores them
in a module's state rounds and clamps them with ``SensorSpec.reading``.
"""

from __future__ import annotations

import abc
import enum
from collections.abc import Sequence
from dataclasses import dataclass, field

from dh2rt.closing import Closing
from dh2rt.errors import DriverConfigError, DriverError

#: The sensors :class:`ServoSensors` provides, as the profile names them: present angles
#: (degrees) and loads (percent of the maximum torque) of DOF1 and DOF2.
SERVO_SENSORS: tuple[str, ...] = ("pos1", "pos2", "load1", "load2")


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

    def read_loads(self) -> tuple[float, float]:
        """Present load of DOF1 and DOF2: the torque each servo applies, in percent of its
        maximum, signed like the joint angle. Drivers whose servos cannot sense it raise
        DriverError (this default)."""
        raise DriverError(f"{type(self).__name__} cannot read its servos' loads")

    def read_feedback(self) -> Feedback:
        """Present positions and loads together; drivers that can read both in one bus
        transaction override this."""
        return Feedback(self.read_positions(), self.read_loads())

    def health(self) -> Health:
        return Health()

    def close(self) -> None:
        """Release the hardware or the simulation handle (nothing by default)."""


@dataclass(frozen=True, slots=True)
class Feedback:
    """What the servos report: present angles (degrees) and loads (percent, signed)."""

    positions: tuple[float, float]
    loads: tuple[float, float]


class SensorSource(abc.ABC):
    """Sensors a module reads each cycle (see the module docs)."""

    @property
    @abc.abstractmethod
    def names(self) -> tuple[str, ...]:
        """The sensors :meth:`read` reports, as the profile names them."""

    @abc.abstractmethod
    def read(self) -> dict[str, float]:
        """One reading of every sensor in :attr:`names`, in the profile's units. A source
        whose device fails raises DriverError; the module keeps its last values."""


class ServoSensors(SensorSource):
    """``pos1``, ``pos2``, ``load1``, ``load2`` from a driver's :meth:`ModuleDriver.read_feedback`."""

    def __init__(self, driver: ModuleDriver) -> None:
        self.driver = driver

    @property
    def names(self) -> tuple[str, ...]:
        return SERVO_SENSORS

    def read(self) -> dict[str, float]:
        fb = self.driver.read_feedback()
        return {"pos1": fb.positions[0], "pos2": fb.positions[1], "load1": fb.loads[0], "load2": fb.loads[1]}


class SensorSources(SensorSource):
    """Several sources read as one; no two may report the same sensor."""

    def __init__(self, sources: Sequence[SensorSource]) -> None:
        seen: dict[str, SensorSource] = {}
        for source in sources:
            for name in source.names:
                if name in seen:
                    raise DriverConfigError(
                        f"sensor {name} is read by both {type(seen[name]).__name__} and {type(source).__name__}"
                    )
                seen[name] = source
        self.sources = tuple(sources)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(name for source in self.sources for name in source.names)

    def read(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for source in self.sources:
            out.update(source.read())
        return out
