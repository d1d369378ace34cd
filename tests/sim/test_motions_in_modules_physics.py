"""The three reconfigurations in physics with the docking motions in the modules
(``PhysicsRun(modules_move=True)``, sim.module_motions): every module runs its own
firmware.motion.host.MotionHost, the code a module process runs; the chains' frames cross
the robot's links a hop a cycle; the run plans nothing and holds no joint (its own docking
sequence stays idle), it plays physics, links and sensors. Each latch within tolerance.

Measured before and after in one sitting: ``python -m benchmarks.bench_motions_in_modules``.
"""

from __future__ import annotations

import pytest

from dh2rt.compiler import compile_file
from dh2rt.events import parse_event
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from sim import legs_to_snake
from sim.legs_to_snake import BACK, FRONT, snake_of
from sim.runner import DOCK_TOLERANCE_DEG, DOCK_TOLERANCE_M, PhysicsRun
from tests.conftest import EXAMPLES
from tests.dh2rt.test_snake_to_quadruped import QUAD_LINKS, QUAD_TYPES
from tests.dh2rt.test_snake_to_t import T_LINKS
from tests.marks import LONG, sweep


def _planned_nothing(run: PhysicsRun) -> None:
    """The run's own sequence never moved a joint: no reach, no trip, no crawl of its own."""
    d = run.docking
    assert not d.outcomes and not d.arrivals and not d.trips_done and not d.busy


def _within_tolerance(run: PhysicsRun, count: int) -> None:
    assert len(run.contacts) == count, run.robot.log[-8:]
    for c in run.contacts:
        assert c.distance_m <= DOCK_TOLERANCE_M and c.attitude_deg <= DOCK_TOLERANCE_DEG, c
        assert 0 < c.ir_mm <= DOCK_TOLERANCE_M * 1000 and c.ir_align_deg <= DOCK_TOLERANCE_DEG, c
    own = [line for line in run.robot.log if "by motion, the module's own" in line]
    assert len(own) == count, own


def _links(robot: Robot) -> set[tuple[str, str, str, str]]:
    names, conn = robot.topology.names, robot.profile.connector_name
    return {(names[x.a], conn(x.a_conn), names[x.b], conn(x.b_conn)) for x in robot.links()}


@pytest.mark.parametrize(("seed", "at"), sweep([(0, "m4"), (1, "m0"), (2, "m7")]))
def test_snake_to_t_with_the_motion_in_the_head(seed: int, at: str) -> None:
    prog = compile_file(str(EXAMPLES / "snake_to_t.dh2"))
    topo = parse_spec("snake:8")
    robot = Robot(prog, topo, seed=seed)
    run = PhysicsRun(robot, modules_move=True)
    try:
        run.run(50)
        run.run(1, [parse_event(f"50:inject:{at}:STT", topo, prog.vocabulary)])
        while not any("released" in line for line in robot.log) and robot.cycle < 1000:
            run.run(1)
        assert _links(robot) == T_LINKS, robot.log[-8:]
        assert run.world.links() == set(robot.links())  # the latches are the logical links
        _within_tolerance(run, 1)
        _planned_nothing(run)
        assert any("m0: cycle" in line and "reach_dock from m0: linked" in line for line in robot.log)
    finally:
        run.close()


@LONG
def test_snake_to_quadruped_with_the_motions_in_the_heads() -> None:
    prog = compile_file(str(EXAMPLES / "snake_to_quadruped.dh2"))
    topo = parse_spec("snake:9")
    robot = Robot(prog, topo, seed=0)
    run = PhysicsRun(robot, modules_move=True)
    try:
        run.run(50)
        run.run(1, [parse_event("50:inject:m4:QSS", topo, prog.vocabulary)])
        while sum("released" in line for line in robot.log) < 5 and robot.cycle < 6000:
            run.run(1)
        assert _links(robot) == QUAD_LINKS, robot.log[-8:]
        assert [e.topo_type.name for e in robot.engines if e is not None] == QUAD_TYPES
        _within_tolerance(run, 4)
        _planned_nothing(run)
    finally:
        run.close()


@LONG
@pytest.mark.parametrize("seed", [0, 1])
def test_legs_to_snake_with_the_motions_in_the_tail_and_the_feet(seed: int) -> None:
    program = compile_file(str(EXAMPLES / "legs_to_snake.dh2"))
    run, formed = legs_to_snake.reconfigure(program, seed, modules_move=True)
    robot = run.robot
    try:
        assert formed is not None, robot.log[-8:]
        chain = snake_of(robot)
        assert chain is not None and len(chain) == 11
        _within_tolerance(run, 4)
        for c in run.contacts:
            assert c.asking[1] == BACK and c.target[1] == FRONT
        assert chain[-4:] == [c.target[0] for c in run.contacts]
        _planned_nothing(run)
        # each foot ran its own trip and creep, told by a SET_OFF
        assert sum(": foot set_off motion" in line for line in robot.log) == 4
        assert sum(": foot docked front linked" in line for line in robot.log) == 4
    finally:
        run.close()
