"""The profile's sensor table and ``sense`` events: parsing, checking, and what a Robot does."""

from __future__ import annotations

from pathlib import Path

import pytest

from dh2rt.cli import main
from dh2rt.compiler import compile_source
from dh2rt.errors import EventError, TopologyError
from dh2rt.events import Event, check_events, parse_event
from dh2rt.profile import CONRO, CONRO_DATA, Profile, SensorSpec
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec

SOURCE = """
program tilt
const ClockCycle = 4
sensor roll, contact
var seen = 0
receptor tipped when S.roll > 45 or S.roll < -45 { DOF2(30); keep_alive() }
receptor upright when S.roll <= 45 and S.roll >= -45 { DOF2(0); keep_alive() }
receptor copy { V.seen = S.roll; keep_alive() }
"""
TOPOLOGY = parse_spec("snake:3")


@pytest.fixture(scope="module")
def tilt() -> CompiledProgram:
    return compile_source(SOURCE, "tilt.dh2")


def event(text: str, program: CompiledProgram) -> Event:
    return parse_event(text, TOPOLOGY, program.vocabulary)


# ---------------------------------------------------------------- the sensor table


def test_conro_declares_its_sensors_with_units_and_ranges() -> None:
    assert CONRO.sensor_names == (
        "roll",
        "pitch",
        "yaw",
        *(n for c in CONRO.connectors for n in (f"ir_{c}", f"ir_{c}_align")),
        "contact",
        "pos1",
        "pos2",
        "load1",
        "load2",
        "docking",
        "floor_x",
        "floor_y",
        "floor_heading",
    )
    assert CONRO.sensor("roll") == SensorSpec("roll", "deg", -180, 180, CONRO.sensor("roll").doc)
    assert (CONRO.sensor("ir_left").unit, CONRO.sensor("ir_left").high) == ("mm", 100)
    assert (CONRO.sensor("load2").low, CONRO.sensor("load2").high) == (-100, 100)
    assert (CONRO.sensor("yaw").unit, CONRO.sensor("yaw").low, CONRO.sensor("yaw").high) == ("deg", -720, 720)
    assert (CONRO.sensor("floor_x").unit, CONRO.sensor("floor_heading").high) == ("mm", 180)
    with pytest.raises(TopologyError, match=r"profile conro has no sensor 'light' \(it has: roll, pitch, yaw, "):
        CONRO.sensor("light")


def test_readings_round_to_integers_within_the_range() -> None:
    roll = CONRO.sensor("roll")
    assert [roll.reading(v) for v in (12.4, 12.6, -0.4, 179.7, 400.0, -1e9)] == [12, 13, 0, 180, 180, -180]
    assert all(isinstance(roll.reading(v), int) for v in (0.5, 1.5))
    assert roll.check(-180) == -180
    with pytest.raises(TopologyError, match=r"sensor roll reads -180\.\.180 deg, not 181"):
        roll.check(181)


def test_a_profile_from_data_declares_its_own_sensors() -> None:
    data = {**CONRO_DATA, "name": "lit", "sensors": [{"name": "light", "unit": "lx", "min": 0, "max": 1000}]}
    lit = Profile.from_dict(data)
    assert lit.sensors == (SensorSpec("light", "lx", 0, 1000),)
    assert Profile.from_dict({k: v for k, v in CONRO_DATA.items() if k != "sensors"}).sensors == ()


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        ([{"name": "a", "unit": "x", "min": 0}], "sensor a: missing or malformed field 'max'"),
        ([{"name": "a b", "unit": "x", "min": 0, "max": 1}], "sensor a b: the name must be an identifier"),
        (
            [{"name": "a", "unit": "x", "min": 2, "max": 1}],
            "sensor a: min and max must be whole numbers with min <= max",
        ),
        ([{"name": "a", "unit": "x", "min": 0.5, "max": 1}], "sensor a: min and max must be whole numbers"),
        ([{"name": "a", "unit": "x", "min": 0, "max": 1}] * 2, "sensor a: declared twice"),
        (["a"], "profile bad: sensor 0: missing or malformed field"),
    ],
)
def test_bad_sensor_tables_are_named(rows: list[object], message: str) -> None:
    with pytest.raises(TopologyError, match=message):
        Profile.from_dict({**CONRO_DATA, "name": "bad", "sensors": rows})


# ---------------------------------------------------------------- parsing and checking


def test_parse_a_sense_event(tilt: CompiledProgram) -> None:
    ev = parse_event("7:sense:m2:roll=-90", TOPOLOGY, tilt.vocabulary)
    assert (ev.cycle, ev.kind, ev.module, ev.sensor, ev.value) == (7, "sense", 2, "roll", -90)
    assert parse_event("0:sense:1: contact = 1 ", TOPOLOGY, tilt.vocabulary).value == 1


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("7:sense:m2", "expected CYCLE:sense:M:NAME=VALUE"),
        ("7:sense:m2:roll", "expected NAME=VALUE"),
        ("7:sense:m2:=4", "expected NAME=VALUE"),
        ("7:sense:m2:roll=4.5", "sensor value '4.5' is not a whole number"),
        ("7:sense:m2:light=4", "profile conro has no sensor 'light'"),
        ("7:sense:m2:contact=2", "sensor contact reads 0..1 bool, not 2"),
        ("7:sense:m9:roll=4", "no module 'm9'"),
    ],
)
def test_bad_sense_events_name_the_event(tilt: CompiledProgram, text: str, message: str) -> None:
    with pytest.raises(EventError, match=message) as info:
        parse_event(text, TOPOLOGY, tilt.vocabulary)
    assert repr(text) in str(info.value)


def test_check_events_refuses_what_cannot_happen(tilt: CompiledProgram) -> None:
    ok = [event("2:sense:m1:roll=10", tilt), event("3:kill:m1", tilt), event("4:restart:m1", tilt)]
    check_events([*ok, event("5:sense:m1:roll=0", tilt)], TOPOLOGY, 10, sensors=tilt.sensor_names)
    with pytest.raises(EventError, match=r"'3:sense:m1:roll=1'.*module m1 is stopped then"):
        check_events([event("2:kill:m1", tilt), event("3:sense:m1:roll=1", tilt)], TOPOLOGY, 10)
    with pytest.raises(EventError, match=r"'2:sense:m1:pitch=1'.*does not declare sensor pitch"):
        check_events([event("2:sense:m1:pitch=1", tilt)], TOPOLOGY, 10, sensors=tilt.sensor_names)
    check_events([event("2:sense:m1:pitch=1", tilt)], TOPOLOGY, 10)  # the program is not known: no check
    with pytest.raises(EventError, match="never happens"):
        check_events([event("10:sense:m1:roll=1", tilt)], TOPOLOGY, 10)


# ---------------------------------------------------------------- a Robot


def test_a_sense_event_moves_the_module(tilt: CompiledProgram) -> None:
    robot = Robot(tilt, TOPOLOGY)
    robot.run(3)
    assert [robot.engine(m).dof[1] for m in range(3)] == [0.0, 0.0, 0.0]
    robot.run(6, [event("5:sense:m1:roll=90", tilt)])
    assert [robot.engine(m).dof[1] for m in range(3)] == [0.0, 30.0, 0.0]
    assert robot.engine(1).var("seen") == 90
    assert "cycle 5: 5:sense:m1:roll=90" in robot.log
    robot.run(3, [event("9:sense:m1:roll=0", tilt)])
    assert robot.engine(1).dof[1] == 0.0


def test_a_sensed_value_holds_across_a_restart(tilt: CompiledProgram) -> None:
    robot = Robot(tilt, TOPOLOGY)
    robot.run(8, [event("1:sense:m0:roll=-100", tilt), event("4:restart:m0", tilt)])
    assert robot.sensed == {0: {"roll": -100}}
    e = robot.engine(0)
    assert e.sensors[tilt.sensor_names.index("roll")] == -100 and e.dof[1] == 30.0


def test_a_sense_event_the_robot_cannot_apply_names_itself(tilt: CompiledProgram) -> None:
    robot = Robot(tilt, TOPOLOGY)
    with pytest.raises(EventError, match=r"event '2:sense:m1:pitch=3' at cycle 2: the program does not declare"):
        robot.run(4, [event("2:sense:m1:pitch=3", tilt)])
    robot.kill(2)
    with pytest.raises(EventError, match="module m2 is not running"):
        robot.apply(event("5:sense:m2:roll=3", tilt))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("3:sense:m1:roll=181", "sensor roll reads -180..180 deg, not 181"),
        ("3:sense:m1:sonar=1", "profile conro has no sensor 'sonar'"),
        ("3:sense:m1:pitch=1", "does not declare sensor pitch"),
        ("3:sense:m1", "expected CYCLE:sense:M:NAME=VALUE"),
    ],
)
def test_cli_bad_sense_events_exit_2_naming_the_event(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, message: str
) -> None:
    source = tmp_path / "tilt.dh2"
    source.write_text(SOURCE)
    assert main(["run", str(source), "--topology", "snake:3", "--cycles", "8", "--event", text]) == 2
    err = capsys.readouterr().err
    assert text in err and message in err


def test_cli_sense_event_runs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    source = tmp_path / "tilt.dh2"
    source.write_text(SOURCE)
    argv = ["run", str(source), "--topology", "snake:3", "--cycles", "8", "--json", "--event", "2:sense:m2:roll=-60"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert '"DOF2": 30.0' in out
