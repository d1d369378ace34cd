"""Docking by the modules' own motion in physics (firmware.motion.reach through sim.runner.PhysicsRun).

A 3-module snake and a module lying apart: the lone module is placed where the snake's tail
could reach if it bent (its yaws at the angles given), facing it, offset and turned a little;
the tail then starts straight. The tail's chain bends, aligns and approaches until the latch
closes. Every new link must have formed with the two faces within the runner's tolerance at
that moment, in the world's own measurement and in the tail's infrared reading (the record
kept in PhysicsRun.contacts); no body is teleported during the motion. Each case is a few
seconds of simulated time; on the shared, loaded machine the file took minutes.
"""

from __future__ import annotations

import math

import pytest

from dh2rt.compiler import compile_source
from dh2rt.profile import CONRO
from dh2rt.robot import Robot
from dh2rt.topology import Link, Topology
from sim.runner import DOCK_TOLERANCE_DEG, DOCK_TOLERANCE_M, PhysicsRun

BACK, FRONT = CONRO.connector_index("back"), CONRO.connector_index("front")
#: A program that holds every joint where it is: only the docking motion moves.
STILL = compile_source("program still\nconst ClockCycle = 40\n")
TOPOLOGY = Topology(CONRO, ("m0", "m1", "m2", "lone"), (Link(0, BACK, 1, FRONT), Link(1, BACK, 2, FRONT)), "3+1")


def scene(seed: int, bend: tuple[float, float], offset_m: float, turn_deg: float, gap_m: float) -> PhysicsRun:
    """The snake's tail bent by ``bend`` (m2's and m1's yaw), its back face noted, the lone
    module's front put there (``gap_m`` out, ``offset_m`` aside, turned ``turn_deg``), and
    the tail straightened again."""
    robot = Robot(STILL, TOPOLOGY, seed=seed)
    run = PhysicsRun(robot)
    w = run.world
    w.set_targets(2, 0.0, bend[0])
    w.set_targets(1, 0.0, bend[1])
    w.step(480)
    face, normal = w.connector_pose(2, BACK)
    heading = math.atan2(normal[1], normal[0])
    yaw = heading + math.pi + math.radians(turn_deg)
    fx = face[0] + normal[0] * gap_m - normal[1] * offset_m
    fy = face[1] + normal[1] * gap_m + normal[0] * offset_m
    w.set_targets(2, 0.0, 0.0)
    w.set_targets(1, 0.0, 0.0)
    w.step(480)
    reach = w.model.centre.half[0] + w.model.front.size[0]  # centre body to front face
    w.set_module_pose(
        3, (fx - math.cos(yaw) * reach, fy - math.sin(yaw) * reach, w.model.height / 2 + 0.001), math.degrees(yaw)
    )
    w.step(60)
    return run


CASES = [
    (0, (50.0, 30.0), 0.0, 0.0, 0.0),
    (1, (-45.0, -35.0), 0.005, 8.0, 0.01),
    (2, (60.0, 0.0), -0.005, -10.0, 0.005),
    # did not latch within 300 cycles before the close phase was bounded (firmware.motion.reach.CLOSE_CYCLES)
    (3, (-30.0, -50.0), 0.0, 12.0, 0.015),
]


@pytest.mark.parametrize(("seed", "bend", "offset", "turn", "gap"), CASES)
def test_tail_bends_aligns_and_docks_within_tolerance(
    seed: int, bend: tuple[float, float], offset: float, turn: float, gap: float
) -> None:
    run = scene(seed, bend, offset, turn, gap)
    try:
        before = run.world.links()
        start = run.world.connector_pose(3, FRONT)[0]
        assert not run.world.aligned(2, BACK, 3, FRONT, DOCK_TOLERANCE_M, DOCK_TOLERANCE_DEG)
        assert run.docking.reach_other(2, BACK, (FRONT, FRONT), (3, FRONT))
        for _ in range(300):
            run.cycle()
            if not run.docking.motions:
                break
        assert not run.docking.motions and not run.failed, run.robot.log
        assert run.world.links() - before == {Link(2, BACK, 3, FRONT)}
        assert run.robot.peer_of((2, BACK)) == (3, FRONT)
        (contact,) = run.contacts
        assert contact.distance_m <= DOCK_TOLERANCE_M and contact.attitude_deg <= DOCK_TOLERANCE_DEG
        assert 0 < contact.ir_mm <= DOCK_TOLERANCE_M * 1000 and contact.ir_align_deg <= DOCK_TOLERANCE_DEG
        assert math.isclose(contact.distance_m, math.dist(contact.asking_face, contact.target_face), abs_tol=1e-9)
        # the lone module was not carried to the tail: it was pushed at most a little
        assert math.dist(start, contact.target_face) < 0.02
        # the tail really bent: its yaw is far from straight at the latch
        assert max(abs(a) for a in (run.world.joint_angles(2)[1], run.world.joint_angles(1)[1])) > 15.0
    finally:
        run.close()


def test_target_out_of_reach_gives_up_and_links_nothing() -> None:
    run = scene(0, (0.0, 0.0), 0.0, 0.0, 0.08)  # 8 cm straight out: the chain cannot stretch
    try:
        before = run.world.links()
        assert run.docking.reach_other(2, BACK, (FRONT, FRONT), (3, FRONT), timeout=120)
        for _ in range(200):
            run.cycle()
        assert not run.docking.motions and not run.contacts
        (failed,) = run.failed
        assert failed.distance_m > DOCK_TOLERANCE_M
        assert run.world.links() == before and run.robot.peer_of((2, BACK)) is None
    finally:
        run.close()


def test_male_to_male_is_refused() -> None:
    run = scene(0, (40.0, 20.0), 0.0, 0.0, 0.0)
    try:
        assert not run.docking.reach_other(2, BACK, (FRONT, FRONT), (3, BACK))
        assert any("both connectors are male" in line for line in run.robot.log)
    finally:
        run.close()
