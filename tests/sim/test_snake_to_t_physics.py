"""examples/snake_to_t.dh2 in physics: an 8-module snake becomes a T by its own motion.

STT enters at cycle 50 (at a body module, the head or the tail). The head bends its front,
by the chain of m0..m4's joints (a loop closing on the robot itself, the chain's pitch wave
unloading the modules in turn), to m5's left side; the latch closes only within the runner's tolerance; two hops back m2
releases its back link. The test checks the topology the robot ends in, the one link formed
by motion (its face poses at that moment, recorded in the run), and that the new robot, a
bar of five led by m3 with a stem of three, moves afterwards.
"""

from __future__ import annotations

import math

import pytest

from dh2rt.compiler import compile_file
from dh2rt.events import parse_event
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from sim.runner import DOCK_TOLERANCE_DEG, DOCK_TOLERANCE_M, PhysicsRun
from tests.conftest import EXAMPLES
from tests.dh2rt.test_snake_to_t import T_LINKS

#: Cycles the T may take to form (it formed after 264 to 335 cycles with seeds 0 to 5).
FORM_WITHIN = 800
#: Cycles the T runs afterwards (15 gait cycles), and how far its centroid must move then:
#: it moved 15 to 28 cm with seeds 0 to 5; with its joints held where they were when it
#: formed (physics stepped alone), 0.1 to 1.0 cm, seeds 0 to 2.
AFTER = 600
MOVES_M = 0.10


@pytest.mark.parametrize(("seed", "at"), [(0, "m4"), (1, "m0"), (2, "m7")])
def test_snake_becomes_t_in_physics_and_moves(seed: int, at: str) -> None:
    prog = compile_file(str(EXAMPLES / "snake_to_t.dh2"))
    topo = parse_spec("snake:8")
    robot = Robot(prog, topo, seed=seed)
    run = PhysicsRun(robot)
    try:
        run.run(50, [])
        run.run(1, [parse_event(f"50:inject:{at}:STT", topo, prog.vocabulary)])
        while not any("released" in line for line in robot.log) and robot.cycle < FORM_WITHIN:
            run.run(1, [])
        names, conn = topo.names, robot.profile.connector_name
        links = {(names[x.a], conn(x.a_conn), names[x.b], conn(x.b_conn)) for x in robot.links()}
        assert links == T_LINKS, robot.log[-6:]
        assert run.world.links() == set(robot.links())  # the latches are the logical links
        types = [e.topo_type.name for e in robot.engines if e is not None]
        assert types[3] == "head" and types[2] == "tail" and types[7] == "tail"
        # the one link made by motion, within tolerance when it latched, female to male
        (contact,) = run.contacts
        assert contact.asking == (0, robot.profile.connector_index("front"))
        assert contact.target == (5, robot.profile.connector_index("left"))
        assert math.isclose(contact.distance_m, math.dist(contact.asking_face, contact.target_face), abs_tol=1e-9)
        assert contact.distance_m <= DOCK_TOLERANCE_M and contact.attitude_deg <= DOCK_TOLERANCE_DEG
        assert 0 < contact.ir_mm <= DOCK_TOLERANCE_M * 1000 and contact.ir_align_deg <= DOCK_TOLERANCE_DEG
        assert not run.failed
        # the new robot moves
        start = run.world.centroid()
        run.run(AFTER, [])
        moved = math.dist(start[:2], run.world.centroid()[:2])
        assert moved >= MOVES_M, f"the T moved {moved * 100:.1f} cm in {AFTER} cycles"
        links = {(names[x.a], conn(x.a_conn), names[x.b], conn(x.b_conn)) for x in robot.links()}
        assert links == T_LINKS  # still a T
    finally:
        run.close()
