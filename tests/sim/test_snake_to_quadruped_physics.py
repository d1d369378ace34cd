"""examples/snake_to_quadruped.dh2 in physics: a 9-module snake becomes a quadruped and a
3-module snake by its own motion, and both move away.

QSS enters at cycle 50 at m4. Each head in turn bends its front, by the chain of joints up to
the spine module that called it (a loop closing on the robot itself, with the pitch wave),
to that module's side, and lets go of the module behind it: m0 to m7's left, m1 to m8's
left, then (after the body has crawled straight and curled towards the right) m2 to m7's
right, m3 to m8's right; then m6 lets go of m7. The test checks the topology the robots end
in, the four links formed by motion (each within tolerance when it latched, female front to
male side, and in the trace: the asking module's record of that cycle carries ``dock``),
and that both robots move afterwards.
"""

from __future__ import annotations

import io
import json
import math

import numpy as np
import pybullet as p
import pytest

from dh2rt.compiler import compile_file
from dh2rt.events import parse_event
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from dh2rt.trace import TraceWriter
from sim.command import traced
from sim.runner import DOCK_TOLERANCE_DEG, DOCK_TOLERANCE_M, PhysicsRun
from tests.conftest import EXAMPLES
from tests.dh2rt.test_snake_to_quadruped import QUAD_LINKS, QUAD_TYPES
from tests.marks import sweep

#: Cycles the two robots may take to form (they formed after 2803 to 3383 cycles, seeds 0 to 2).
FORM_WITHIN = 4200
#: Cycles the robots run afterwards (30 gait cycles: the snake lies still for the first 240,
#: while the quadruped walks off past it), how far each one's centroid must move then, and by
#: how much their centroids must draw apart. Seeds 0 to 5: the quadruped moved 116.1 to 171.6
#: cm, the snake (backing away) 37.4 to 52.0 cm, and they drew apart by 57.3 to 105.3 cm; with
#: every joint held where it was when they formed (physics stepped alone), 0.1 to 0.6 cm and
#: 0.0 to 1.0 cm in 800 cycles.
AFTER = 1200
QUAD_MOVES_M = 0.30
SNAKE_MOVES_M = 0.20
APART_M = 0.30
#: Each module's up axis must stay within 60 degrees of vertical: the robots walk and crawl on
#: their feet and bellies, not rolled onto their sides (about 0) or backs (-1); a crawling
#: module's centre tilts with its 45-degree pitch (0.72 seen).
UPRIGHT = 0.5
QUADRUPED, SNAKE = (0, 1, 2, 3, 7, 8), (4, 5, 6)
#: (asking module, its connector), (target module, its connector), in the order they latch.
DOCKS = [
    ((0, "front"), (7, "left")),
    ((1, "front"), (8, "left")),
    ((2, "front"), (7, "right")),
    ((3, "front"), (8, "right")),
]


@pytest.mark.slow
@pytest.mark.parametrize(("seed", "at"), sweep([(0, "m4"), (1, "m4"), (2, "m4")], keep=(2,)))
def test_snake_becomes_quadruped_and_snake_in_physics_and_both_move(seed: int, at: str) -> None:
    prog = compile_file(str(EXAMPLES / "snake_to_quadruped.dh2"))
    topo = parse_spec("snake:9")
    robot = Robot(prog, topo, seed=seed)
    robot.record = True
    run = PhysicsRun(robot)
    stream = io.StringIO()
    trace = TraceWriter(stream, robot, extra=lambda m: traced(run, m, list(run.world.module_position(m))))
    names, conn, idx = topo.names, robot.profile.connector_name, robot.profile.connector_index

    def write(_c: int) -> None:
        trace.write_cycle()

    try:
        run.run(50, [], write)
        run.run(1, [parse_event(f"50:inject:{at}:QSS", topo, prog.vocabulary)], write)
        while sum("released" in line for line in robot.log) < 5 and robot.cycle < FORM_WITHIN:
            run.run(1, [], write)
        links = {(names[x.a], conn(x.a_conn), names[x.b], conn(x.b_conn)) for x in robot.links()}
        assert links == QUAD_LINKS, robot.log[-8:]
        assert run.world.links() == set(robot.links())  # the latches are the logical links
        assert [e.topo_type.name for e in robot.engines if e is not None] == QUAD_TYPES
        # the four links made by motion, each within tolerance when it latched, female to male
        assert [(c.asking, c.target) for c in run.contacts] == [
            ((a, idx(ac)), (b, idx(bc))) for (a, ac), (b, bc) in DOCKS
        ]
        records = [json.loads(line) for line in stream.getvalue().splitlines()]
        docks = [r for r in records if "dock" in r]
        assert [(r["module"], r["cycle"]) for r in docks] == [(c.asking[0], c.cycle) for c in run.contacts]
        for contact, rec in zip(run.contacts, docks, strict=True):
            assert rec["dock"] == contact.as_dict()
            assert math.isclose(contact.distance_m, math.dist(contact.asking_face, contact.target_face), abs_tol=1e-9)
            assert contact.distance_m <= DOCK_TOLERANCE_M and contact.attitude_deg <= DOCK_TOLERANCE_DEG
            assert 0 < contact.ir_mm <= DOCK_TOLERANCE_M * 1000 and contact.ir_align_deg <= DOCK_TOLERANCE_DEG
        # a motion that gave up linked nothing, and its head asked again
        assert sum("gave up" in line for line in robot.log) == len(run.failed)
        assert sum("bending" in line for line in robot.log) == 4 + len(run.failed)

        def up(m: int) -> float:  # the z component of the module's own up axis
            _pos, orn = p.getBasePositionAndOrientation(run.world.body(m), physicsClientId=run.world.client)
            return float(p.getMatrixFromQuaternion(orn)[8])

        assert min(up(m) for m in range(9)) >= UPRIGHT

        # the two robots move away, each by its own gait, and stay upright
        def centroid(group: tuple[int, ...]) -> tuple[float, float]:
            x = np.mean(np.asarray([run.world.module_position(m) for m in group], dtype=np.float64), axis=0)
            return float(x[0]), float(x[1])

        q0, s0 = centroid(QUADRUPED), centroid(SNAKE)
        run.run(AFTER, [])
        q1, s1 = centroid(QUADRUPED), centroid(SNAKE)
        quad_moved, snake_moved = math.dist(q0, q1), math.dist(s0, s1)
        apart = math.dist(q1, s1) - math.dist(q0, s0)
        assert quad_moved >= QUAD_MOVES_M, f"the quadruped moved {quad_moved * 100:.1f} cm in {AFTER} cycles"
        assert snake_moved >= SNAKE_MOVES_M, f"the snake moved {snake_moved * 100:.1f} cm in {AFTER} cycles"
        assert apart >= APART_M, f"they drew apart by {apart * 100:.1f} cm in {AFTER} cycles"
        assert min(up(m) for m in range(9)) >= UPRIGHT
        links = {(names[x.a], conn(x.a_conn), names[x.b], conn(x.b_conn)) for x in robot.links()}
        assert links == QUAD_LINKS
    finally:
        run.close()
