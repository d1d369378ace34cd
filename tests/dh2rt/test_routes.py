"""Following a route (path-1) through the links, as reach_and_dock does."""

from __future__ import annotations

from dh2rt.docking import reach_target, route_end
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec


def test_route_end_follows_links_hop_by_hop(caterpillar: CompiledProgram) -> None:
    robot = Robot(caterpillar, parse_spec("snake:4"))
    front, back, left = (robot.profile.connector_index(c) for c in ("front", "back", "left"))
    assert route_end(robot.peer.get, 0, (back, back, back)) == (3, front)
    assert route_end(robot.peer.get, 3, (front, front)) == (1, back)
    assert route_end(robot.peer.get, 2, ()) == (2, 0)
    assert route_end(robot.peer.get, 0, (back, left)) is None


def test_reach_target_refuses_broken_routes_and_routes_back(caterpillar: CompiledProgram) -> None:
    robot = Robot(caterpillar, parse_spec("snake:4"))
    front, back, left = (robot.profile.connector_index(c) for c in ("front", "back", "left"))
    assert reach_target(robot, 0, front, (back, back)) == (2, front)
    assert reach_target(robot, 0, front, (back, left)) is None
    assert robot.log[-1].endswith("reach_and_dock from m0.front: route broken")
    assert reach_target(robot, 0, front, (back, front)) is None  # leads back to m0
    assert reach_target(robot, 1, front, (back,)) is None  # m1.front is docked
    assert robot.log[-1].endswith("reach_and_dock: m1.front is not free")
