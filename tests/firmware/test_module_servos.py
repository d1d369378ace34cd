"""A module process's actuators: Dynamixel servos when a servo port is configured (here the
emulator's pty), the stand-in otherwise; servos that cannot be opened are an actuator fault
and the module still runs its program."""

from __future__ import annotations

import queue
from pathlib import Path
from typing import Any

import pytest

from dh2rt.compiler import compile_file
from drivers.dxl_table import GOAL_POSITION, deg_to_ticks
from drivers.recording import RecordingDriver
from firmware.config import ModuleConfig
from firmware.control import Command, Go, report_to_json
from firmware.main_loop import ModuleHost
from hil.servo_emulator import ServoEmulator

ROOT = Path(__file__).resolve().parents[2]


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


def serve(config: dict[str, Any]) -> list[dict[str, Any]]:
    """Run a module from its config as JSON; its reports as they would cross the pipe."""
    reports: list[dict[str, Any]] = []
    commands: queue.Queue[Command] = queue.Queue()
    commands.put(Go())
    host = ModuleHost(ModuleConfig.from_json(config), commands, lambda rep: reports.append(report_to_json(rep)))
    try:
        assert host.serve() == 0
    finally:
        host.runtime.close()
    return reports


def base_config() -> dict[str, Any]:
    image = compile_file(str(ROOT / "examples" / "caterpillar.dh2")).image
    return {"module": 0, "image": image.hex(), "transport": "inproc:servos", "cycles": 45, "cycle_period": 0.004}


def test_no_servo_port_takes_the_stand_in() -> None:
    host = ModuleHost(ModuleConfig.from_json(base_config()), queue.Queue(), lambda _r: None)
    try:
        assert isinstance(host.driver, RecordingDriver)
    finally:
        host.runtime.close()


def test_servo_port_drives_the_servos() -> None:
    with ServoEmulator((1, 2)) as emulator:
        emulator.start()
        reports = serve({**base_config(), "servo_port": emulator.port_path})
        final = next(r for r in reports if r["event"] == "final")
        assert final["actuator_fault"] is None
        # a lone head has run its quarters: the servo's goal is the engine's last DOF1
        assert final["DOF1"] in (45.0, -45.0)
        assert emulator.servo(1).get(GOAL_POSITION) == deg_to_ticks(final["DOF1"])


def test_servos_that_cannot_be_opened_are_a_fault_not_a_crash() -> None:
    with ServoEmulator((1,)) as emulator:  # the DOF2 servo (id 2) is missing
        emulator.start()
        reports = serve({**base_config(), "servo_port": emulator.port_path})
    final = next(r for r in reports if r["event"] == "final")
    assert "did not answer" in final["actuator_fault"]
    assert final["counters"]["cycles"] == 45  # it ran its program all the same
    assert final["DOF1"] in (45.0, -45.0)
