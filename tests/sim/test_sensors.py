"""Sensors from physics (sim.sensors, PhysicsRun): IMU roll and pitch, infrared per connector,
ground contact, joint positions and loads; sense events forcing values in a physics run."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import pybullet as p
import pytest

from dh2rt.cli import main
from dh2rt.compiler import compile_source
from dh2rt.errors import PhysicsWorldError
from dh2rt.events import parse_event
from dh2rt.profile import CONRO
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.topology import Topology, parse_spec
from firmware.motion.body import BACK, FRONT
from sim.gaits import run_caterpillar
from sim.runner import PhysicsRun
from sim.sensors import IR_NEAR_M, NOTHING_IN_VIEW_DEG, PhysicsSensors, physics_sensor_names
from sim.world import World

ROLL_TOLERANCE_DEG = 5.0
IR_TOLERANCE_MM = 5.0
Z_REST = 0.0254 / 2 + 0.001  # a module's centre height lying on the floor

WATCHER = """
program watcher
const ClockCycle = 4
sensor roll, pitch, contact, ir_front, pos1
var roll = 0
var ir_front = 0
receptor watch { V.roll = S.roll; V.ir_front = S.ir_front; keep_alive() }
"""


@pytest.fixture(scope="module")
def watcher() -> CompiledProgram:
    return compile_source(WATCHER, "watcher.dh2")


def loose(n: int) -> Topology:
    return Topology(CONRO, tuple(f"m{i}" for i in range(n)), (), "loose")


@pytest.fixture
def pair() -> Iterator[World]:
    """Two undocked modules on the floor, nothing between them yet."""
    with World(loose(3)) as w:
        w.set_module_pose(2, (0.0, 1.0, Z_REST), 0.0)  # out of the way until a test needs it
        yield w


def face_to_face(w: World, gap_m: float, yaw_1_deg: float = 0.0) -> None:
    """Module 0's front facing module 1's back across ``gap_m`` (module 1 turned by ``yaw_1_deg``)."""
    front_x = w.model.centre.half[0] + w.model.front.size[0]
    back_x = w.model.centre.half[0] + w.model.back.size[0]
    w.set_module_pose(0, (0.0, 0.0, Z_REST), 0.0)
    w.set_module_pose(1, (front_x + gap_m + back_x, 0.0, Z_REST), yaw_1_deg)
    w.step(24)


def roll_over(w: World, module: int, roll_deg: float, yaw_deg: float = 30.0) -> None:
    """Lay ``module`` down rolled by ``roll_deg`` (and some heading) and let it settle."""
    orn = p.getQuaternionFromEuler((math.radians(roll_deg), 0.0, math.radians(yaw_deg)))
    p.resetBasePositionAndOrientation(w.body(module), (0.0, 0.0, 0.02), orn, physicsClientId=w.client)
    w.step(240)


# ---------------------------------------------------------------- IMU


@pytest.mark.parametrize("roll", [90.0, -90.0, 180.0])
def test_a_module_rolled_over_reads_its_roll(roll: float) -> None:
    with World(parse_spec("snake:1")) as w:
        sensors = PhysicsSensors(w, ["roll", "pitch"])
        upright = sensors.read([0])[0]
        assert abs(upright["roll"]) < 1.0 and abs(upright["pitch"]) < 1.0
        roll_over(w, 0, roll)
        got = sensors.read([0])[0]
        # upside down is +180 or -180: the same attitude
        error = (got["roll"] - roll + 180.0) % 360.0 - 180.0
        assert abs(error) <= ROLL_TOLERANCE_DEG, got
        assert abs(got["pitch"]) <= ROLL_TOLERANCE_DEG, got


def test_pitch_is_positive_front_end_down() -> None:
    with World(parse_spec("snake:1")) as w:
        orn = p.getQuaternionFromEuler((0.0, math.radians(30.0), 0.0))
        p.resetBasePositionAndOrientation(w.body(0), (0.0, 0.0, 0.3), orn, physicsClientId=w.client)
        w.step(1)
        front, _ = w.connector_pose(0, "front")
        back, _ = w.connector_pose(0, "back")
        assert front[2] < back[2]  # the front end is the lower one
        assert PhysicsSensors(w, ["pitch"]).read([0])[0]["pitch"] == pytest.approx(30.0, abs=1.0)


def test_yaw_is_the_turn_since_the_first_reading_left_positive_and_unwrapped() -> None:
    """The heading a gyro integrates: 0 at the first reading whatever the module's heading in
    the world, positive turning left (counter-clockwise seen from above), and on past 180
    degrees as the module goes on turning (read at least every half turn)."""
    with World(parse_spec("snake:1")) as w:
        w.set_module_pose(0, (0.0, 0.0, Z_REST), 130.0)
        w.step(24)
        sensors = PhysicsSensors(w, ["yaw"])
        assert sensors.read([0])[0]["yaw"] == pytest.approx(0.0, abs=0.5)
        for turned in (60, 120, 180, 240, 300, 420, 300, 180, 60, 0, -100, -200):
            w.set_module_pose(0, (0.0, 0.0, Z_REST), 130.0 + turned)
            w.step(24)
            assert sensors.read([0])[0]["yaw"] == pytest.approx(turned, abs=1.0)
            _, normal = w.connector_pose(0, "front")
        # left positive: the front's normal points 130 - 200 = -70 degrees off the world's x
        assert math.degrees(math.atan2(normal[1], normal[0])) == pytest.approx(-70.0, abs=1.0)


def test_a_physics_run_fills_the_sensors_a_program_declares(watcher: CompiledProgram) -> None:
    """End to end: a rolled-over module's program sees S.roll, rounded to an integer."""
    run = PhysicsRun(Robot(watcher, parse_spec("snake:1")))
    try:
        run.run(4)
        e = run.robot.engine(0)
        assert e.var("roll") == 0 and e.sensors[watcher.sensor_names.index("contact")] == 1
        roll_over(run.world, 0, 90.0)
        run.run(4)
        roll = e.var("roll")
        assert isinstance(roll, int) and abs(roll - 90) <= ROLL_TOLERANCE_DEG
        assert set(run.sensors.names) == {"roll", "pitch", "contact", "ir_front", "pos1"}
    finally:
        run.close()


# ---------------------------------------------------------------- infrared


@pytest.mark.parametrize("gap_mm", [20.0, 50.0, 80.0])
def test_a_connector_facing_another_reads_its_distance(pair: World, gap_mm: float) -> None:
    face_to_face(pair, gap_mm / 1000)
    got = PhysicsSensors(pair, physics_sensor_names(pair.model)).read([0, 1])
    assert got[0]["ir_front"] == pytest.approx(gap_mm, abs=IR_TOLERANCE_MM)
    assert got[1]["ir_back"] == pytest.approx(gap_mm, abs=IR_TOLERANCE_MM)
    assert got[0]["ir_front_align"] <= 5.0 and got[1]["ir_back_align"] <= 5.0
    # nothing faces the other connectors
    for m, c in ((0, "back"), (0, "left"), (0, "right"), (1, "front"), (1, "left"), (1, "right")):
        assert got[m][f"ir_{c}"] == 0.0 and got[m][f"ir_{c}_align"] == NOTHING_IN_VIEW_DEG, (m, c)


def test_a_connector_turned_away_reads_nothing(pair: World) -> None:
    sensors = PhysicsSensors(pair, ["ir_front", "ir_front_align"])
    face_to_face(pair, 0.050, yaw_1_deg=45.0)  # module 1's faces all 45 degrees off
    assert sensors.read([0])[0] == {"ir_front": 0.0, "ir_front_align": NOTHING_IN_VIEW_DEG}
    face_to_face(pair, 0.050)
    pair.set_module_pose(0, (0.0, 0.0, Z_REST), 180.0)  # module 0 looks the other way
    pair.step(24)
    assert sensors.read([0])[0]["ir_front"] == 0.0


def test_a_face_askew_within_the_cone_reads_its_angle(pair: World) -> None:
    face_to_face(pair, 0.050, yaw_1_deg=15.0)
    got = PhysicsSensors(pair, ["ir_front", "ir_front_align"]).read([0])[0]
    assert got["ir_front_align"] == pytest.approx(15.0, abs=2.0)
    assert 40.0 <= got["ir_front"] <= 60.0


def test_a_module_without_power_is_dark_and_sees_again_when_powered(pair: World) -> None:
    """A killed module's emitters are dark: no pair sees its faces (the asker's dead-foot
    signal, firmware.motion.assimilating.DARK_CYCLES); powered again, it is seen."""
    sensors = PhysicsSensors(pair, ["ir_front", "ir_back"])
    face_to_face(pair, 0.050)
    try:
        pair.unpowered = {1}
        got = sensors.read([0, 1])
        assert got[0]["ir_front"] == 0.0  # module 1's back is dark
        assert got[1]["ir_back"] == pytest.approx(50.0, abs=IR_TOLERANCE_MM)  # module 0's front is lit
        pair.unpowered = set()
        assert sensors.read([0])[0]["ir_front"] == pytest.approx(50.0, abs=IR_TOLERANCE_MM)
    finally:
        pair.unpowered = set()


def test_beyond_range_reads_nothing(pair: World) -> None:
    face_to_face(pair, 0.120)
    assert PhysicsSensors(pair, ["ir_front"]).read([0])[0]["ir_front"] == 0.0


def test_a_module_in_between_blocks_the_view(pair: World) -> None:
    sensors = PhysicsSensors(pair, ["ir_front"])
    face_to_face(pair, 0.090)
    assert sensors.read([0])[0]["ir_front"] == pytest.approx(90.0, abs=IR_TOLERANCE_MM)
    # module 2 across the line of sight: its side faces point along y, its end faces are
    # out of module 0's cone, its centre body stands in the way
    middle = pair.model.centre.half[0] + pair.model.front.size[0] + 0.045
    pair.set_module_pose(2, (middle, 0.0, Z_REST), 90.0)
    pair.step(12)
    assert sensors.read([0])[0]["ir_front"] == 0.0


def test_docked_faces_read_contact() -> None:
    with World(parse_spec("snake:3")) as w:
        w.step(24)
        got = PhysicsSensors(w, physics_sensor_names(w.model)).read([0, 1, 2])
        assert got[0]["ir_back"] == 1.0 and got[1]["ir_front"] == 1.0 and got[1]["ir_back"] == 1.0
        assert got[0]["ir_front"] == 0.0 and got[2]["ir_back"] == 0.0


def test_docked_faces_see_each_other_while_the_robot_crawls() -> None:
    """The dock's soft constraint lets mated faces part by millimetres and twist as the
    snake bends: they still see each other, at most IR_NEAR_M apart."""
    with World(parse_spec("snake:5")) as w:
        sensors = PhysicsSensors(w, ["ir_front", "ir_back"])
        seen: list[float] = []

        def look(_cycle: int) -> None:
            got = sensors.read(range(5))
            seen.extend(got[m]["ir_back"] for m in range(4))
            seen.extend(got[m]["ir_front"] for m in range(1, 5))

        run_caterpillar(w, 64, on_step=look)
        assert min(seen) >= 1.0 and max(seen) <= IR_NEAR_M * 1000
        assert max(seen) > 1.0  # they do part: the near rule is what keeps them in view


# ---------------------------------------------------------------- contact and joints


def test_ground_contact() -> None:
    with World(parse_spec("snake:1")) as w:
        sensors = PhysicsSensors(w, ["contact"])
        w.step(12)
        assert sensors.read([0])[0]["contact"] == 1.0
        w.set_module_pose(0, (0.0, 0.0, 0.5), 0.0)
        w.step(1)
        assert sensors.read([0])[0]["contact"] == 0.0


def test_joint_positions_follow_the_servos() -> None:
    with World(parse_spec("snake:1")) as w:
        sensors = PhysicsSensors(w, ["pos1", "pos2"])
        w.set_targets(0, -40.0, 25.0)
        w.step(120)
        got = sensors.read([0])[0]
        assert got["pos1"] == pytest.approx(-40.0, abs=1.0) and got["pos2"] == pytest.approx(25.0, abs=1.0)


def test_joint_load_is_the_torque_held_against_gravity() -> None:
    """A module hung by its centre holds its front body level: DOF1 carries the front body's
    weight times its lever, as a percentage of the servo's 0.3 N*m (about 1.7 %)."""
    with World(parse_spec("snake:1")) as w:
        body = w.body(0)
        p.resetBasePositionAndOrientation(body, (0.0, 0.0, 0.5), (0.0, 0.0, 0.0, 1.0), physicsClientId=w.client)
        p.changeDynamics(body, -1, mass=0.0, physicsClientId=w.client)  # pinned in the air
        w.step(120)
        front = w.model.front
        expected = -100.0 * front.mass * 9.81 * front.half[0] / w.model.dof1.max_torque_nm
        got = PhysicsSensors(w, ["load1", "load2"]).read([0])[0]
        assert got["load1"] == pytest.approx(expected, abs=0.2)
        assert abs(got["load2"]) < 0.2  # the yaw joint holds nothing up
        assert w.driver(0).read_loads() == pytest.approx((got["load1"], got["load2"]))
        w.set_targets(0, 90.0, 0.0)  # front body hanging straight down: no lever
        w.step(240)
        assert abs(PhysicsSensors(w, ["load1"]).read([0])[0]["load1"]) < 0.2


def test_only_what_is_named_is_read() -> None:
    with World(parse_spec("snake:2")) as w:
        assert PhysicsSensors(w, ["light", "roll"]).names == ("roll",)
        assert PhysicsSensors(w, ["light"]).read([0, 1]) == {0: {}, 1: {}}
        got = PhysicsSensors(w, ["ir_left_align"]).read([1])
        assert set(got[1]) == {"ir_left", "ir_left_align"}
        # every sensor but the docking motion's state, which the runner fills (sim.runner), and
        # the overhead tracker's, which sim.tracker fills
        tracker = {"floor_x", "floor_y", "floor_heading"}
        assert set(physics_sensor_names(w.model)) == set(CONRO.sensor_names) - {"docking"} - tracker


def test_sensor_geometry_matches_the_world() -> None:
    """The infrared's own connector poses agree with World.connector_pose, joints bent."""
    with World(parse_spec("snake:2"), seed=3) as w:
        w.set_targets(0, 35.0, -20.0)
        w.step(60)
        faces, normals = PhysicsSensors(w, ["ir_front"]).connector_poses()
        for m in (0, 1):
            for i, c in enumerate(w.model.connectors):
                pos, normal = w.connector_pose(m, c.index)
                assert faces[m, i] == pytest.approx(pos, abs=1e-6)
                assert normals[m, i] == pytest.approx(normal, abs=1e-6)
        assert {c.link for c in w.model.connectors} == {FRONT, BACK}


# ---------------------------------------------------------------- sense events in physics


def test_a_sense_event_holds_against_the_physics(watcher: CompiledProgram) -> None:
    robot = Robot(watcher, parse_spec("snake:2"))
    run = PhysicsRun(robot)
    try:
        events = [parse_event(e, robot.topology, watcher.vocabulary) for e in ("3:sense:m1:roll=-120", "6:restart:m1")]
        run.run(12, events)
        assert robot.engine(1).var("roll") == -120  # physics says 0: the event holds, across the restart
        assert robot.engine(0).var("roll") == 0  # the other module still reads its body
        assert robot.engine(1).var("ir_front") == 1  # and module 1's other sensors still follow it
        run.run(2, [parse_event("12:sense:m1:roll=7", robot.topology, watcher.vocabulary)])
        assert robot.engine(1).var("roll") == 7
    finally:
        run.close()


@pytest.mark.parametrize(
    ("event", "message"),
    [
        ("3:sense:m0:roll=500", "reads -180..180 deg, not 500"),
        ("3:sense:m0:light=1", "profile conro has no sensor 'light'"),
        ("3:sense:m0:load1=-101", "reads -100..100 %, not -101"),
        ("3:sense:m0:roll", "expected NAME=VALUE"),
        ("3:sense:m0:roll=tilted", "'tilted' is not a whole number"),
        ("3:sense:m0:pitch=10", "does not declare sensor pitch"),
    ],
)
def test_bad_sense_events_in_a_physics_run_exit_2_naming_the_event(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], event: str, message: str
) -> None:
    source = tmp_path / "rolls.dh2"
    source.write_text("const ClockCycle = 4\nsensor roll\nreceptor r when S.roll > 45 { DOF2(30) }\n")
    code = main(["run", str(source), "--sim", "pybullet", "--topology", "snake:2", "--cycles", "6", "--event", event])
    err = capsys.readouterr().err
    assert code == 2
    assert event in err and message in err


@pytest.mark.parametrize(("range_m", "cone_deg"), [(0.0, 30.0), (0.1, 0.0), (0.1, 90.0)])
def test_bad_infrared_settings_are_refused(range_m: float, cone_deg: float) -> None:
    with World(parse_spec("snake:1")) as w, pytest.raises(PhysicsWorldError, match="infrared range"):
        PhysicsSensors(w, ["ir_front"], ir_range_m=range_m, ir_cone_deg=cone_deg)
