"""One source for each shared option: every command's python-can bus options come from
dh2rt.cmdline.add_bus_arguments with one default bit rate, and every cycle period default
(commands, module.toml, the configuration, the HIL world, the runtime) is the core's."""

from __future__ import annotations

import argparse
import inspect
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from dh2rt.cmdline import CAN_BITRATE, add_bus_arguments
from dh2rt.compiler import compile_source
from dh2rt.runtime import CYCLE_PERIOD_S, ModuleRuntime, ms_to_s, s_to_ms
from firmware.config import DEFAULTS, ModuleConfig
from firmware.module_toml import dump_toml, parse_toml
from hil import launcher
from hil.world import World
from tools import capture, diff, flash

BUS_COMMANDS: dict[str, Callable[[], argparse.ArgumentParser]] = {
    "launch": launcher.build_parser,
    "flash": flash.build_parser,
    "capture": capture.build_parser,
}
PROGRAM = "const ClockCycle = 4\nhormone X\n"
CYCLE_COMMANDS: dict[str, Callable[[], argparse.ArgumentParser]] = {
    "launch": launcher.build_parser,
    "flash": flash.build_parser,
    "diff": diff.build_parser,
}


def _help(parser: argparse.ArgumentParser) -> str:
    return " ".join(parser.format_help().split())


@pytest.mark.parametrize("name", sorted(BUS_COMMANDS))
def test_every_bus_command_takes_the_same_bus_options(name: str) -> None:
    parser = BUS_COMMANDS[name]()
    assert parser.get_default("bitrate") == CAN_BITRATE
    text = _help(parser)
    for short, long in (("-i", "--interface"), ("-c", "--channel"), ("-b", "--bitrate")):
        assert f"{short} {long.upper()[2:]}, {long} {long.upper()[2:]}" in text, (short, text)
    assert f"(default: {CAN_BITRATE})" in text  # the help says the default the parser has


def test_add_bus_arguments_names_options_as_python_can_does() -> None:
    parser = argparse.ArgumentParser()
    add_bus_arguments(parser, required=True)
    ns = parser.parse_args(["-i", "virtual", "-c", "x"])
    assert (ns.interface, ns.channel, ns.bitrate) == ("virtual", "x", CAN_BITRATE)
    ns = parser.parse_args(["--interface", "slcan", "--channel", "/dev/ttyACM0", "--bitrate", "500000"])
    assert (ns.interface, ns.channel, ns.bitrate) == ("slcan", "/dev/ttyACM0", 500_000)
    with pytest.raises(SystemExit):
        parser.parse_args(["-c", "x"])  # required here: --interface is missing


@pytest.mark.parametrize("name", sorted(CYCLE_COMMANDS))
def test_every_cycle_option_defaults_to_the_core_period(name: str) -> None:
    parser = CYCLE_COMMANDS[name]()
    assert ms_to_s(parser.get_default("cycle_ms")) == CYCLE_PERIOD_S
    assert f"(default: {s_to_ms(CYCLE_PERIOD_S):g})" in _help(parser)


def test_the_runtime_world_config_and_module_toml_share_the_period() -> None:
    for owner in (ModuleRuntime.__init__, World.__init__):
        assert inspect.signature(owner).parameters["cycle_period"].default == CYCLE_PERIOD_S
    assert ModuleConfig().cycle_period == DEFAULTS.cycle_period == CYCLE_PERIOD_S
    assert ms_to_s(s_to_ms(CYCLE_PERIOD_S)) == CYCLE_PERIOD_S


def test_module_toml_reads_and_writes_the_period_in_ms(tmp_path: Path) -> None:
    flash = tmp_path / "flash"
    flash.mkdir()
    (flash / "program.img").write_bytes(compile_source(PROGRAM, "p.dh2").image)
    data: dict[str, Any] = {"program": {"flash": str(flash), "allow_unsigned": True}, "transport": {"kind": "inproc"}}
    assert parse_toml(data, "module.toml", tmp_path).cycle_period == CYCLE_PERIOD_S
    data["cycle"] = {"period_ms": 30}
    config = parse_toml(data, "module.toml", tmp_path)
    assert config.cycle_period == ms_to_s(30)
    assert "period_ms = 30.0" in dump_toml(config, flash)
