"""A module runtime's sensors (dh2rt.sensing through ModuleRuntime): sources read before the
engine runs, values rounded and clamped to the profile, failing reads counted and logged,
pushed readings, and ``sense`` overrides that nothing overwrites."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator, Mapping

import pytest

from dh2rt.compiler import compile_source
from dh2rt.errors import DriverError, TopologyError
from dh2rt.program import CompiledProgram
from dh2rt.runtime import ModuleRuntime
from dh2rt.testing import FakeClock
from dh2rt.transport.inproc import InprocBus, InprocTransport
from dh2rt.wire.frame import FrameCodec
from drivers.base import SensorSources, ServoSensors
from drivers.recording import RecordingDriver

SOURCE = """
program tilt
const ClockCycle = 4
sensor roll, contact, pos1
var seen = 0
receptor tipped when S.roll > 45 or S.roll < -45 { DOF2(30); keep_alive() }
receptor upright when S.roll <= 45 and S.roll >= -45 { DOF2(0); keep_alive() }
receptor copy { V.seen = S.roll; keep_alive() }
"""


@pytest.fixture(scope="module")
def tilt() -> CompiledProgram:
    return compile_source(SOURCE, "tilt.dh2")


@pytest.fixture
def runtime(tilt: CompiledProgram) -> Iterator[ModuleRuntime]:
    codec = FrameCodec(tilt.vocabulary, tilt.profile.connector_count)
    rt = ModuleRuntime(tilt, InprocTransport(codec, bus=InprocBus()), clock=FakeClock(0.001), record=True)
    yield rt
    rt.close()


class Imu:
    """A sensor source whose readings the test sets; it can fail on demand."""

    def __init__(self) -> None:
        self.roll = 0.0
        self.fail: str | None = None
        self.reads = 0

    @property
    def names(self) -> tuple[str, ...]:
        return ("roll", "pitch")

    def read(self) -> Mapping[str, float]:
        self.reads += 1
        if self.fail:
            raise DriverError(self.fail)
        return {"roll": self.roll, "pitch": 3.0}


def test_a_source_fills_s_before_the_engine_runs_rounded_and_clamped(runtime: ModuleRuntime) -> None:
    imu = Imu()
    assert runtime.add_sensor_source(imu)
    for roll, expected_s, dof2 in ((12.6, 13, 0), (60.0, 60, 30), (-400.0, -180, 30), (44.5, 44, 0)):
        imu.roll = roll
        runtime.step()
        assert runtime.engine.sensors[0] == expected_s
        assert runtime.engine.var("seen") == expected_s  # the receptor read it in the same cycle
        assert runtime.engine.dof[1] == dof2
        assert runtime.records[-1]["sensors"]["roll"] == expected_s
    assert runtime.status()["sensors"] == {"roll": 44, "contact": 0, "pos1": 0}


def test_a_failing_read_is_a_counted_logged_fault_and_the_last_value_holds(runtime: ModuleRuntime) -> None:
    imu = Imu()
    assert runtime.add_sensor_source(imu, label="imu")
    assert runtime.sensing.reading == ("imu",)
    imu.roll = 70.0
    runtime.step()
    imu.fail = "I2C bus: no ACK"
    read_at: list[int] = []
    for _ in range(70):
        reads = imu.reads
        runtime.step()
        if imu.reads > reads:
            read_at.append(runtime.cycle - 1)
    assert runtime.cycle == 71  # never stopped
    assert runtime.engine.sensors[0] == 70 and runtime.engine.dof[1] == 30
    # read again after 1, 2, 4, 8, 16, then every 32 turns skipped: a device that is gone
    # (each read waiting out a timeout) costs the loop now and then, not every cycle
    assert read_at == [1, 3, 6, 11, 20, 37, 70]
    assert runtime.counters["sensor_faults"] == len(read_at)
    assert [line for line in runtime.log if "sensor fault" in line] == [
        "cycle 1: sensor fault: imu: DriverError: I2C bus: no ACK"
    ]  # logged once while the message stays the same
    assert runtime.status()["last_sensor_fault"] == "cycle 70: imu: DriverError: I2C bus: no ACK"
    imu.fail = None
    imu.roll = 0.0
    for _ in range(33):  # the next turn comes at cycle 103: read, and every cycle again after it
        runtime.step()
    assert runtime.engine.sensors[0] == 0 and runtime.counters["sensor_faults"] == len(read_at)
    reads = imu.reads
    for _ in range(5):
        runtime.step()
    assert imu.reads == reads + 5


@pytest.mark.parametrize("every", [1, 3])
def test_a_failing_source_backs_off_in_its_own_turns(tilt: CompiledProgram, every: int) -> None:
    codec = FrameCodec(tilt.vocabulary, tilt.profile.connector_count)
    rt = ModuleRuntime(tilt, InprocTransport(codec, bus=InprocBus()), timer_phase=1, clock=FakeClock(0.001))
    try:
        read_at: list[int] = []

        def broken() -> Mapping[str, float]:
            read_at.append(rt.cycle)
            raise OSError("no device")

        rt.add_sensor_source(broken, every=every)
        for _ in range(40 * every):
            rt.step()
        turns = [c // every for c in read_at]
        assert all(c % every == 1 % every for c in read_at)
        assert [b - a for a, b in itertools.pairwise(turns)][:5] == [2, 3, 5, 9, 17]
    finally:
        rt.close()


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, "12", None])
def test_a_value_that_is_not_a_number_is_a_fault(runtime: ModuleRuntime, bad: object) -> None:
    values: dict[str, object] = {"roll": 20.0}
    runtime.add_sensor_source(lambda: values)  # type: ignore[arg-type,return-value]
    runtime.step()
    values["roll"] = bad
    runtime.step()
    assert runtime.engine.sensors[0] == 20
    assert runtime.counters["sensor_faults"] == 1
    assert "not a number" in (runtime.status()["last_sensor_fault"] or "")


def test_a_name_outside_the_profile_is_refused_or_a_fault(runtime: ModuleRuntime) -> None:
    class Light:
        names = ("light",)

        def read(self) -> Mapping[str, float]:
            return {"light": 1.0}

    with pytest.raises(TopologyError, match="no sensor 'light'"):
        runtime.add_sensor_source(Light())
    runtime.add_sensor_source(lambda: {"light": 3.0, "roll": 5.0}, label="board")
    runtime.step()
    assert runtime.engine.sensors[0] == 5
    assert runtime.counters["sensor_faults"] == 1
    assert "board: no sensor 'light' in profile conro" in (runtime.status()["last_sensor_fault"] or "")


def test_a_source_of_undeclared_sensors_is_never_read(runtime: ModuleRuntime) -> None:
    class Ir:
        names = ("ir_front", "ir_front_align")
        reads = 0

        def read(self) -> Mapping[str, float]:
            Ir.reads += 1
            return {"ir_front": 40.0}

    assert not runtime.add_sensor_source(Ir())
    runtime.step()
    assert Ir.reads == 0


@pytest.mark.parametrize("every", [1, 2, 3, 5])
@pytest.mark.parametrize("phase", [0, 1, 4, 7])
def test_a_source_read_every_n_cycles_at_the_modules_offset(tilt: CompiledProgram, every: int, phase: int) -> None:
    codec = FrameCodec(tilt.vocabulary, tilt.profile.connector_count)
    rt = ModuleRuntime(tilt, InprocTransport(codec, bus=InprocBus()), timer_phase=phase, clock=FakeClock(0.001))
    try:
        read_at: list[int] = []
        rt.add_sensor_source(lambda: read_at.append(rt.cycle) or {"roll": float(rt.cycle)}, every=every)  # type: ignore[func-returns-value]
        for _ in range(20):
            rt.step()
        assert read_at == [c for c in range(20) if c % every == phase % every]
        assert rt.engine.sensors[0] == read_at[-1]
    finally:
        rt.close()


def test_sense_overrides_sources_and_pushes_from_then_on(runtime: ModuleRuntime) -> None:
    imu = Imu()
    runtime.add_sensor_source(imu)
    imu.roll = 10.0
    runtime.step()
    runtime.sense("roll", 90)
    assert runtime.engine.sensors[0] == 90  # at once, before the next cycle
    for roll in (0.0, -30.0, 170.0):
        imu.roll = roll
        runtime.push_readings({"roll": roll, "contact": 1})
        runtime.step()
        assert runtime.engine.sensors[0] == 90 and runtime.engine.dof[1] == 30
        assert runtime.engine.sensors[1] == 1  # the others still follow
    runtime.sense("roll", 0)
    runtime.step()
    assert runtime.engine.sensors[0] == 0


def test_sense_refuses_what_the_profile_or_program_does_not_allow(runtime: ModuleRuntime) -> None:
    with pytest.raises(TopologyError, match=r"sensor roll reads -180\.\.180 deg, not 200"):
        runtime.sense("roll", 200)
    with pytest.raises(TopologyError, match="does not declare sensor pitch"):
        runtime.sense("pitch", 3)
    with pytest.raises(TopologyError, match="no sensor 'light'"):
        runtime.sense("light", 3)


def test_pushed_readings_land_in_the_next_cycle_only_once(runtime: ModuleRuntime) -> None:
    runtime.push_readings({"roll": 33.4, "contact": 1})
    runtime.step()
    assert (runtime.engine.sensors[0], runtime.engine.sensors[1]) == (33, 1)
    runtime.step()  # nothing new pushed: the last readings hold
    assert (runtime.engine.sensors[0], runtime.engine.sensors[1]) == (33, 1)
    assert runtime.sensing.pushes == 1


def test_servo_sensors_from_a_driver_reach_s(runtime: ModuleRuntime) -> None:
    driver = RecordingDriver()
    runtime.driver = driver
    runtime.add_sensor_source(SensorSources([ServoSensors(driver)]))
    runtime.step()  # DOF targets are commanded after the engine runs; read back the next cycle
    driver.set_targets(-37.4, 12.0)
    runtime.step()
    assert runtime.engine.sensors[2] == -37


LEVEL = """
program level
const ClockCycle = 4
sensor pitch, roll
receptor steep when S.pitch > 20 { DOF1(10); keep_alive() }
"""

BLIND = """
program blind
const ClockCycle = 4
receptor idle { keep_alive() }
"""


def test_a_program_switch_keeps_what_both_programs_read_and_reads_what_the_new_one_declares(
    runtime: ModuleRuntime,
) -> None:
    """A rollout switches the program at a cycle start: the new engine gets the sensors both
    declare (values and what ``sense`` forced), sources are read for the new declarations,
    and a program that reads no sensor has nothing read for it."""
    imu = Imu()
    runtime.add_sensor_source(imu, label="imu")
    imu.roll = 12.0
    runtime.step()
    runtime.sense("contact", 1)
    runtime.step()
    level = compile_source(LEVEL, "level.dh2")
    runtime.switch_program(level, 2, "switched to level")
    assert runtime.engine.sensors == [0, 12]  # pitch not read yet; roll carried over
    assert runtime.sensing.forced == {} and any("no longer forced" in line for line in runtime.log)
    imu.roll = 50.0
    runtime.step()
    assert runtime.engine.sensors == [3, 50]  # the IMU's pitch is read now
    assert runtime.records[-1]["sensors"] == {"pitch": 3, "roll": 50}
    runtime.sense("roll", -5)
    runtime.switch_program(compile_source(BLIND, "blind.dh2"), 3, "switched to blind")
    reads = imu.reads
    assert runtime.sensing.reading == ()
    runtime.step()
    assert imu.reads == reads and runtime.engine.sensors == []
    runtime.switch_program(level, 4, "back to level")
    runtime.step()
    assert imu.reads == reads + 1 and runtime.engine.sensors == [3, 50]


def test_a_stand_in_reading_reaches_a_sensor_a_switched_to_program_declares_anew(runtime: ModuleRuntime) -> None:
    runtime.sensing.stand_in({"pitch": 7, "roll": 4})
    runtime.step()
    assert runtime.engine.sensors[0] == 4  # tilt reads roll (and not pitch)
    runtime.push_readings({"roll": 30})
    runtime.step()
    runtime.switch_program(compile_source(LEVEL, "level.dh2"), 2, "switched to level")
    assert runtime.engine.sensors == [7, 30]  # pitch: the stand-in; roll: carried over
    runtime.step()
    assert runtime.records[-1]["sensors"] == {"pitch": 7, "roll": 30}
