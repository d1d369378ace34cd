"""The Sense command (a ``sense`` event on its way from the world to a module process):
round-tripped through JSON, malformed ones refused naming the field."""

from __future__ import annotations

import json
from typing import Any

import pytest

from dh2rt.errors import ControlProtocolError
from firmware.control import Sense, command_from_json, command_to_json


def test_sense_round_trips_through_json() -> None:
    cmd = Sense("roll", -90)
    wire = json.dumps(command_to_json(cmd))
    assert json.loads(wire) == {"cmd": "sense", "sensor": "roll", "value": -90}
    assert command_from_json(json.loads(wire)) == cmd


@pytest.mark.parametrize(
    ("obj", "message"),
    [
        ({"cmd": "sense", "value": 3}, "field 'sensor' None is not a name"),
        ({"cmd": "sense", "sensor": "", "value": 3}, "field 'sensor' '' is not a name"),
        ({"cmd": "sense", "sensor": "roll"}, "field 'value' None is not a whole number"),
        ({"cmd": "sense", "sensor": "roll", "value": 2.5}, "field 'value' 2.5 is not a whole number"),
        ({"cmd": "sense", "sensor": "roll", "value": True}, "field 'value' True is not a whole number"),
    ],
)
def test_malformed_sense_commands_name_the_field(obj: dict[str, Any], message: str) -> None:
    with pytest.raises(ControlProtocolError, match=message):
        command_from_json(obj)
