"""Servo faults from the emulator reach the module runtime as reported actuator faults; the
module keeps running its program throughout, and recovers when the servo does."""

from __future__ import annotations

from pathlib import Path

import pytest

from dh2rt.compiler import compile_file, compile_source
from dh2rt.errors import ServoModelMismatch, ServoNotFound
from dh2rt.program import CompiledProgram
from dh2rt.runtime import HEALTH_EVERY, ModuleRuntime
from dh2rt.testing import FakeClock
from dh2rt.transport.inproc import InprocBus, InprocTransport
from dh2rt.wire.frame import FrameCodec
from drivers.base import ServoSensors
from drivers.dxl_table import GOAL_POSITION, deg_to_ticks
from drivers.dynamixel import DynamixelDriver
from hil.servo_emulator import ServoEmulator

ROOT = Path(__file__).resolve().parents[2]
# a generous reply timeout: the emulator shares this process's GIL with the SDK's busy wait
LATENCY_MS = 60


@pytest.fixture(scope="module")
def caterpillar() -> CompiledProgram:
    return compile_file(str(ROOT / "examples" / "caterpillar.dh2"))


def lone_head(program: CompiledProgram, driver: DynamixelDriver) -> ModuleRuntime:
    codec = FrameCodec(program.vocabulary, program.profile.connector_count)
    return ModuleRuntime(program, InprocTransport(codec, bus=InprocBus()), driver=driver, clock=FakeClock(0.001))


@pytest.mark.parametrize(
    ("fault", "words"),
    [
        ("no_reply", "did not answer"),
        ("crc_error", "bad CRC"),
        ("hardware_alert", "overload"),
        ("wrong_model", "model"),
    ],
)
def test_fault_is_reported_module_keeps_running_and_recovers(
    caterpillar: CompiledProgram, fault: str, words: str
) -> None:
    with ServoEmulator((1, 2)) as emulator:
        emulator.start()
        with DynamixelDriver(emulator.port_path, latency_timer_ms=LATENCY_MS) as driver:
            rt = lone_head(caterpillar, driver)
            for _ in range(2 * HEALTH_EVERY):
                rt.step()
            assert rt.actuator_fault is None
            kwargs = {"hardware_bits": 0x20} if fault == "hardware_alert" else {}
            emulator.set_fault(2, fault, **kwargs)  # type: ignore[arg-type]
            sent_before = rt.engine.counters["sent"]
            reported = None
            for _ in range(2 * HEALTH_EVERY):
                rt.step()  # never raises
                reported = reported or rt.status()["actuator_fault"]
            # reported at the next health check, with words that say what is wrong
            assert reported is not None and words.lower() in reported.lower(), reported
            assert rt.stats.actuator_faults >= 1
            assert any("actuator fault" in line for line in rt.log)
            # the program runs on: the head still emits its four hormones per ClockCycle
            assert rt.engine.counters["sent"] - sent_before >= 2 * HEALTH_EVERY // caterpillar.clock_cycle * 4
            if fault == "hardware_alert":
                # recover() rebooted the servo, which clears the alert: already back
                assert rt.actuator_fault is None
            else:
                assert rt.actuator_fault is not None  # lasts as long as the servo is faulty
                emulator.clear_faults(2)
                for _ in range(2 * HEALTH_EVERY):
                    rt.step()
                assert rt.actuator_fault is None, rt.log
            assert any("actuators recovered" in line for line in rt.log)
            # commands reach the servos again: the goal registers follow the engine's targets
            for _ in range(caterpillar.clock_cycle):
                rt.step()
            dof1, dof2 = rt.engine.dof
            driver.read_positions()  # a round trip: the emulator has handled the last (unacknowledged) write
            assert emulator.servo(1).get(GOAL_POSITION) == deg_to_ticks(dof1)
            assert emulator.servo(2).get(GOAL_POSITION) == deg_to_ticks(dof2)
            assert dof1 in (45.0, -45.0)


def test_missing_servo_and_wrong_model_fail_clearly_at_open() -> None:
    with ServoEmulator((1,)) as emulator:  # no servo with id 2
        emulator.start()
        with pytest.raises(ServoNotFound, match="2"):
            DynamixelDriver(emulator.port_path, latency_timer_ms=LATENCY_MS)
    with ServoEmulator((1, 2), model_number=1060) as emulator:  # an XL430, not the XM430 expected
        emulator.start()
        with pytest.raises(ServoModelMismatch, match="1060"):
            DynamixelDriver(emulator.port_path, latency_timer_ms=LATENCY_MS)


HOLD = """
program hold
const ClockCycle = 4
sensor pos1, load1
receptor hold { DOF1(25); keep_alive() }
"""


@pytest.mark.parametrize("phase", [0, 7])
def test_servos_that_are_gone_cost_a_few_reply_timeouts_not_one_a_cycle(phase: int) -> None:
    """Both servos stop answering while the module reads them as sensors too: each request
    then waits out its reply timeout (122 ms here). The runtime tries recover() only at its
    health checks (one every HEALTH_EVERY cycles) and the sensor feed backs off a failing
    source, so over 2 x HEALTH_EVERY cycles a handful of requests go out, not several a cycle
    (before: health() and recover() every cycle while the fault lasted, which stretched each
    cycle by three timeouts, and the modules of the loop ran 1-10 cycles of 200)."""
    with ServoEmulator((1, 2)) as emulator:
        emulator.start()
        with DynamixelDriver(emulator.port_path, latency_timer_ms=LATENCY_MS) as driver:
            program = compile_source(HOLD, "hold.dh2")
            codec = FrameCodec(program.vocabulary, program.profile.connector_count)
            rt = ModuleRuntime(
                program, InprocTransport(codec, bus=InprocBus()), driver=driver, timer_phase=phase,
                clock=FakeClock(0.001),
            )  # fmt: skip
            feedback: list[int] = []

            def servos() -> dict[str, float]:
                feedback.append(rt.cycle)
                return ServoSensors(driver).read()

            rt.add_sensor_source(servos, label="servos")
            for _ in range(HEALTH_EVERY):
                rt.step()
            assert rt.actuator_fault is None and rt.sensing.faults == 0
            assert 0 < rt.status()["sensors"]["pos1"] <= 25  # on its way to DOF1(25)
            for dxl_id in (1, 2):
                emulator.set_fault(dxl_id, "no_reply")
            before = emulator.packets_received
            for _ in range(2 * HEALTH_EVERY):
                rt.step()
            requests = emulator.packets_received - before
            assert rt.actuator_fault is not None and "did not answer" in rt.actuator_fault
            # health(): 2 PINGs; then recover(): 1 PING (it stops at the first servo gone);
            # the feed: reads 1, 2, 4, 8, 16 turns apart after the first failure
            assert requests <= 3 + 6, (requests, feedback[-8:], rt.log)
            assert rt.sensing.faults >= 3
            emulator.clear_faults()
            for _ in range(2 * HEALTH_EVERY):
                rt.step()
            assert rt.actuator_fault is None, rt.log
