"""examples/snake_to_t.dh2 on the in-process robot: an 8-module snake becomes a T (a bar of
five, a stem of three on the middle module's left), STT entering at the head, the tail or a
body module."""

from __future__ import annotations

import pytest

from dh2rt.compiler import compile_file
from dh2rt.events import parse_event
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from tests.conftest import EXAMPLES

T_LINKS = {
    ("m0", "back", "m1", "front"),
    ("m0", "front", "m5", "left"),
    ("m1", "back", "m2", "front"),
    ("m3", "back", "m4", "front"),
    ("m4", "back", "m5", "front"),
    ("m5", "back", "m6", "front"),
    ("m6", "back", "m7", "front"),
}


@pytest.mark.parametrize(
    ("seed", "at", "cycle"),
    [(0, "m4", 50), (1, "m4", 50), (2, "m4", 50), (0, "m0", 50), (1, "m7", 50), (2, "m1", 30), (0, "m6", 70)],
)
def test_snake_becomes_t(seed: int, at: str, cycle: int) -> None:
    prog = compile_file(str(EXAMPLES / "snake_to_t.dh2"))
    topo = parse_spec("snake:8")
    robot = Robot(prog, topo, seed=seed)
    robot.run(cycle + 200, [parse_event(f"{cycle}:inject:{at}:STT", topo, prog.vocabulary)])
    names, conn = topo.names, robot.profile.connector_name
    links = {(names[x.a], conn(x.a_conn), names[x.b], conn(x.b_conn)) for x in robot.links()}
    assert links == T_LINKS, robot.log
    assert sum("docked to" in line for line in robot.log) == 1 and sum("released" in line for line in robot.log) == 1
    types = [e.topo_type.name for e in robot.engines if e is not None]
    assert types[3] == "head" and types[2] == "tail" and types[7] == "tail"
