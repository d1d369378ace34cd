"""Servo feedback as sensors: present position and load through the real dynamixel-sdk and the
Protocol 2.0 emulator (kinematic horns, and PyBullet joints), ServoSensors and SensorSources."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

import pybullet as p
import pytest

from dh2rt.errors import DriverConfigError, DriverError
from dh2rt.profile import CONRO
from dh2rt.topology import parse_spec
from drivers import dxl_table as dxt
from drivers.base import SERVO_SENSORS, Feedback, JointLimits, ModuleDriver, SensorSource, SensorSources, ServoSensors
from drivers.dynamixel import DynamixelDriver
from drivers.recording import RecordingDriver
from hil.physics_stand_in import PhysicsStandIn
from hil.servo_emulator import ServoEmulator
from hil.servo_joints import KinematicJoint
from sim.sensors import ModuleSensors, PhysicsSensors
from sim.world import World

#: A generous reply timeout (2 x 250 ms): the in-process emulator shares two busy cores with
#: PyBullet, which holds the GIL while it steps (a reply was seen 1.2 s late on a loaded
#: machine); the figures under test are not timings.
LATENCY_MS = 250.0


class LoadedJoint(KinematicJoint):
    """A kinematic horn carrying a set load (percent of the maximum torque)."""

    def __init__(self, load: float) -> None:
        super().__init__()
        self.load = load

    def present_load_percent(self) -> float:
        return self.load


def wait_for(predicate: Callable[[], bool], timeout: float = 3.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.02)


@pytest.mark.parametrize(
    ("model", "resolution"),
    [(dxt.MODEL_XM430_W350, 100 / 1193), (dxt.MODEL_XL430_W250, dxt.LOAD_UNIT_PERCENT)],
)
def test_loads_read_as_percent_of_the_maximum_whatever_the_model(model: int, resolution: float) -> None:
    """Address 126 is Present Current on an XM430 (units of its Current Limit) and Present
    Load on an XL430 (0.1 %): both read back as the same percentages."""
    joints = {1: LoadedJoint(37.5), 2: LoadedJoint(-12.25)}
    with (
        ServoEmulator(joints, model_number=model) as emu,
        DynamixelDriver(emu.port_path, expected_model=model, latency_timer_ms=LATENCY_MS) as drv,
    ):
        assert drv.models == [model, model]
        loads = drv.read_loads()
        assert loads == pytest.approx((37.5, -12.25), abs=resolution)
        raw = emu.servo(1).get(dxt.PRESENT_LOAD)
        assert raw == (375 if model == dxt.MODEL_XL430_W250 else round(0.375 * 1193))
        joints[1].load = 150.0  # beyond the servo's range: it reports its limit
        assert drv.read_loads()[0] == pytest.approx(100.0, abs=resolution)
        assert emu.error is None


def test_feedback_is_positions_and_loads_in_one_read() -> None:
    joints = {1: LoadedJoint(20.0), 2: LoadedJoint(-5.0)}
    with ServoEmulator(joints) as emu, DynamixelDriver(emu.port_path, latency_timer_ms=LATENCY_MS) as drv:
        drv.set_targets(40.0, -30.0)
        wait_for(lambda: drv.read_positions() == pytest.approx((40.0, -30.0), abs=dxt.DEG_PER_TICK))
        before = emu.packets_received
        fb = drv.read_feedback()
        assert emu.packets_received == before + 1  # one SYNC_READ for both servos, both figures
        assert fb.positions == pytest.approx((40.0, -30.0), abs=dxt.DEG_PER_TICK)
        assert fb.loads == pytest.approx((20.0, -5.0), abs=0.1)
        readings = ServoSensors(drv).read()
        assert readings == pytest.approx({"pos1": 40.0, "pos2": -30.0, "load1": 20.0, "load2": -5.0}, abs=0.1)


def test_torque_off_reports_no_load() -> None:
    joints = {1: LoadedJoint(50.0), 2: LoadedJoint(50.0)}
    with ServoEmulator(joints) as emu, DynamixelDriver(emu.port_path, latency_timer_ms=LATENCY_MS) as drv:
        assert drv.read_loads()[0] == pytest.approx(50.0, abs=0.1)
        drv.set_torque(False)
        assert drv.read_loads() == (0.0, 0.0)


def test_the_loop_reads_the_pybullet_joints_through_the_emulator() -> None:
    """The loop's physics stand-in (servo emulators on PyBullet joints, one lock): a module
    hung by its centre; its Dynamixel driver reads the angles and the gravity load of the
    very joints the physics sensors read."""
    with PhysicsStandIn(parse_spec("snake:1")) as stand_in:
        w = stand_in.world
        with stand_in.lock:
            body = w.body(0)
            p.resetBasePositionAndOrientation(body, (0.0, 0.0, 0.5), (0.0, 0.0, 0.0, 1.0), physicsClientId=w.client)
            p.changeDynamics(body, -1, mass=0.0, physicsClientId=w.client)
        with DynamixelDriver(stand_in.port(0), latency_timer_ms=LATENCY_MS) as drv:
            drv.set_targets(-30.0, 20.0)
            landed = pytest.approx((-30.0, 20.0), abs=dxt.DEG_PER_TICK)
            wait_for(lambda: w.driver(0).targets == landed)  # SYNC_WRITE has no reply
            with stand_in.lock:
                w.step(240)
                physics = PhysicsSensors(w, SERVO_SENSORS).read([0])[0]
            fb = drv.read_feedback()
            assert fb.positions == pytest.approx((physics["pos1"], physics["pos2"]), abs=dxt.DEG_PER_TICK)
            assert fb.positions == pytest.approx((-30.0, 20.0), abs=1.0)
            assert fb.loads[0] == pytest.approx(physics["load1"], abs=0.1)
            lever = math.cos(math.radians(30.0)) * w.model.front.half[0]
            expected = -100.0 * w.model.front.mass * 9.81 * lever / w.model.dof1.max_torque_nm
            assert fb.loads[0] == pytest.approx(expected, abs=0.2)
            assert stand_in.emulators[0].error is None


def test_servo_sensors_are_named_as_the_profile_names_them() -> None:
    assert set(SERVO_SENSORS) <= set(CONRO.sensor_names)
    assert ServoSensors(RecordingDriver()).read() == {"pos1": 0.0, "pos2": 0.0, "load1": 0.0, "load2": 0.0}


class _Limp(ModuleDriver):
    """A driver whose servos cannot sense their load (the base class's default)."""

    limits = (JointLimits(), JointLimits())

    def set_targets(self, dof1_deg: float, dof2_deg: float) -> None:
        pass

    def read_positions(self) -> tuple[float, float]:
        return (1.0, 2.0)

    def set_torque(self, enabled: bool) -> None:
        pass


def test_a_driver_without_load_sensing_says_so() -> None:
    with pytest.raises(DriverError, match="_Limp cannot read its servos' loads"):
        ServoSensors(_Limp()).read()


class _Fixed(SensorSource):
    def __init__(self, **values: float) -> None:
        self.values = values

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.values)

    def read(self) -> dict[str, float]:
        return dict(self.values)


def test_sources_read_as_one() -> None:
    both = SensorSources([ServoSensors(RecordingDriver()), _Fixed(roll=3.0, pitch=-1.0)])
    assert both.names == (*SERVO_SENSORS, "roll", "pitch")
    assert both.read() == {"pos1": 0.0, "pos2": 0.0, "load1": 0.0, "load2": 0.0, "roll": 3.0, "pitch": -1.0}
    with pytest.raises(DriverConfigError, match="sensor roll is read by both _Fixed and _Fixed"):
        SensorSources([_Fixed(roll=1.0), _Fixed(roll=2.0)])
    driver = RecordingDriver()
    driver.set_targets(10.0, -10.0)
    assert driver.read_feedback() == Feedback((10.0, -10.0), (0.0, 0.0))  # the default: both reads


def test_a_module_reads_its_physics_sensors_as_a_source() -> None:
    """The physics behind the interface an IMU on I2C would have: one module's readings."""
    with World(parse_spec("snake:2")) as w:
        w.step(24)
        lock = threading.Lock()
        source = ModuleSensors(PhysicsSensors(w, ["roll", "contact", "ir_front"]), 1, lock)
        assert source.names == ("roll", "ir_front", "contact")
        got = source.read()
        assert got["ir_front"] == 1.0 and got["contact"] == 1.0 and abs(got["roll"]) < 1.0
        # it reads under the lock the physics steps under
        done = threading.Event()

        def read() -> None:
            source.read()
            done.set()

        reader = threading.Thread(target=read)
        with lock:
            reader.start()
            assert not done.wait(0.2)
        reader.join(5)
        assert done.is_set()
