"""module.toml's ``[latch]``: every value checked (the key named, exit 2), ``--check-config``
naming a latch device that is not there and saying what the latch is, the config's round
trips (JSON to a module process, TOML from the world), and ``open_latch``, the seam a module's
dock builds its latch with."""

from __future__ import annotations

import time
import tomllib
from pathlib import Path

import pytest

from dh2rt.bundled import compile_bundled
from dh2rt.errors import ModuleConfigError
from drivers.dynamixel import DynamixelDriver
from drivers.latch import LatchState, ServoLatch
from drivers.recording import RecordingLatch
from firmware import main_loop
from firmware.config import LatchSpec, ModuleConfig
from firmware.latch import open_latch
from firmware.module_toml import dump_toml, load_toml
from hil.latch_emulator import LatchJoint, emulate
from hil.servo_joints import KinematicJoint

SERVO = '[latch]\nkind = "servo"\nid = 3\nopen_deg = -30\nclosed_deg = 30\n'
GPIO = '[latch]\nkind = "gpio"\nchip = "/dev/gpiochip0"\noutput_line = 5\ninput_line = 6\n'
SERVOS = '[servos]\nport = "/dev/ttyUSB0"\n'


def module_toml(tmp_path: Path, body: str) -> Path:
    """A module.toml booting an unsigned caterpillar from its flash, on an in-process bus."""
    (tmp_path / "flash").mkdir(exist_ok=True)
    (tmp_path / "flash" / "program.img").write_bytes(compile_bundled("caterpillar.dh2").image)
    config = tmp_path / "module.toml"
    config.write_text('[program]\nflash = "flash"\nallow_unsigned = true\n[transport]\nkind = "inproc"\n' + body)
    return config


def check_config(config: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """``dh2rt module --config CONFIG --check-config`` (its main, in this process); the exit
    code and what it printed."""
    monkeypatch.setattr(main_loop, "lean_process", lambda: None)  # keeps this process's ssl
    code = main_loop.main(["--config", str(config), "--check-config"])
    out, err = capsys.readouterr()
    return code, out + err


BAD = [
    ('[latch]\nkind = "magnet"\n', "[latch] kind: expected one of servo, gpio, recording, none, got 'magnet'"),
    ("[latch]\nid = 3\n", "[latch] kind: missing: one of servo, gpio, recording, none"),
    (SERVOS + SERVO.replace("id = 3", "id = 300"), "[latch] id: expected an integer 0..252, got 300"),
    (SERVOS + SERVO.replace("id = 3", 'id = "3"'), "[latch] id: expected an integer 0..252, got '3'"),
    (SERVOS + SERVO.replace("id = 3", "id = true"), "[latch] id: expected an integer 0..252, got True"),
    (SERVOS + SERVO.replace("open_deg = -30\n", ""), "[latch] open_deg: missing"),
    (
        SERVOS + SERVO.replace("open_deg = -30", "open_deg = nan"),
        "[latch] open_deg: expected a number from -180 to 180",
    ),
    (SERVOS + SERVO.replace("closed_deg = 30", "closed_deg = 200"), "[latch] closed_deg: expected a number from -180"),
    (SERVOS + SERVO.replace("closed_deg = 30", "closed_deg = -27"), "[latch] closed_deg: -27 is within twice"),
    (SERVOS + SERVO + "tolerance_deg = 0\n", "[latch] tolerance_deg: expected a positive number at most 45"),
    (SERVOS + SERVO + "tolerance_deg = inf\n", "[latch] tolerance_deg: expected a positive number at most 45"),
    (SERVOS + SERVO + "timeout_s = nan\n", "[latch] timeout_s: expected a positive number at most 60"),
    (SERVOS + SERVO + "timeout_s = -1\n", "[latch] timeout_s: expected a positive number at most 60"),
    (SERVOS + SERVO + "timeout_s = 61\n", "[latch] timeout_s: expected a positive number at most 60"),
    (SERVO, "[latch] port: missing: a servo latch is on the [servos] port, and there is none"),
    (SERVOS + SERVO + "baud = 57600\n", "[latch] baud: only with a port of the latch's own"),
    (SERVO + 'port = "/dev/ttyUSB1"\nbaud = 100\n', "[latch] baud: expected an integer 9600..12000000, got 100"),
    (SERVO + 'port = "/dev/ttyUSB1"\nlatency_ms = 0\n', "[latch] latency_ms: expected a positive number at most 500"),
    (SERVO + "port = 7\n", "[latch] port: expected a device path, got 7"),
    (GPIO.replace('chip = "/dev/gpiochip0"\n', ""), "[latch] chip: missing"),
    (GPIO.replace("output_line = 5", "output_line = -1"), "[latch] output_line: expected an integer 0..65535"),
    (GPIO.replace("input_line = 6", "input_line = 5"), "[latch] input_line: the output and the input need two"),
    (GPIO + 'input_active_low = "yes"\n', "[latch] input_active_low: expected true or false, got 'yes'"),
    (GPIO + "id = 3\n", "[latch] id: unknown key for kind = 'gpio' (known: kind, connector, chip,"),
    ('[latch]\nkind = "none"\nid = 3\n', '[latch] id: unknown key for kind = "none"'),
    (GPIO + 'connector = "back"\n', "[latch] connector: back is male: a latch holds a female face"),
    (GPIO + 'connector = "nose"\n', "[latch] connector: no such connector 'nose' (this profile's: front, back"),
    (GPIO + "connector = 1\n", "[latch] connector: expected a connector's name, got 1"),
]


@pytest.mark.parametrize(("body", "words"), BAD)
def test_every_latch_error_names_its_key_and_exits_2(
    body: str, words: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    config = module_toml(tmp_path, body)
    code, printed = check_config(config, monkeypatch, capsys)
    assert code == 2, printed
    assert f"dh2rt module: {config}: [latch]" in printed and words in printed, printed
    assert "Traceback" not in printed


def test_check_config_names_a_missing_latch_device(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    config = module_toml(tmp_path, SERVO + 'port = "/dev/no-such-latch"\n')
    code, printed = check_config(config, monkeypatch, capsys)
    assert code == 2 and "[latch] port: /dev/no-such-latch: no such device" in printed, printed
    config = module_toml(tmp_path, GPIO.replace("/dev/gpiochip0", "/dev/no-such-gpiochip"))
    code, printed = check_config(config, monkeypatch, capsys)
    assert code == 2 and "[latch] chip: /dev/no-such-gpiochip: no such device" in printed, printed


def test_check_config_says_what_the_latch_is(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    servos = tmp_path / "ttyUSB0"
    servos.touch()  # the servo port, there
    config = module_toml(tmp_path, SERVOS.replace("/dev/ttyUSB0", str(servos)) + SERVO + "timeout_s = 0.5\n")
    code, printed = check_config(config, monkeypatch, capsys)
    assert code == 0, printed
    assert (
        f"latch: Dynamixel servo id 3 on {servos} (shared with the joints), open -30 / closed 30 degrees "
        "within 3, on front, moves within 0.5 s"
    ) in printed
    chip = tmp_path / "gpiochip0"
    chip.touch()
    config = module_toml(tmp_path, GPIO.replace("/dev/gpiochip0", str(chip)) + "input_active_low = true\n")
    code, printed = check_config(config, monkeypatch, capsys)
    assert code == 0, printed
    assert f"latch: GPIO {chip}, output line 5, closed switch on line 6 (input active low), on front" in printed
    code, printed = check_config(module_toml(tmp_path, ""), monkeypatch, capsys)
    assert code == 0 and "latch: none" in printed


def test_the_latch_survives_the_worlds_round_trips(tmp_path: Path) -> None:
    """JSON (to a module process) and module.toml (dump_toml, as the world starts its modules)."""
    config = load_toml(module_toml(tmp_path, SERVO + 'port = "/dev/ttyUSB1"\nbaud = 57600\n'))
    assert config.latch is not None and config.latch.settings["baud"] == 57600 and config.latch.connector == 1
    assert ModuleConfig.from_json(config.to_json()) == config
    again = load_toml_text(tmp_path / "again", dump_toml(config, tmp_path / "again" / "flash"))
    assert again.latch == config.latch
    with pytest.raises(ModuleConfigError, match="config latch id: missing"):
        ModuleConfig.from_json({**config.to_json(), "latch": {"kind": "servo"}})


def load_toml_text(folder: Path, text: str) -> ModuleConfig:
    (folder / "module.toml").write_text(text)
    return load_toml(folder / "module.toml")


def spec(text: str, servo_port: str | None = None) -> LatchSpec | None:
    return LatchSpec.from_mapping(tomllib.loads(text)["latch"], "[latch]", servo_port)


def test_open_latch_builds_what_the_config_says(tmp_path: Path) -> None:
    assert open_latch(ModuleConfig()) == (None, None)
    latch, fault = open_latch(ModuleConfig(latch=spec('[latch]\nkind = "recording"\n')))
    assert isinstance(latch, RecordingLatch) and fault is None
    missing = spec(GPIO.replace("/dev/gpiochip0", str(tmp_path / "gpiochip9")))
    why = f"[latch] gpio: GPIO chip {tmp_path}/gpiochip9: no such device"
    assert open_latch(ModuleConfig(latch=missing)) == (None, why)


def test_open_latch_shares_the_joints_bus_or_opens_its_own() -> None:
    joints = {1: KinematicJoint(), 2: KinematicJoint()}
    with emulate(3, LatchJoint(-30.0, 30.0), joints) as emu:
        config = ModuleConfig(servo_port=emu.port_path, servo_latency_ms=250.0, latch=spec(SERVO, emu.port_path))
        with DynamixelDriver(emu.port_path, latency_timer_ms=250.0) as driver:
            latch, fault = open_latch(config, driver)
            assert isinstance(latch, ServoLatch) and fault is None and latch.bus is driver.bus
            assert not latch.owns_bus
            latch.close()
            while latch.state().state is LatchState.MOVING:
                time.sleep(0.01)
            assert latch.state().state is LatchState.CLOSED
        alone, fault = open_latch(config, None)  # the joints' driver failed: the latch opens the port itself
        assert isinstance(alone, ServoLatch) and fault is None and alone.owns_bus
        assert alone.state().state is LatchState.CLOSED
        alone.release()
        assert not alone.bus.is_open
        nine = spec(SERVO.replace("id = 3", "id = 9"), emu.port_path)
        lost = ModuleConfig(servo_port=emu.port_path, servo_latency_ms=20.0, latch=nine)
        why = f"[latch] servo: latch servo id 9 did not answer a PING on {emu.port_path} at 1000000 bps"
        assert open_latch(lost) == (None, why)
