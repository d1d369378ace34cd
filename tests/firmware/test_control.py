"""The world's control protocol and the module's configuration: typed, round-tripped through
JSON, malformed input refused naming the field, one source for every default."""

from __future__ import annotations

import json
from typing import Any

import pytest

from dh2rt.errors import ControlProtocolError, ModuleConfigError
from dh2rt.liveness import SILENCE_CYCLES
from dh2rt.runtime import ModuleRuntime
from dh2rt.transport.base import BusEnd, PortEnd
from firmware.config import DEFAULT_STAND_IN, DEFAULTS, ModuleConfig
from firmware.control import (
    Attach,
    Command,
    Detach,
    Effect,
    Exited,
    Failure,
    Floor,
    Go,
    Hold,
    Inject,
    LatchAnswer,
    Log,
    OwnMotions,
    Ready,
    Report,
    Status,
    StatusRequest,
    Stop,
    TraceRecord,
    command_from_json,
    command_to_json,
    report_from_json,
    report_to_json,
)
from hil import launcher
from hil.world import World

COMMANDS: list[Command] = [
    Go(),
    Go(at=12.5),
    Go(at=3.0, cycles=None),
    Go(at=None, cycles=40),
    Attach(2, BusEnd(7, 1)),
    Attach(1, PortEnd("/dev/pts/9")),
    Detach(3),
    Inject("X(A)"),
    Hold({0: 12.5, 1: -30.0}),
    Hold({1: 4.0}),
    Hold(),
    OwnMotions(),
    Floor({0: ((0.5, -0.25, 1.5), (0.6, -0.25, 1.5), (0.4, -0.25, 1.5))}, {0: (2.0, -3.5)}),
    Floor(),
    LatchAnswer(1, True),
    LatchAnswer(3, False),
    StatusRequest(),
    Stop(),
]
REPORTS: list[Report] = [
    Ready(),
    Status({"cycle": 5, "type": "head", "counters": {"frames_sent": 3}}),
    Status({"cycle": 9, "counters": {}}, final=True, failed=True, targets=(45.0, -30.0)),
    TraceRecord({"cycle": 1, "module": 0}),
    Effect("reach_and_dock", [2, [1, 2]]),
    Log("connector back silent for 3 cycles"),
    Failure("RuntimeError: boom"),
    Exited(),
]


@pytest.mark.parametrize("cmd", COMMANDS, ids=repr)
def test_every_command_round_trips_through_json(cmd: Command) -> None:
    assert command_from_json(json.loads(json.dumps(command_to_json(cmd)))) == cmd


@pytest.mark.parametrize("rep", REPORTS, ids=repr)
def test_every_report_round_trips_through_json(rep: Report) -> None:
    assert report_from_json(json.loads(json.dumps(report_to_json(rep)))) == rep


@pytest.mark.parametrize(
    ("obj", "words"),
    [
        ({"cmd": "fly"}, "unknown 'cmd'"),
        ({"cmd": "go", "at": "soon"}, "'at'"),
        ({"cmd": "go", "cycles": 1.5}, "'cycles'"),
        ({"cmd": "attach", "connector": 2}, "'link'"),
        ({"cmd": "attach", "connector": "2", "link": {"port": "/dev/x"}}, "'connector'"),
        ({"cmd": "detach"}, "'connector'"),
        ({"cmd": "inject", "hormone": 3}, "'hormone'"),
        ({"cmd": "hold", "targets": [1, 2]}, "'targets'"),
        ({"cmd": "hold", "targets": {"2": 10.0}}, "joint '2'"),
        ({"cmd": "hold", "targets": {"0": "ten"}}, "not a number"),
        ({"cmd": "latch", "connector": 1, "closed": 1}, "'closed'"),
        ({"cmd": "floor", "parts": [], "attitude": {}}, "'parts'"),
        ({"cmd": "floor", "parts": {"a": []}, "attitude": {}}, "module 'a' is not an index"),
        ({"cmd": "floor", "parts": {"1": [[0, 0, 0]]}, "attitude": {}}, "module 1 has not 3 parts"),
        ({"cmd": "floor", "parts": {"1": [[0, 0], [0, 0, 0], [0, 0, 0]]}, "attitude": {}}, "not 3 numbers"),
        ({"cmd": "floor", "parts": {}, "attitude": {"1": [0, True]}}, "an attitude"),
        ({"cmd": "latch", "closed": True}, "'connector'"),
        ([1, 2], "expected an object"),
    ],
)
def test_malformed_commands_name_the_field(obj: Any, words: str) -> None:
    with pytest.raises(ControlProtocolError, match=words):
        command_from_json(obj)


@pytest.mark.parametrize(
    ("obj", "words"),
    [
        ({"event": "dance"}, "unknown 'event'"),
        ({"event": "trace", "record": 5}, "'record'"),
        ({"event": "effect", "kind": 1}, "'kind'"),
        ({"event": "status", "counters": []}, "'counters'"),
    ],
)
def test_malformed_reports_name_the_field(obj: Any, words: str) -> None:
    with pytest.raises(ControlProtocolError, match=words):
        report_from_json(obj)


def test_config_round_trips_and_names_bad_fields() -> None:
    cfg = ModuleConfig(image=b"\x01\x02", module=3, attach={2: BusEnd(7, 0), 1: PortEnd("/dev/pts/4")}, cycles=10)
    assert ModuleConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg
    for obj, words in [
        ({}, "'image'"),
        ({"image": "zz"}, "image: not hexadecimal"),
        ({"image": "", "cycle_period": "fast"}, "cycle_period"),
        ({"image": "", "cycle_period": 0}, "cycle_period 0"),
        ({"image": "", "silence_cycles": True}, "silence_cycles"),
        ({"image": "", "driver": "magic"}, "driver 'magic'"),
        ({"image": "", "servo_ids": [1]}, "servo_ids"),
        ({"image": "", "attach": {"back": {"port": "x"}}}, "connector 'back'"),
        ({"image": "", "attach": {"2": {"side": 3}}}, r"attach\[2\]"),
        ({"image": "", "colour": "red"}, "unknown field"),
    ]:
        with pytest.raises(ModuleConfigError, match=words):
            ModuleConfig.from_json(obj)


def test_one_source_for_every_default() -> None:
    """The launcher's option defaults, the world's and the runtime's are the config's."""
    ns = launcher.build_parser().parse_args([])
    assert ns.silence_cycles == DEFAULTS.silence_cycles == SILENCE_CYCLES
    assert ns.cycle_ms / 1000 == DEFAULTS.cycle_period
    assert launcher.stand_in_for(ns.stand_in, None) == DEFAULT_STAND_IN == "pybullet"
    world_defaults = World.__init__.__kwdefaults__ or {}
    assert world_defaults["silence_cycles"] == DEFAULTS.silence_cycles
    assert world_defaults["handshake"] == DEFAULTS.handshake
    assert world_defaults["status_every"] == DEFAULTS.status_every
    assert world_defaults["stand_in"] == DEFAULT_STAND_IN
    runtime_defaults = ModuleRuntime.__init__.__kwdefaults__ or {}
    assert runtime_defaults["silence_cycles"] == DEFAULTS.silence_cycles
    assert runtime_defaults["cycle_period"] == DEFAULTS.cycle_period
