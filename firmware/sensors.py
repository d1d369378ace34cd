"""A module process's sensors: where ``dh2rt module`` gets each ``S.name`` from.

* ``pos1``, ``pos2``, ``load1``, ``load2``: the servos' present position and load, one
  Dynamixel SYNC_READ (``drivers.base.ServoSensors``) every ``[sensors] servo_every``
  cycles, through whatever driver the module has now (real servos, the servo emulator of the
  HIL world's PyBullet stand-in, or the recording stand-in, whose servos are ideal: present
  angle = target, no load). While the servos are missing (an actuator fault), nothing is read
  and the sensors keep their last values; a failed read is a sensor fault (counted, logged).
  Read only when the program declares one of them.
* sensors with no device on the module (an IMU, infrared): ``[sensors] stand_in`` holds fixed
  readings, written once before the first cycle.
* in the loop, the world pushes what its physics measures (IMU, infrared, ground contact):
  :class:`firmware.control.Readings`, handled by the module host;
* ``sense`` events (:class:`firmware.control.Sense`) force a value from then on.
"""

from __future__ import annotations

from collections.abc import Callable

from dh2rt.errors import ModuleConfigError, TopologyError
from dh2rt.runtime import ModuleRuntime
from drivers.base import SERVO_SENSORS, ModuleDriver, SensorSource, ServoSensors
from firmware.config import ModuleConfig


class CurrentServoSensors(SensorSource):
    """The servos' present position and load through the driver the module holds *now*
    (``driver_of()``; None while its servos are missing: nothing is read)."""

    def __init__(self, driver_of: Callable[[], ModuleDriver | None]) -> None:
        self.driver_of = driver_of

    @property
    def names(self) -> tuple[str, ...]:
        return SERVO_SENSORS

    def read(self) -> dict[str, float]:
        driver = self.driver_of()
        if driver is None:
            return {}
        return ServoSensors(driver).read()


def attach_sensors(rt: ModuleRuntime, config: ModuleConfig, driver_of: Callable[[], ModuleDriver | None]) -> None:
    """Give ``rt`` its sensor sources from ``config`` (see the module docs); a stand-in value
    the profile does not allow is a ModuleConfigError naming it."""
    profile = rt.engine.profile
    for name, value in config.sensor_values.items():
        try:
            profile.sensor(name).check(value)
        except TopologyError as exc:
            raise ModuleConfigError(f"config sensor_values {name}: {exc}") from None
    if config.sensor_values:
        rt.sensing.stand_in(config.sensor_values)
    if config.servo_port or config.driver == "recording":

        def healthy_driver() -> ModuleDriver | None:
            # servos the runtime holds faulty are not read as sensors too: it tries recover()
            # at its health checks meanwhile, and a read of a missing servo waits its timeout
            return None if rt.actuator_fault is not None else driver_of()

        rt.add_sensor_source(CurrentServoSensors(healthy_driver), every=config.servo_sensor_every, label="servos")
