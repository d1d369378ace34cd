"""examples/snake_to_quadruped.dh2 in physics: what works, and where it stops.

QSS enters at cycle 50 at m4. The head (m0) bends its front, by the chain of m0..m6's joints
(a loop of eight closing on the robot itself, with the pitch wave), to m7's left side and
lets go of m1; m1 then bends to m8's left (the loop grows by one) and lets go of m2. Both
latches close only within the runner's tolerance, female front to male side, and each is in
the trace: the asking module's record of that cycle carries ``dock``.

The third motion, m2's front to m7's right, does not latch (wip/README.md): the five modules
m2..m6 lie curled on the quadruped's left side and m6's yaw has to swing them round m7's
front to its right; they stall 0.33 to 0.36 m from the target and the motion gives up after
400 cycles, seeds 0 to 2. This test checks that state too, so that a change that makes it
latch is seen (and the rest of wip/snake_to_quadruped_physics.patch can land).
"""

from __future__ import annotations

import io
import json
import math

import pytest

from dh2rt.compiler import compile_file
from dh2rt.events import parse_event
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from dh2rt.trace import TraceWriter
from sim.command import traced
from sim.runner import DOCK_TOLERANCE_DEG, DOCK_TOLERANCE_M, PhysicsRun
from tests.conftest import EXAMPLES

#: Cycles the two left legs may take (they took 555 to 586 cycles from QSS, seeds 0 to 2).
TWO_LEGS_WITHIN = 800
#: The links once the two left legs are on: m2..m8 a chain, m0 on m7's left, m1 on m8's left.
TWO_LEGS = {
    ("m0", "front", "m7", "left"),
    ("m1", "front", "m8", "left"),
    *{(f"m{i}", "back", f"m{i + 1}", "front") for i in range(2, 8)},
}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_left_legs_dock_by_motion_within_tolerance(seed: int) -> None:
    prog = compile_file(str(EXAMPLES / "snake_to_quadruped.dh2"))
    topo = parse_spec("snake:9")
    robot = Robot(prog, topo, seed=seed)
    robot.record = True
    run = PhysicsRun(robot)
    stream = io.StringIO()
    trace = TraceWriter(stream, robot, extra=lambda m: traced(run, m, list(run.world.module_position(m))))
    names, conn = topo.names, robot.profile.connector_name
    idx = robot.profile.connector_index
    try:
        run.run(50, [], lambda _c: trace.write_cycle())
        run.run(1, [parse_event("50:inject:m4:QSS", topo, prog.vocabulary)], lambda _c: trace.write_cycle())
        while sum("released" in line for line in robot.log) < 2 and robot.cycle < TWO_LEGS_WITHIN:
            run.run(1, [], lambda _c: trace.write_cycle())
        links = {(names[x.a], conn(x.a_conn), names[x.b], conn(x.b_conn)) for x in robot.links()}
        assert links == TWO_LEGS, robot.log[-6:]
        assert run.world.links() == set(robot.links())  # the latches are the logical links
        types = [e.topo_type.name for e in robot.engines if e is not None]
        assert types[0] == "left_foot" and types[1] == "left_foot" and types[2] == "head"
        # the two links made by motion, each within tolerance when it latched, female to male
        assert [(c.asking, c.target) for c in run.contacts] == [
            ((0, idx("front")), (7, idx("left"))),
            ((1, idx("front")), (8, idx("left"))),
        ]
        records = [json.loads(line) for line in stream.getvalue().splitlines()]
        docks = [r for r in records if "dock" in r]
        assert [(r["module"], r["cycle"]) for r in docks] == [(c.asking[0], c.cycle) for c in run.contacts]
        for contact, rec in zip(run.contacts, docks, strict=True):
            assert rec["dock"] == contact.as_dict()
            assert math.isclose(contact.distance_m, math.dist(contact.asking_face, contact.target_face), abs_tol=1e-9)
            assert contact.distance_m <= DOCK_TOLERANCE_M and contact.attitude_deg <= DOCK_TOLERANCE_DEG
            assert 0 < contact.ir_mm <= DOCK_TOLERANCE_M * 1000 and contact.ir_align_deg <= DOCK_TOLERANCE_DEG
        assert not run.failed
        # the third motion starts (m2 asked for m7's right) and, today, gives up: nothing links
        while not run.failed and robot.cycle < TWO_LEGS_WITHIN + 500:
            run.run(1, [])
        assert any("reach_dock m2.front -> m7.right: bending" in line for line in robot.log)
        (gave_up,) = run.failed
        assert gave_up.asking == (2, idx("front")) and gave_up.target == (7, idx("right"))
        assert gave_up.distance_m > DOCK_TOLERANCE_M
        links = {(names[x.a], conn(x.a_conn), names[x.b], conn(x.b_conn)) for x in robot.links()}
        assert links == TWO_LEGS and len(run.contacts) == 2
    finally:
        run.close()
