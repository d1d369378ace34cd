"""examples/locomotion.dh2's side legs steer by their own IMU (``S.yaw``), in one process.

Each side leg notes its yaw when Stand reaches it; from then on it strokes SteerNum /
SteerDen degrees further at each end per degree the robot has turned towards its side (a
left leg: yaw up; a right leg: yaw down), and the opposite side less. Here a ``sense`` event
stands in for the IMU; tests/sim/test_legged_gaits.py measures the heading it keeps in physics.
"""

from __future__ import annotations

import pytest

from dh2rt.events import parse_event
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec

QUADRUPED = parse_spec("quadruped")
SWING, STEER = 60, 3 / 2  # locomotion.dh2's Swing and SteerNum / SteerDen


def strokes(program: CompiledProgram, events: list[str], cycles: int = 200) -> dict[str, tuple[float, float]]:
    """Each leg's smallest and largest DOF2 target over ``cycles`` after the first gait cycle."""
    robot = Robot(program, QUADRUPED, seed=0)
    legs = {n: QUADRUPED.names.index(n) for n in QUADRUPED.names if "leg" in n}
    robot.run(40, [parse_event(e, QUADRUPED, program.vocabulary) for e in events])
    seen: dict[str, list[float]] = {n: [] for n in legs}
    for _ in range(cycles):
        robot.run(1)
        for n, m in legs.items():
            seen[n].append(robot.engine(m).dof[1])
    return {n: (min(v), max(v)) for n, v in seen.items()}


def test_without_a_turn_every_leg_strokes_swing_to_either_side(locomotion: CompiledProgram) -> None:
    assert set(strokes(locomotion, []).values()) == {(-SWING, SWING)}


@pytest.mark.parametrize("turned", [10, -10, 20])
def test_turned_one_way_the_legs_on_that_side_stroke_further_and_the_others_less(
    locomotion: CompiledProgram, turned: int
) -> None:
    """The robot turned left (yaw up): the left legs reach further, the right ones less, so
    the left side pushes the robot round to the right; turned right, the other way."""
    events = [f"20:sense:{leg}:yaw={turned}" for leg in ("left_leg0", "left_leg1", "right_leg0", "right_leg1")]
    got = strokes(locomotion, events)
    left, right = SWING + int(turned * STEER), SWING - int(turned * STEER)
    assert got["left_leg0"] == got["left_leg1"] == (-left, left)
    assert got["right_leg0"] == got["right_leg1"] == (-right, right)


def test_a_leg_steers_from_where_it_stood_not_from_where_it_booted(locomotion: CompiledProgram) -> None:
    """A leg that had already turned 90 degrees when Stand reached it (a quadruped formed
    from a snake) strokes Swing until the robot turns from there."""
    got = strokes(locomotion, ["0:sense:left_leg0:yaw=90"])
    assert got["left_leg0"] == (-SWING, SWING)
