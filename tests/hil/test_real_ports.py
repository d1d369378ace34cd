"""The launcher on real ports: any python-can interface (`--transport can --interface ...`),
a hardware map naming each module's servo port, UARTs and CAN adapter, and the views of the
PyBullet stand-in (`--record`, `--plot`).

There is no USB-CAN adapter and no SocketCAN here: the slcan path runs against ptys that
speak the adapters' protocol (tests/hil/slcan_emulator.py) with python-can's own slcan driver in every
module, and the test on a real adapter skips with the reason."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Any

import pytest

from drivers.dxl_table import GOAL_POSITION, deg_to_ticks
from hil.link_emulator import LinkEmulator
from hil.pace import PACE
from hil.servo_emulator import ServoEmulator
from tests.hil.holds import assert_no_module_held_itself
from tests.hil.slcan_emulator import SlcanBusEmulator

ROOT = Path(__file__).resolve().parents[2]


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


def launch(*args: str, timeout: float = 120) -> tuple[int, dict[str, Any], str]:
    cmd = [sys.executable, "-m", "hil.launcher", "--json", *args]
    proc = PACE.run(cmd, text=True, timeout=timeout, cwd=ROOT)
    summary = json.loads(proc.stdout) if proc.stdout.strip().startswith("{") else {}
    return proc.returncode, summary, proc.stderr


def clean(summary: dict[str, Any], size: int, silence_cycles: int) -> None:
    rows = summary["modules"]
    assert [r["type"] for r in rows] == ["head"] + ["body"] * (size - 2) + ["tail"]
    assert_no_module_held_itself(summary, silence_cycles)  # no link lost that the machine did not cause
    frames = summary["frames"]
    assert frames["unaccounted"] == 0 and frames["sent"] == frames["received"] > 100, frames


def test_slcan_adapters_one_per_module(tmp_path: Path) -> None:
    """`--transport can --interface slcan`: each module opens its own adapter, as on a robot."""
    with SlcanBusEmulator() as bus:
        adapters = [bus.add_adapter() for _ in range(4)]
        hw = tmp_path / "hardware.toml"
        hw.write_text("".join(f'[m{i}]\ncan_channel = "{a.path}"\n' for i, a in enumerate(adapters)))
        code, summary, err = launch(
            "--transport", "can", "--interface", "slcan", "--bitrate", "1000000", "--hardware-map", str(hw),
            "--module-count", "4", "--cycles", "120", "--cycle-ms", "30", "--silence-cycles", "6",
        )  # fmt: skip
        assert code == 0, (summary.get("problems"), err[-2000:])
        clean(summary, 4, silence_cycles=6)
        assert summary["stand_in"] == "recording"  # the default with a hardware map
        # every module's frames crossed the emulated wire between the adapters
        assert all(a.sent > 100 and a.received > 100 for a in bus.adapters)


REAL_SLCAN = os.environ.get("DH2RT_SLCAN_DEVICE", "/dev/ttyACM0")


@pytest.mark.skipif(
    not os.path.exists(REAL_SLCAN),
    reason=f"no USB-CAN adapter at {REAL_SLCAN} on this machine "
    "(set DH2RT_SLCAN_DEVICE); test_slcan_adapters_one_per_module runs the same path on ptys",
)
def test_a_real_slcan_adapter(tmp_path: Path) -> None:  # pragma: no cover - needs the device
    """One module on the adapter (one process can own a serial adapter): it opens the bus,
    cycles and stops cleanly."""
    code, summary, err = launch(
        "--transport", "can", "--interface", "slcan", "--channel", REAL_SLCAN, "--bitrate", "1000000",
        "--module-count", "1", "--cycles", "100", "--stand-in", "none",
    )  # fmt: skip
    assert code == 0, err[-2000:]
    assert summary["modules"][0]["cycle"] >= 99


def test_a_hardware_map_of_servo_ports_and_uarts(tmp_path: Path) -> None:
    """Every module's servos on their own port and a UART per docked connector: the launcher
    emulates nothing (the test plays the hardware with emulators on ptys)."""
    servos = [ServoEmulator((1, 2)) for _ in range(3)]
    try:
        for s in servos:
            s.start()
        with LinkEmulator() as wires:
            l0, l1 = wires.add_link(0), wires.add_link(1)
            hw = tmp_path / "hardware.toml"
            hw.write_text(
                f'[m0]\nservo_port = "{servos[0].port_path}"\n[m0.connectors]\nback = "{l0.paths[0]}"\n'
                f'[m1]\nservo_port = "{servos[1].port_path}"\nservo_model = "XM430-W350"\n'
                f'[m1.connectors]\nfront = "{l0.paths[1]}"\nback = {{ device = "{l1.paths[0]}", baud = 115200 }}\n'
                f'[m2]\nservo_port = "{servos[2].port_path}"\nservo_ids = [1, 2]\n'
                f'[m2.connectors]\nfront = "{l1.paths[1]}"\n'
            )
            code, summary, err = launch(
                "--transport", "serial", "--hardware-map", str(hw), "--module-count", "3", "--cycles", "120",
                "--cycle-ms", "30", "--silence-cycles", "6",
            )  # fmt: skip
            relayed = [wires.stats(i).bytes_relayed for i in (0, 1)]
        assert code == 0, (summary.get("problems"), err[-2000:])
        clean(summary, 3, silence_cycles=6)
        assert all(r["actuator_fault"] is None for r in summary["modules"])
        assert min(relayed) > 1000  # the frames crossed the test's wires, not emulated ones
        # each module's DOF1 servo holds the angle the module last commanded (the wave's +-45)
        assert [s.servo(1).get(GOAL_POSITION) for s in servos] == [deg_to_ticks(r["DOF1"]) for r in summary["modules"]]
        assert {abs(r["DOF1"]) for r in summary["modules"]} == {45.0}
    finally:
        for s in servos:
            s.stop()


BAD_MAPS = [
    ('[m9]\nservo_port = "/dev/x"\n', "[m9]: no such module"),
    ('[m0]\nservo_prt = "/dev/x"\n', "[m0]: servo_prt: unknown key"),
    ('[m0]\nservo_port = "/dev/x"\nservo_ids = [1, 1]\n', "[m0]: servo_ids: expected two different ids"),
    ("[m0]\nservo_ids = [1, 2]\n", "[m0]: servo_ids, servo_baud and servo_model need a servo_port"),
    ('[m0]\nservo_port = "/dev/x"\nservo_model = "XX1"\n', "[m0]: servo_model: unknown Dynamixel model"),
    ('[m0.connectors]\nnose = "/dev/x"\n', "[m0.connectors]: nose: no such connector"),
    ('[m0.connectors]\nback = "/dev/x"\n', "[m1.connectors]: front is docked in snake:3 but not mapped"),
    ("[m0\n", "not valid TOML"),
]


@pytest.mark.parametrize(("text", "words"), BAD_MAPS)
def test_hardware_map_errors_name_the_key(text: str, words: str, tmp_path: Path) -> None:
    hw = tmp_path / "hardware.toml"
    hw.write_text(text)
    code, _summary, err = launch("--hardware-map", str(hw), "--module-count", "3", "--cycles", "5")
    assert code == 2 and words in err and "Traceback" not in err, err


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--transport", "can"], "--transport can needs --interface"),
        (["--transport", "can", "--interface", "slcan"], "needs --channel"),
        (["--transport", "can", "--interface", "slcan", "--channel", "/dev/nothing-here"], "no such device"),
        (["--transport", "can", "-i", "virtual", "-c", "x", "--data-bitrate", "2000000"], "add --fd"),
        (["--transport", "serial", "--bitrate", "500000"], "--bitrate: only with --transport can"),
        (["--stand-in", "recording", "--plot", "x.png"], "--plot: shows the PyBullet stand-in"),
        (["--record", "x.mp4"], "--record"),
        (["--gui"], "needs a display"),
    ],
)
def test_bad_real_port_options_exit_2(args: list[str], words: str, tmp_path: Path) -> None:
    env_display = os.environ.pop("DISPLAY", None)
    try:
        code, _summary, err = launch(*args, "--module-count", "2", "--cycles", "5")
    finally:
        if env_display is not None:
            os.environ["DISPLAY"] = env_display
    assert code == 2 and words in err and "Traceback" not in err, err


def test_record_and_plot_of_the_stand_in(tmp_path: Path) -> None:
    gif, png = tmp_path / "run.gif", tmp_path / "run.png"
    code, summary, err = launch(
        "--transport", "serial", "--module-count", "3", "--cycles", "80", "--cycle-ms", "30",
        "--silence-cycles", "6", "--record", str(gif), "--plot", str(png),
    )  # fmt: skip
    assert code == 0, (summary.get("problems"), err[-2000:])
    assert gif.read_bytes()[:6] == b"GIF89a" and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert f"animation: {gif}" in err and f"plot: {png}" in err  # with --json, to stderr
