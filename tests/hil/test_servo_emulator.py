"""The servo emulator: its sans-IO core, its joint models, and the real dynamixel-sdk on a pty."""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Iterator

import dynamixel_sdk
import pytest
from dynamixel_sdk import GroupSyncRead, GroupSyncWrite, PacketHandler, PortHandler

from dh2rt.errors import EmulatorError
from dh2rt.testing import FakeClock
from drivers import dxl_table as dxt
from drivers.dynamixel import port_handler
from drivers.recording import RecordingDriver
from hil.dxl_protocol import (
    BROADCAST_ID,
    CorruptPacket,
    Instruction,
    Packet,
    decode_packet,
    encode_instruction,
)
from hil.servo_emulator import ServoEmulator
from hil.servo_joints import KinematicJoint, ModuleJointAdapter
from hil.servo_table import Fault

COMM_SUCCESS, COMM_RX_TIMEOUT, COMM_RX_CORRUPT = 0, -3001, -3002


def u16(v: int) -> bytes:
    return v.to_bytes(2, "little")


def replies(emu: ServoEmulator, packet: Packet) -> list[Packet]:
    return [decode_packet(raw) for _, raw in emu.handle(packet)]


def write(emu: ServoEmulator, dxl_id: int, field: dxt.Field, value: int) -> int:
    params = u16(field.address) + value.to_bytes(field.size, "little", signed=field.signed)
    (status,) = replies(emu, Packet(dxl_id, Instruction.WRITE, params))
    return status.error


@pytest.fixture
def core() -> Iterator[ServoEmulator]:
    """An emulator used through handle() only (the thread is never started)."""
    emu = ServoEmulator((1, 2, 3))
    yield emu
    emu.stop()


@pytest.fixture
def sdk() -> Iterator[tuple[ServoEmulator, PortHandler, PacketHandler]]:
    with ServoEmulator((1, 2)) as emu:
        # the SDK's PortHandler as the driver makes it: replies awaited in select, a 250 ms
        # latency timer (an emulator thread's reply can come hundreds of ms late on a loaded
        # machine; these tests are about what the replies say)
        port = port_handler(dynamixel_sdk, emu.port_path, 250.0)
        assert port.openPort() and port.setBaudRate(1_000_000)
        try:
            yield emu, port, PacketHandler(2.0)
        finally:
            port.closePort()
        assert emu.error is None


# -- the sans-IO core --


def test_ping_reports_model_and_firmware(core: ServoEmulator) -> None:
    (status,) = replies(core, Packet(2, Instruction.PING))
    assert (status.id, status.error, status.data) == (2, 0, u16(1020) + b"\x30")


def test_broadcast_ping_answers_every_servo_in_id_order(core: ServoEmulator) -> None:
    assert [p.id for p in replies(core, Packet(BROADCAST_ID, Instruction.PING))] == [1, 2, 3]


def test_absent_id_is_silent(core: ServoEmulator) -> None:
    assert replies(core, Packet(9, Instruction.PING)) == []


def test_read_only_and_locked_eeprom_give_access_errors(core: ServoEmulator) -> None:
    assert write(core, 1, dxt.OPERATING_MODE, 1) == 0  # EEPROM, torque off: fine
    assert write(core, 1, dxt.TORQUE_ENABLE, 1) == 0
    assert write(core, 1, dxt.OPERATING_MODE, 3) == dxt.ERRNUM_ACCESS  # locked by torque
    assert write(core, 1, dxt.PRESENT_POSITION, 5) == dxt.ERRNUM_ACCESS  # read-only
    (status,) = replies(core, Packet(1, Instruction.READ, u16(140) + u16(40)))
    assert status.error == dxt.ERRNUM_ACCESS  # past the modelled table


def test_goal_outside_limits_is_refused(core: ServoEmulator) -> None:
    assert write(core, 1, dxt.MAX_POSITION_LIMIT, 3072) == 0
    assert write(core, 1, dxt.TORQUE_ENABLE, 1) == 0
    assert write(core, 1, dxt.GOAL_POSITION, 3500) == dxt.ERRNUM_DATA_LIMIT
    assert write(core, 1, dxt.GOAL_POSITION, 3000) == 0
    assert core.servo(1).get(dxt.GOAL_POSITION) == 3000


def test_torque_on_sets_goal_to_present(core: ServoEmulator) -> None:
    servo = core.servo(1)
    assert write(core, 1, dxt.GOAL_POSITION, 100) == 0  # torque off: stored, nothing moves
    assert write(core, 1, dxt.TORQUE_ENABLE, 1) == 0
    assert servo.get(dxt.GOAL_POSITION) == 2048
    assert servo.get(dxt.PRESENT_POSITION) == 2048


def test_status_return_level_one_suppresses_write_replies(core: ServoEmulator) -> None:
    # The level applies at once: the write that sets it already goes unanswered.
    assert replies(core, Packet(1, Instruction.WRITE, u16(68) + b"\x01")) == []
    assert replies(core, Packet(1, Instruction.WRITE, u16(65) + b"\x01")) == []
    (status,) = replies(core, Packet(1, Instruction.READ, u16(65) + u16(1)))
    assert status.data == b"\x01"


def test_reg_write_applies_on_action(core: ServoEmulator) -> None:
    replies(core, Packet(2, Instruction.REG_WRITE, u16(65) + b"\x01"))
    assert core.servo(2).get(dxt.LED) == 0 and core.servo(2).get(dxt.REGISTERED_INSTRUCTION)
    assert replies(core, Packet(BROADCAST_ID, Instruction.ACTION)) == []
    assert core.servo(2).get(dxt.LED) == 1


def test_sync_write_and_sync_read_in_listed_order(core: ServoEmulator) -> None:
    body = b"".join(bytes((i,)) + (1000 + i).to_bytes(4, "little") for i in (3, 1))
    sync_write = Packet(BROADCAST_ID, Instruction.SYNC_WRITE, u16(116) + u16(4) + body)
    assert replies(core, sync_write) == []
    read = Packet(BROADCAST_ID, Instruction.SYNC_READ, u16(116) + u16(4) + bytes((3, 9, 1)))
    got = [(p.id, int.from_bytes(p.data, "little")) for p in replies(core, read)]
    assert got == [(3, 1003), (1, 1001)]


def test_corrupt_packet_gets_a_crc_error_status(core: ServoEmulator) -> None:
    (status,) = replies(core, CorruptPacket(2, b""))  # type: ignore[arg-type]
    assert status.error == dxt.ERRNUM_CRC


def test_unknown_instruction_is_an_instruction_error(core: ServoEmulator) -> None:
    (status,) = replies(core, Packet(1, 0x77))
    assert status.error == dxt.ERRNUM_INSTRUCTION


def test_writing_the_id_moves_the_servo(core: ServoEmulator) -> None:
    assert write(core, 3, dxt.ID, 7) == 0
    assert core.ids == (1, 2, 7)
    assert replies(core, Packet(7, Instruction.PING))


def test_faults_in_the_core(core: ServoEmulator) -> None:
    core.set_fault(1, Fault.NO_REPLY)
    assert replies(core, Packet(1, Instruction.WRITE, u16(65) + b"\x01")) == []
    assert core.servo(1).get(dxt.LED) == 0  # an absent servo does not act either
    core.set_fault(2, "wrong_model", model_number=1120)
    assert replies(core, Packet(2, Instruction.PING))[0].data[:2] == u16(1120)
    core.set_fault(3, Fault.HARDWARE_ALERT, hardware_bits=dxt.HW_OVERHEATING)
    (status,) = replies(core, Packet(3, Instruction.READ, u16(70) + u16(1)))
    assert status.error == dxt.ERRBIT_ALERT and status.data == bytes((dxt.HW_OVERHEATING,))
    assert write(core, 3, dxt.TORQUE_ENABLE, 1) == dxt.ERRBIT_ALERT
    assert core.servo(3).get(dxt.TORQUE_ENABLE) == 0  # shut down until reboot
    core.set_fault(2, Fault.WRONG_MODEL, active=False)
    assert replies(core, Packet(2, Instruction.PING))[0].data[:2] == u16(1020)
    core.clear_faults()
    assert all(not core.faults(i) for i in core.ids)


def test_misuse_is_reported_clearly(core: ServoEmulator) -> None:
    with pytest.raises(EmulatorError, match="unknown fault 'melted'"):
        core.set_fault(1, "melted")
    with pytest.raises(EmulatorError, match=r"no servo with id 9 on this bus \(ids: \[1, 2, 3\]\)"):
        core.servo(9)
    with pytest.raises(EmulatorError, match=r"servo id must be an integer in 0\.\.252, got 300"):
        ServoEmulator((300,))


# -- joint backends --


def test_kinematic_joint_is_speed_limited_then_first_order() -> None:
    clock = FakeClock()
    joint = KinematicJoint(2048, speed_limit_tps=1000, time_constant_s=0.01, clock=clock)
    joint.set_torque(True)
    joint.set_goal_ticks(3048)
    clock.now = 0.5
    assert joint.present_ticks() == pytest.approx(2548)  # 1000 ticks/s, saturated
    clock.now = 0.99
    assert joint.present_ticks() == pytest.approx(3048 - 10)  # saturation ends vmax*tau short
    clock.now = 1.04
    assert joint.present_ticks() == pytest.approx(3048 - 10 * 2.718281828**-5)
    joint.set_torque(False)
    joint.set_goal_ticks(0)
    clock.now = 5
    assert joint.present_ticks() == pytest.approx(3048 - 10 * 2.718281828**-5)  # limp


def test_module_adapter_drives_a_module_driver() -> None:
    driver = RecordingDriver()
    adapter = ModuleJointAdapter(driver)
    dof1, dof2 = adapter.joint(0), adapter.joint(1)  # type: ignore[arg-type]
    assert driver.torque is False
    dof2.set_torque(True)
    assert driver.torque is True
    dof1.set_goal_ticks(2048 + 512)
    dof2.set_goal_ticks(2048 - 1024)
    assert driver.targets == (45.0, -90.0)
    assert dof1.present_ticks() == 2560


# -- the real SDK over a pty --


def test_sdk_ping_read_write_round_trip(
    sdk: tuple[ServoEmulator, PortHandler, PacketHandler],
) -> None:
    _, port, ph = sdk
    assert ph.ping(port, 1) == (1020, COMM_SUCCESS, 0)
    assert ph.read2ByteTxRx(port, 2, 0) == (1020, COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(port, 1, 64, 1) == (COMM_SUCCESS, 0)
    assert ph.write4ByteTxRx(port, 1, 116, 2500) == (COMM_SUCCESS, 0)
    deadline = time.monotonic() + 2
    while ph.read4ByteTxRx(port, 1, 132)[0] != 2500:
        assert time.monotonic() < deadline, "servo 1 never reached its goal"
        time.sleep(0.02)
    assert ph.read1ByteTxRx(port, 1, 122) == (0, COMM_SUCCESS, 0)  # Moving = 0 at the goal
    assert ph.ping(port, 3)[1] == COMM_RX_TIMEOUT


def test_sdk_broadcast_ping(sdk: tuple[ServoEmulator, PortHandler, PacketHandler]) -> None:
    _, port, ph = sdk
    assert ph.broadcastPing(port) == ({1: [1020, 48], 2: [1020, 48]}, COMM_SUCCESS)


def test_sdk_group_sync_write_and_read(
    sdk: tuple[ServoEmulator, PortHandler, PacketHandler],
) -> None:
    _, port, ph = sdk
    writer = GroupSyncWrite(port, ph, 116, 4)
    reader = GroupSyncRead(port, ph, 116, 4)
    for dxl_id, goal in ((1, 1111), (2, 3333)):
        assert writer.addParam(dxl_id, list(goal.to_bytes(4, "little")))
        assert reader.addParam(dxl_id)
    assert writer.txPacket() == COMM_SUCCESS
    assert reader.txRxPacket() == COMM_SUCCESS
    assert (reader.getData(1, 116, 4), reader.getData(2, 116, 4)) == (1111, 3333)


def test_sdk_sees_each_fault(sdk: tuple[ServoEmulator, PortHandler, PacketHandler]) -> None:
    emu, port, ph = sdk
    emu.set_fault(2, Fault.NO_REPLY)
    assert ph.ping(port, 2)[1] == COMM_RX_TIMEOUT
    emu.set_fault(2, Fault.NO_REPLY, active=False)
    emu.set_fault(2, Fault.CRC_ERROR)
    assert ph.ping(port, 2)[1] == COMM_RX_CORRUPT
    emu.clear_faults(2)
    emu.set_fault(2, Fault.WRONG_MODEL)
    assert ph.ping(port, 2) == (1060, COMM_SUCCESS, 0)
    emu.set_fault(2, Fault.HARDWARE_ALERT)
    assert ph.read1ByteTxRx(port, 2, 70) == (dxt.HW_OVERLOAD, COMM_SUCCESS, 0x80)
    assert ph.reboot(port, 2)[0] == COMM_SUCCESS
    time.sleep(emu.reboot_time_s + 0.02)
    assert Fault.HARDWARE_ALERT not in emu.faults(2)
    assert ph.read1ByteTxRx(port, 2, 70) == (0, COMM_SUCCESS, 0)
    assert ph.ping(port, 1) == (1020, COMM_SUCCESS, 0)  # the neighbour never noticed


def test_sdk_recovers_from_line_noise(
    sdk: tuple[ServoEmulator, PortHandler, PacketHandler],
) -> None:
    emu, port, ph = sdk
    port.writePort(b"\xff\xff\xfd\x00\x01\x30\x00garbage")  # a header with a bogus length
    time.sleep(0.01)
    port.writePort(encode_instruction(1, Instruction.PING) + bytes(64))
    time.sleep(0.05)
    assert ph.ping(port, 1) == (1020, COMM_SUCCESS, 0)
    assert emu.parser.skipped_bytes > 0


def test_emulator_for_a_module_driver_over_the_sdk() -> None:
    driver = RecordingDriver()
    with ServoEmulator.for_module(driver, dof1_id=11, dof2_id=12) as emu:
        port = PortHandler(emu.port_path)
        assert port.setBaudRate(1_000_000)
        ph = PacketHandler(2.0)
        try:
            assert ph.write1ByteTxRx(port, 11, 64, 1) == (COMM_SUCCESS, 0)
            assert ph.write4ByteTxRx(port, 11, 116, 2048 + 341) == (COMM_SUCCESS, 0)
            assert driver.targets[0] == pytest.approx(29.97, abs=0.01)
            assert ph.read4ByteTxRx(port, 11, 132) == (2048 + 341, COMM_SUCCESS, 0)
        finally:
            port.closePort()


def open_fds() -> set[int]:
    """This process's open file descriptors (not the one that listed them, closed by then)."""
    fds = set()
    for name in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):
            os.fstat(int(name))
            fds.add(int(name))
    return fds


def test_stop_ends_the_thread_and_closes_every_fd() -> None:
    fds_before, threads_before = open_fds(), set(threading.enumerate())
    emu = ServoEmulator((1,)).start()
    fds = open_fds() - fds_before
    assert len(fds) == 4  # the pty's two ends and the wake-up pipe's two
    (thread,) = set(threading.enumerate()) - threads_before
    emu.stop()
    emu.stop()  # idempotent
    assert thread is not None and not thread.is_alive()
    for fd in fds:
        with pytest.raises(OSError):
            os.fstat(fd)
    with pytest.raises(EmulatorError, match="cannot be restarted"):
        emu.start()
