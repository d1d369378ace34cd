"""examples/snake_to_quadruped.dh2 on the in-process robot: a 9-module snake peels its four
front modules off into legs on its two rear modules (m0 on m7's left, m1 on m8's left, m2 on
m7's right, m3 on m8's right; between the sides the body crawls for 800 cycles), then m6 lets
go of m7: a quadruped (spine m7, m8) and a 3-module snake (m4, m5, m6), each then moving by
its own gait. QSS enters at the head, the tail or a body module."""

from __future__ import annotations

import pytest

from dh2rt.compiler import compile_file
from dh2rt.events import parse_event
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from tests.conftest import EXAMPLES

#: The two robots' links: the quadruped (m7 its front spine module) and the snake m4-m5-m6.
QUAD_LINKS = {
    ("m0", "front", "m7", "left"),
    ("m1", "front", "m8", "left"),
    ("m2", "front", "m7", "right"),
    ("m3", "front", "m8", "right"),
    ("m7", "back", "m8", "front"),
    ("m4", "back", "m5", "front"),
    ("m5", "back", "m6", "front"),
}
#: Each module's type once split.
QUAD_TYPES = [
    "left_foot",
    "left_foot",
    "right_foot",
    "right_foot",
    "head",
    "body",
    "tail",
    "spine_front",
    "spine_rear",
]


def link_set(robot: Robot) -> set[tuple[str, str, str, str]]:
    names, conn = robot.topology.names, robot.profile.connector_name
    return {(names[x.a], conn(x.a_conn), names[x.b], conn(x.b_conn)) for x in robot.links()}


@pytest.mark.parametrize(
    ("seed", "at", "cycle"),
    [(0, "m4", 50), (1, "m4", 50), (2, "m4", 50), (0, "m0", 50), (1, "m8", 50), (2, "m1", 30), (0, "m7", 70)],
)
def test_snake_becomes_quadruped_and_snake(seed: int, at: str, cycle: int) -> None:
    prog = compile_file(str(EXAMPLES / "snake_to_quadruped.dh2"))
    topo = parse_spec("snake:9")
    robot = Robot(prog, topo, seed=seed)
    # the split, then the snake lies still for Still (240) cycles before it backs away
    robot.run(cycle + 1300, [parse_event(f"{cycle}:inject:{at}:QSS", topo, prog.vocabulary)])
    assert link_set(robot) == QUAD_LINKS, robot.log
    docks = [line for line in robot.log if "docked to" in line]
    assert [d.split(": ", 1)[1] for d in docks] == [
        "m0.front docked to m7.left",
        "m1.front docked to m8.left",
        "m2.front docked to m7.right",
        "m3.front docked to m8.right",
    ]
    assert sum("released" in line for line in robot.log) == 5
    # between the sides, the body crawls straight, then curled, then lies still (Crawl cycles)
    second, third = (int(d.split(":")[0].split()[1]) for d in docks[1:3])
    assert third - second >= 800
    assert [e.topo_type.name for e in robot.engines if e is not None] == QUAD_TYPES

    # afterwards both robots move by their own gaits: the snake's head (m4) and body wave
    # their pitch, the quadruped's feet lift and swing
    seen: list[list[tuple[float, float]]] = [[] for _ in range(9)]
    for _ in robot.iter_cycles(80):
        for m, e in enumerate(robot.engines):
            assert e is not None
            seen[m].append((e.dof[0], e.dof[1]))
    for m in (4, 5, 6):  # the caterpillar: DOF1 between +45 and -45
        assert {d1 for d1, _ in seen[m]} == {45, -45}, (m, seen[m][:10])
    for m in (0, 1, 2, 3):  # locomotion.dh2's legs: each lifts and plants, swings back and forth
        assert len({d1 for d1, _ in seen[m]}) >= 2 and len({d2 for _, d2 in seen[m]}) >= 2, (m, seen[m][:10])
    assert link_set(robot) == QUAD_LINKS


def test_nothing_happens_without_qss() -> None:
    prog = compile_file(str(EXAMPLES / "snake_to_quadruped.dh2"))
    topo = parse_spec("snake:9")
    robot = Robot(prog, topo, seed=0)
    robot.run(400)
    assert link_set(robot) == {(f"m{i}", "back", f"m{i + 1}", "front") for i in range(8)}
    assert not any("docked" in line or "released" in line for line in robot.log)
