"""firmware.motion.clearing: the robot crawls whole gait cycles of the caterpillar's wave, lies straight,
and looks again, until nothing lies on the spot (or its budget runs out); in physics, a dead
foot laid behind the dragon's tail is left behind before the next foot lets go. Whole
reconfigurations with a foot killed as it docks: test_legs_to_snake_physics.py."""

from __future__ import annotations

import math

import pytest

from dh2rt.compiler import compile_file
from dh2rt.events import parse_event
from dh2rt.profile import CONRO
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from firmware.motion.clearing import SETTLE_CYCLES, Clearing
from firmware.motion.gaits import caterpillar_schedule
from sim.runner import PhysicsRun
from tests.conftest import EXAMPLES

FRONT, BACK = CONRO.connector_index("front"), CONRO.connector_index("back")

BODY = [4, 7, 2]  # head first: module ids, not positions


def run_until_done(clearing: Clearing, limit: int = 10_000) -> list[dict[int, float]]:
    steps: list[dict[int, float]] = []
    while not clearing.done and len(steps) < limit:
        steps.append(clearing.step())
    return steps


@pytest.mark.parametrize("clear_after", [1, 2, 3])
def test_it_crawls_gait_cycles_until_the_spot_is_clear_and_looks_only_while_lying_straight(clear_after: int) -> None:
    looks: list[int] = []

    def taken() -> bool:
        looks.append(len(steps))
        return len(looks) < clear_after

    clearing = Clearing(BODY, taken, clock_cycle=8)
    steps: list[dict[int, float]] = []
    while not clearing.done:
        steps.append(clearing.step())
    per_gait = 8 + SETTLE_CYCLES
    assert clearing.cleared and clearing.gait_cycles == clear_after
    assert len(steps) == clear_after * per_gait + 1  # the last step hands the joints back: {}
    assert steps[-1] == {}
    wave = 0
    for k in range(clear_after):
        crawl = steps[k * per_gait : k * per_gait + 8]
        settle = steps[k * per_gait + 8 : (k + 1) * per_gait]
        for got in crawl:  # Table I over the body, head first, continuing from gait to gait
            assert got == dict(zip(BODY, caterpillar_schedule(len(BODY), wave, 8), strict=True))
            wave += 1
        assert all(got == dict.fromkeys(BODY, 0.0) for got in settle)
    # it looked once after each gait cycle's settling, never during the wave
    assert looks == [(k + 1) * per_gait for k in range(clear_after)]


def test_a_spot_that_stays_taken_ends_the_crawl_at_its_budget() -> None:
    clearing = Clearing(BODY, lambda: True, clock_cycle=8, max_gait_cycles=3)
    steps = run_until_done(clearing)
    assert clearing.done and not clearing.cleared and clearing.gait_cycles == 3
    assert len(steps) == 3 * (8 + SETTLE_CYCLES) + 1
    assert clearing.step() == {}


def test_an_empty_body_is_refused() -> None:
    with pytest.raises(ValueError, match="at least one module"):
        Clearing([], lambda: True)


# ---------------------------------------------------------------- in physics


def dead_foot_behind_the_tail(run: PhysicsRun, foot: int, behind_m: float) -> None:
    """Kill ``foot``, let go of its link and lay it (its centre) ``behind_m`` behind the tail's
    back, its front to the tail: where a foot killed as its dock began lies (its centre 12 to
    14 cm behind)."""
    run.robot.kill(foot)
    run.cut(foot, FRONT)
    tail = run.robot.topology.names.index("tail4")
    (px, py, pz), (nx, ny, _) = run.world.connector_pose(tail, BACK)
    run.world.set_module_pose(foot, (px + nx * behind_m, py + ny * behind_m, pz), math.degrees(math.atan2(-ny, -nx)))


@pytest.mark.parametrize(("seed", "behind_m"), [(0, 0.12), (1, 0.08), (2, 0.16)])
def test_the_robot_crawls_clear_of_a_dead_foot_before_the_next_foot_lets_go(seed: int, behind_m: float) -> None:
    """legs_to_snake on the dragon, left_leg0 dead behind the tail before LTS: the next
    winner's round starts with the robot crawling (the tail's docking sensor reading 1), and
    only once nothing lies on the spot does the foot let go and set off."""
    program = compile_file(str(EXAMPLES / "legs_to_snake.dh2"))
    dragon = parse_spec("dragon")
    robot = Robot(program, dragon, seed=seed)
    run = PhysicsRun(robot)
    dead, tail = dragon.names.index("left_leg0"), dragon.names.index("tail4")
    face = (tail, BACK)
    try:
        run.run(20)
        dead_foot_behind_the_tail(run, dead, behind_m)
        run.run(30)
        run.apply(parse_event("50:inject:spine0:LTS", dragon, program.vocabulary))
        docking_read: list[int] = []
        while not run.docking.trips and robot.cycle < 1200:
            run.cycle()
            if run.docking.clearings:
                docking_read.append(run.docking.docking_modules() == {tail})
        log = robot.log
        asked = [i for i, line in enumerate(log) if "lies behind tail4.back; the robot crawls clear first" in line]
        crawled = [i for i, line in enumerate(log) if "tail4.back: crawled" in line]
        assert len(asked) == 1 and "left_leg0 lies behind" in log[asked[0]], log
        assert len(crawled) == 1 and "the spot clear" in log[crawled[0]], log
        winner = run.docking.trips[0].trip.module
        released = [i for i, line in enumerate(log) if f"{dragon.names[winner]}.front released" in line]
        assert released and asked[0] < crawled[0] < released[0], log  # the foot let go only after
        assert docking_read and all(docking_read)
        assert run.docking.spot_taken(face, winner) is None
        # left behind by the crawl: its centre was laid behind_m from the face (measured: 11
        # to 14 cm further at seeds 0 to 2)
        (px, py, _), _ = run.world.connector_pose(*face)
        assert math.dist((px, py), run.world.module_position(dead)[:2]) > behind_m + 0.08
    finally:
        run.close()


def test_nothing_on_the_spot_no_crawl() -> None:
    """The spot is looked at once, when the round begins: with nothing lying apart the foot
    lets go at once (the runs of tests/sim/test_legs_to_snake_physics.py measure the rest)."""
    program = compile_file(str(EXAMPLES / "legs_to_snake.dh2"))
    dragon = parse_spec("dragon")
    run = PhysicsRun(Robot(program, dragon, seed=0))
    try:
        run.run(50)
        run.apply(parse_event("50:inject:spine0:LTS", dragon, program.vocabulary))
        while not run.docking.trips and run.robot.cycle < 300:
            run.cycle()
        assert run.docking.trips and not run.docking.clearings
        assert not any("crawls clear" in line for line in run.robot.log)
    finally:
        run.close()


def test_the_asking_module_lets_go_of_a_dead_foot_latched_to_its_face_before_it_crawls() -> None:
    """With the motions in the modules: a foot that died latched to the tail's back (killed
    as its dock closed: seed 7) has no link, so the rules let the next round begin, yet the
    latch still holds it. The asker lets go of its face before the robot crawls: the crawl
    leaves the body behind, where it would otherwise drag it along."""
    program = compile_file(str(EXAMPLES / "legs_to_snake.dh2"))
    dragon = parse_spec("dragon")
    robot = Robot(program, dragon, seed=0)
    run = PhysicsRun(robot, modules_move=True)
    dead, tail = dragon.names.index("left_leg0"), dragon.names.index("tail4")
    face = (tail, BACK)
    try:
        run.run(20)
        run.cut(dead, FRONT)
        (fx, fy, _), _ = run.world.connector_pose(dead, FRONT)
        centre_to_front = math.dist((fx, fy), run.world.module_position(dead)[:2])
        (px, py, pz), (nx, ny, _) = run.world.connector_pose(*face)
        at = (px + nx * centre_to_front, py + ny * centre_to_front, pz)
        run.world.set_module_pose(dead, at, math.degrees(math.atan2(-ny, -nx)))  # its front on the tail's back
        run.dock(tail, BACK, dead, FRONT)
        assert robot.peer_of(face) == (dead, FRONT), robot.log[-3:]
        robot.kill(dead)
        run.run(30)
        run.apply(parse_event("50:inject:spine0:LTS", dragon, program.vocabulary))
        log = robot.log

        def crawled() -> list[int]:
            return [i for i, line in enumerate(log) if line.startswith("tail4: ") and "reach_and_dock: crawled" in line]

        while robot.cycle < 1500 and not crawled():
            run.cycle()
        lies = f"module {dead} lies behind the face; the robot crawls clear"
        lying = [i for i, line in enumerate(log) if lies in line]
        released = [i for i, line in enumerate(log) if line.endswith("tail4.back released")]
        crawls = crawled()
        assert len(lying) == 1 and len(released) == 1 and len(crawls) == 1, log[-30:]
        assert lying[0] < released[0] < crawls[0], log[-30:]
        assert "the spot clear" in log[crawls[0]], log[crawls[0]]
        (px, py, _), _ = run.world.connector_pose(*face)
        assert math.dist((px, py), run.world.module_position(dead)[:2]) > 0.30  # left behind
    finally:
        run.close()
