"""The connector latch: a servo latch through the real dynamixel-sdk against the emulated
latch servo over a pty, a GPIO latch on a real (simulated) chip when the kernel has gpio-sim
and on stand-in lines otherwise, and the recording stand-in."""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from dh2rt.errors import DriverConfigError, DriverError, EmulatorError
from drivers import dxl_table as dxt
from drivers.dynamixel import DynamixelBus, DynamixelDriver
from drivers.latch import GpioLatch, Latch, LatchState, LatchStatus, ServoLatch
from drivers.recording import RecordingLatch
from hil.latch_emulator import LatchJoint, emulate
from hil.servo_joints import KinematicJoint

#: Reply timeout of about 0.5 s: the emulator is a thread of this process (see test_dynamixel.py).
LATENCY_MS = 250.0
LATCH_ID = 3
OPEN_DEG, CLOSED_DEG = -30.0, 30.0


def settle(latch: Latch, limit_s: float = 5.0) -> tuple[LatchStatus, float]:
    """Poll as a module's cycle does until the latch stops moving; the status and how long."""
    start = time.monotonic()
    while (status := latch.state()).state is LatchState.MOVING:
        assert time.monotonic() - start < limit_s, "the latch never stopped moving"
        time.sleep(0.01)
    return status, time.monotonic() - start


class Faces:
    """The world's word on whether the faces line up (the latch emulator's hook)."""

    def __init__(self) -> None:
        self.aligned = True

    def __call__(self) -> bool:
        return self.aligned


@contextlib.contextmanager
def latch_bus(faces: Faces, **joint: object) -> Iterator[tuple[LatchJoint, DynamixelBus, Callable[..., ServoLatch]]]:
    """An emulated latch servo alone on a pty; a bus to it and a way to make latches on it."""
    horn = LatchJoint(OPEN_DEG, CLOSED_DEG, faces, **joint)  # type: ignore[arg-type]
    with emulate(LATCH_ID, horn, reboot_time_s=0.01) as emu:  # back before the first PING after a REBOOT
        bus = DynamixelBus(emu.port_path, latency_timer_ms=LATENCY_MS)

        def make(**kw: object) -> ServoLatch:
            kw.setdefault("speed_dps", 360.0)  # 60 degrees in 0.17 s: quick tests
            return ServoLatch(bus, LATCH_ID, OPEN_DEG, CLOSED_DEG, **kw)  # type: ignore[arg-type]

        try:
            yield horn, bus, make
        finally:
            bus.close()
        assert emu.error is None


def test_a_servo_latch_opens_and_closes_through_the_sdk() -> None:
    faces = Faces()
    with latch_bus(faces) as (horn, _bus, make):
        latch = make()
        assert latch.state() == LatchStatus(LatchState.OPEN)  # found open: taken as commanded
        latch.close()
        assert latch.state().state is LatchState.MOVING
        status, took = settle(latch)
        assert status == LatchStatus(LatchState.CLOSED), status
        assert horn.is_past_the_pins and 0.1 < took < latch.timeout_s
        latch.open()
        assert settle(latch)[0] == LatchStatus(LatchState.OPEN)
        assert not horn.is_past_the_pins and horn.refused == 0


def test_a_close_the_faces_refuse_is_a_fault_that_stops_pushing_and_opening_still_works() -> None:
    faces = Faces()
    faces.aligned = False
    with latch_bus(faces, overload_after_s=None) as (horn, bus, make):
        latch = make()
        latch.close()
        status, took = settle(latch)
        assert status.state is LatchState.FAULT and "close stalled" in status.reason, status
        assert "latch servo id 3 at 0.0 degrees" in status.reason  # stopped where the pins met the face
        assert took < latch.timeout_s and horn.refused == 1 and not horn.is_past_the_pins
        # it stopped pushing: the goal is where the horn is, and the fault stays until a command
        assert abs(bus.read(LATCH_ID, "latch", dxt.GOAL_POSITION) - dxt.deg_to_ticks(0.0)) <= 2
        assert latch.state() == status
        latch.open()
        assert settle(latch)[0] == LatchStatus(LatchState.OPEN)
        faces.aligned = True  # lined up now: the same latch closes
        latch.close()
        assert settle(latch)[0] == LatchStatus(LatchState.CLOSED)


def test_a_jammed_servo_that_overloads_names_its_hardware_error_and_a_reboot_reopens_it() -> None:
    faces = Faces()
    faces.aligned = False
    with latch_bus(faces, overload_after_s=0.1) as (horn, bus, make):
        latch = make(stall_s=5.0)  # the overload comes first
        latch.close()
        status, _ = settle(latch)
        assert status.state is LatchState.FAULT, status
        assert "overload (Hardware Error Status 0x20)" in status.reason and horn.overloads == 1
        latch.open()  # reboots the shut-down servo, then drives it
        assert settle(latch)[0] == LatchStatus(LatchState.OPEN)
        assert bus.read(LATCH_ID, "latch", dxt.TORQUE_ENABLE) == 1


def test_a_close_that_does_not_finish_in_time_is_a_fault() -> None:
    with latch_bus(Faces()) as (_horn, _bus, make):
        latch = make(speed_dps=20.0, timeout_s=0.3)  # 60 degrees at 20 degrees/s: 3 s
        start = time.monotonic()  # the timeout counts from the command
        latch.close()
        status, _ = settle(latch)
        took = time.monotonic() - start
        assert status.state is LatchState.FAULT and "close did not finish in 0.3 s" in status.reason, status
        assert 0.3 <= took < 1.0


def test_a_latch_made_again_after_a_restart_keeps_what_it_finds() -> None:
    """A module restarted with its latch closed finds it closed and does not move it; one
    found between open and closed says so until it is told where to go."""
    with latch_bus(Faces()) as (horn, bus, make):
        first = make()
        first.close()
        assert settle(first)[0].state is LatchState.CLOSED
        bus.close()  # the module process ends; the servo holds
        again = make()
        assert again.state() == LatchStatus(LatchState.CLOSED) and again.target is not None
        assert horn.is_past_the_pins
        again.open()
        assert settle(again)[0].state is LatchState.OPEN
    with latch_bus(Faces(), start_deg=10.0) as (_horn, _bus, make):
        between = make()
        status = between.state()
        assert status.state is LatchState.FAULT and "neither opened nor closed since start" in status.reason
        between.close()
        assert settle(between)[0].state is LatchState.CLOSED


def test_the_latch_shares_the_joints_bus() -> None:
    """On the module's servo bus at its own id: one port, one lock, joints and latch both driven."""
    joints = {1: KinematicJoint(), 2: KinematicJoint()}
    horn = LatchJoint(OPEN_DEG, CLOSED_DEG)
    with emulate(LATCH_ID, horn, joints) as emu, DynamixelDriver(emu.port_path, latency_timer_ms=LATENCY_MS) as drv:
        latch = ServoLatch(drv.bus, LATCH_ID, OPEN_DEG, CLOSED_DEG)
        latch.close()
        drv.set_targets(20.0, -10.0)
        while latch.state().state is LatchState.MOVING:
            drv.read_positions()
            time.sleep(0.01)
        assert latch.state().state is LatchState.CLOSED
        assert all(abs(a - b) < 1.0 for a, b in zip(drv.read_positions(), (20.0, -10.0), strict=True))
        latch.release()  # the bus is the driver's: still open
        assert drv.bus.is_open
    with pytest.raises(EmulatorError, match="servo id 1 is taken"):
        emulate(1, horn, joints)


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"dxl_id": 300}, "latch servo id must be in 0..252"),
        ({"closed_deg": -28.0}, "more than twice tolerance_deg"),
        ({"open_deg": float("nan")}, "open_deg must be a number"),
        ({"timeout_s": 0.0}, "timeout_s must be a positive number"),
        ({"tolerance_deg": float("inf")}, "tolerance_deg must be a positive number"),
    ],
)
def test_a_servo_latch_refuses_bad_arguments(kwargs: dict[str, float], words: str) -> None:
    args: dict[str, float] = {"dxl_id": LATCH_ID, "open_deg": OPEN_DEG, "closed_deg": CLOSED_DEG, **kwargs}
    with pytest.raises(DriverConfigError, match=words):
        ServoLatch(DynamixelBus("/dev/null"), **args)  # type: ignore[arg-type]


def test_a_missing_latch_servo_is_a_clear_error() -> None:
    with emulate(LATCH_ID, LatchJoint(OPEN_DEG, CLOSED_DEG)) as emu:
        bus = DynamixelBus(emu.port_path, latency_timer_ms=20.0)
        with pytest.raises(DriverError, match="latch servo id 9 did not answer a PING"):
            ServoLatch(bus, 9, OPEN_DEG, CLOSED_DEG)
        bus.close()


# -- GPIO --


class Mechanism:
    """A latch's mechanics as the test plays them: the actuator's output level, and the closed switch."""

    def output_active(self) -> bool:
        raise NotImplementedError

    def set_switch(self, closed: bool) -> None:
        raise NotImplementedError


class StandInLines(Mechanism):
    """The two calls GpioLatch makes, on plain values (no GPIO chip here): the fallback."""

    def __init__(self, output: int, switch: int) -> None:
        self.output, self.switch = output, switch
        self.values = {output: False, switch: False}
        self.writes: list[bool] = []

    def set_value(self, line: int, value: object) -> None:
        assert line == self.output, "the latch writes its output line only"
        self.values[line] = bool(value)
        self.writes.append(bool(value))

    def get_value(self, line: int) -> object:
        return self.values[line]

    def output_active(self) -> bool:
        return self.values[self.output]

    def set_switch(self, closed: bool) -> None:
        self.values[self.switch] = closed


GPIO_SIM = Path("/sys/kernel/config/gpio-sim")


class SimulatedChip(Mechanism):
    """A chip of the kernel's gpio-sim (configfs): the latch uses it through the real libgpiod,
    the test reads the output line and pulls the switch line through sysfs."""

    def __init__(self, name: str, output: int, switch: int) -> None:
        self.root = GPIO_SIM / name
        bank = self.root / "gpio-bank0"
        bank.mkdir(parents=True)
        (bank / "num_lines").write_text("8")
        (self.root / "live").write_text("1")
        self.chip = "/dev/" + (bank / "chip_name").read_text().strip()
        self.sysfs = Path("/sys/devices/platform") / (self.root / "dev_name").read_text().strip()
        self.sysfs /= (bank / "chip_name").read_text().strip()
        self.output, self.switch = output, switch

    def output_active(self) -> bool:
        return (self.sysfs / f"sim_gpio{self.output}" / "value").read_text().strip() == "1"

    def set_switch(self, closed: bool) -> None:
        (self.sysfs / f"sim_gpio{self.switch}" / "pull").write_text("pull-up" if closed else "pull-down")

    def remove(self) -> None:
        (self.root / "live").write_text("0")
        (self.root / "gpio-bank0").rmdir()
        self.root.rmdir()


def exercise_gpio_latch(make: Callable[[], GpioLatch], mechanism: Mechanism) -> None:
    """What every GPIO latch does, on whatever lines ``make`` opens."""
    latch = make()
    assert latch.state() == LatchStatus(LatchState.OPEN) and not mechanism.output_active()
    latch.close()
    assert mechanism.output_active() and latch.state().state is LatchState.MOVING
    mechanism.set_switch(True)  # the pins went in
    assert latch.state() == LatchStatus(LatchState.CLOSED)
    latch.release()
    again = make()  # restarted: found closed, kept closed (the output driven at once)
    assert again.state() == LatchStatus(LatchState.CLOSED) and mechanism.output_active()
    mechanism.set_switch(False)  # forced open while it should hold
    status = again.state()
    assert status.state is LatchState.FAULT and "left closed by itself" in status.reason
    assert "the closed switch (line" in status.reason
    again.open()
    assert again.state() == LatchStatus(LatchState.OPEN) and not mechanism.output_active()
    again.close()  # nothing goes in this time
    time.sleep(again.timeout_s + 0.05)
    status = again.state()
    assert status.state is LatchState.FAULT and f"close did not finish in {again.timeout_s:g} s" in status.reason
    again.release()


def test_a_gpio_latch_on_a_real_chip() -> None:
    if not GPIO_SIM.is_dir():
        pytest.skip(
            "no GPIO chip to drive here: this kernel has no gpio-sim (no configfs at /sys/kernel/config, "
            "no /dev/gpiochip*); the same test runs on stand-in lines below"
        )
    chip = SimulatedChip(f"dh2rt-latch-{os.getpid()}", output=0, switch=1)
    try:
        exercise_gpio_latch(lambda: GpioLatch.on_chip(chip.chip, 0, 1, timeout_s=0.1), chip)
    finally:
        chip.remove()


def test_a_gpio_latch_on_stand_in_lines() -> None:
    lines = StandInLines(output=5, switch=6)
    exercise_gpio_latch(lambda: GpioLatch(lines, 5, 6, timeout_s=0.1), lines)
    assert lines.writes[:2] == [False, True]  # opened at the first start, then closed


def test_a_missing_gpio_chip_or_package_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(DriverError, match="GPIO chip /dev/gpiochip-none: no such device"):
        GpioLatch.on_chip("/dev/gpiochip-none", 5, 6)
    with pytest.raises(DriverError, match="GPIO chip /dev/null, lines 5 and 6: No such device"):
        GpioLatch.on_chip("/dev/null", 5, 6)
    with pytest.raises(DriverConfigError, match="output_line and input_line must differ"):
        GpioLatch.on_chip("/dev/null", 5, 5)
    monkeypatch.setitem(sys.modules, "gpiod", None)  # as if the gpio extra were not installed
    with pytest.raises(DriverError, match=r"gpiod is not installed; install dh2rt\[gpio\]"):
        GpioLatch.on_chip("/dev/gpiochip0", 5, 6)


def test_the_recording_latch_is_where_it_was_told_to_be() -> None:
    latch = RecordingLatch()
    assert latch.state() == LatchStatus(LatchState.OPEN)
    latch.close()
    assert latch.state() == LatchStatus(LatchState.CLOSED)
    latch.open()
    assert latch.state() == LatchStatus(LatchState.OPEN)
    assert [p.value for p in latch.history] == ["closed", "open"]
