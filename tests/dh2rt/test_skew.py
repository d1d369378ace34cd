"""Time-skewed windows (Robot.advance) give exactly the lockstep run, on any topology."""

from __future__ import annotations

import random

import pytest

from dh2rt.events import parse_event
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.skew import breadth_first_order, make_plan
from dh2rt.testing import robot_snapshot
from dh2rt.topology import Link, Topology, parse_spec

SHAPES = ("snake:1", "snake:7", "snake:61", "ring:6", "ring:40", "t-shape", "hexapod", "octopod", "dragon")


def shuffled(topo: Topology, seed: int) -> Topology:
    """The same robot with its modules numbered at random (no locality in the numbering)."""
    perm = list(range(topo.size))
    random.Random(seed).shuffle(perm)
    names = [""] * topo.size
    for old, new in enumerate(perm):
        names[new] = topo.names[old]
    links = tuple(Link(perm[k.a], k.a_conn, perm[k.b], k.b_conn) for k in topo.links)
    return Topology(topo.profile, tuple(names), links, f"{topo.spec}, renumbered")


def state(robot: Robot) -> tuple[object, ...]:
    mail = sorted((m, [(a.at, a.remote, a.hormone) for a in box]) for m, box in robot.inbox.items())
    return robot.cycle, robot_snapshot(robot), mail


def replay(neighbours: list[list[int]], block: int, depth: int) -> int:
    """Run a plan's sweeps on cycle counters, checking every step; returns the planned depth."""
    plan = make_plan(neighbours, block=block, depth=depth)
    assert sorted(breadth_first_order(neighbours)) == list(range(len(neighbours)))
    done = [0] * len(neighbours)  # cycles each module has done
    for i, members in (r for sweep in plan.sweeps for r in sweep.rounds(plan.depth)):
        for m in members:
            assert done[m] == i, "each module does its cycles in order, once each"
            assert all(i <= done[k] <= i + 1 for k in neighbours[m]), "mail complete, none pending"
            done[m] += 1
    assert done == [plan.depth] * len(neighbours)
    return plan.depth


@pytest.mark.parametrize("spec", SHAPES)
@pytest.mark.parametrize("block,depth", [(1, 2), (3, 4), (8, 5), (256, 16)])
def test_plan_steps_every_module_once_per_cycle_after_its_neighbours(spec: str, block: int, depth: int) -> None:
    for topo in (parse_spec(spec), shuffled(parse_spec(spec), 7)):
        neighbours = [[] for _ in range(topo.size)]  # type: list[list[int]]
        for k in topo.links:
            neighbours[k.a].append(k.b)
            neighbours[k.b].append(k.a)
        assert 1 <= replay(neighbours, block, depth) <= depth


def test_plan_is_shallower_where_blocks_are_round() -> None:
    """A 40x40 lattice: blocks of 128 are about 12 links across, too round for 64-cycle
    windows (the band would join into one piece: plain lockstep); a snake is not."""
    side = 40
    lattice = [
        [k for k in (m - side, m + side) if 0 <= k < side * side]
        + [k for k in (m - 1, m + 1) if 0 <= k < side * side and k // side == m // side]
        for m in range(side * side)
    ]
    assert 2 <= replay(lattice, 128, 64) <= 16
    chain = [[k for k in (m - 1, m + 1) if 0 <= k < 2000] for m in range(2000)]
    assert replay(chain, 128, 64) == 64


@pytest.mark.parametrize("spec", SHAPES)
def test_advance_equals_stepping(spec: str, caterpillar: CompiledProgram, locomotion: CompiledProgram) -> None:
    for program in (caterpillar, locomotion):
        for topo in (parse_spec(spec), shuffled(parse_spec(spec), 3)):
            for block, depth in ((2, 3), (5, 7), (256, 16)):
                stepped = Robot(program, topo, seed=11)
                skewed = Robot(program, topo, seed=11)
                skewed.skew_block, skewed.skew_depth = block, depth
                for chunk in (1, 37, 100, 2, 64):
                    for _ in range(chunk):
                        stepped.step()
                    skewed.advance(chunk)
                    assert state(skewed) == state(stepped), (program.name, topo.spec, block, depth)


def test_advance_after_surgery_docking_deaths(locomotion: CompiledProgram) -> None:
    """Links and deaths change between windows: the plan follows the links."""
    topo = parse_spec("octopod")
    events = ["40:cut:spine1.back", "90:kill:spine0", "130:dock:spine1.back-spine2.front", "170:restart:spine0"]
    evs = [parse_event(e, topo, locomotion.vocabulary) for e in events]
    stepped = Robot(locomotion, topo, seed=2)
    skewed = Robot(locomotion, topo, seed=2)
    skewed.skew_block, skewed.skew_depth = 4, 6
    yielded = [-1]
    for robot, every in ((stepped, True), (skewed, False)):
        for cycle in robot.iter_cycles(250, evs, every_cycle=every):
            if not every:
                start = yielded[-1] + 1  # the window ran cycles start .. cycle
                assert not any(start < c <= cycle for c in (40, 90, 130, 170)), "a window crossed an event"
                yielded.append(cycle)
    assert state(skewed) == state(stepped)
    assert skewed.log == stepped.log
    assert yielded[-1] == 249 and len(yielded) < 100  # windows, not single cycles


def test_advance_falls_back_to_steps_when_the_world_may_change(legs_to_snake: CompiledProgram) -> None:
    """Native actions act on the world at one cycle: such programs step cycle by cycle."""
    topo = parse_spec("dragon")
    inject = parse_event("3:inject:tail1:LTS", topo, legs_to_snake.vocabulary)
    stepped, skewed = Robot(legs_to_snake, topo, seed=8), Robot(legs_to_snake, topo, seed=8)
    skewed.skew_block = 4
    for robot in (stepped, skewed):
        robot.advance(3)
        robot.apply(inject)
    for _ in range(300):
        stepped.step()
    skewed.advance(300)
    assert skewed.skew_plan is None  # never planned: every cycle was a plain step
    assert state(skewed) == state(stepped) and skewed.log == stepped.log
    assert any("docked" in line for line in skewed.log)


def test_advance_keeps_scheduled_actions_on_their_cycle(caterpillar: CompiledProgram) -> None:
    topo = parse_spec("snake:30")
    stepped, skewed = Robot(caterpillar, topo, seed=4), Robot(caterpillar, topo, seed=4)
    skewed.skew_block = 8
    for robot in (stepped, skewed):
        robot.schedule(23, lambda r=robot: r.cut(10, 1))  # type: ignore[misc]
    for _ in range(80):
        stepped.step()
    skewed.advance(80)
    assert state(skewed) == state(stepped)
    assert skewed.skew_plan is not None  # windows before and after the cut


def test_recording_robot_steps_every_cycle(caterpillar: CompiledProgram) -> None:
    robot = Robot(caterpillar, parse_spec("snake:5"), seed=1, record=True)
    robot.skew_block = 2
    robot.advance(20)
    assert sorted({r.cycle for r in robot.records}) == list(range(20))
    assert robot.skew_plan is None


def test_plan_rejects_nonsense() -> None:
    with pytest.raises(ValueError, match="at least 1"):
        make_plan([[]], block=0)
