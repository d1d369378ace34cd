"""Following a route (path-1) through the links, as reach_and_dock does."""

from __future__ import annotations

from dh2rt.docking import body_up, off_path, reach_target, route_end
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


def test_a_foot_on_its_way_steers_round_every_module_off_its_path(caterpillar: CompiledProgram) -> None:
    """off_path: the legs still on the dragon and a foot lying apart (released, dead) beside
    it, never the tail's spine the foot follows up the robot, nor the foot itself."""
    dragon = parse_spec("dragon")
    robot = Robot(caterpillar, dragon)
    index = dragon.names.index
    tail, foot, lying = index("tail4"), index("left_leg1"), index("left_leg0")
    spine = body_up(robot.peer.get, robot.profile, tail)
    assert [dragon.names[m] for m in spine] == ["tail4", "tail3", "tail2", "tail1", "tail0", "spine1", "spine0"]
    robot.cut(lying, robot.profile.connector_index("front"))
    robot.kill(lying)
    others = off_path(robot.peer.get, robot.profile, tail, dragon.size, foot)
    assert [dragon.names[m] for m in others] == ["left_leg0", "right_leg0", "right_leg1"]
