"""Live surgery (Sec. 7.1): pieces re-type themselves and keep moving, no ids involved."""

from __future__ import annotations

from dh2rt.profile import CONRO
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec, snake

BACK = CONRO.connector_index("back")
#: examples/locomotion.dh2's Slots: a leg hormone per slot, eight per ClockCycle.
SLOTS = 8


def types(robot: Robot) -> list[str]:
    return [robot.engine(m).topo_type.name for m in range(robot.size)]


def expected_types(robot: Robot) -> list[str]:
    """The type each module should have given the links docked now (fresh, no history)."""
    out = []
    for m in range(robot.size):
        status = [0] * CONRO.connector_count
        for c in range(1, CONRO.connector_count + 1):
            other = robot.peer.get((m, c))
            if other is not None:
                status[c - 1] = other[1]
        out.append(CONRO.type_of(status).name)
    return out


def waves_started(robot: Robot, heads: list[int], cycles: int) -> dict[int, int]:
    """Run; for each head, count X hormones its back neighbour receives."""
    got = dict.fromkeys(heads, 0)
    robot.record = True
    for _ in robot.iter_cycles(cycles):
        for rec in robot.records:
            linked = robot.peer.get((rec.module - 1, BACK)) == (rec.module, CONRO.connector_index("front"))
            if rec.module - 1 in got and rec.received and linked:
                got[rec.module - 1] += len(rec.received)
        robot.records.clear()
    return got


def test_snake8_cut_into_2_then_4_then_8(caterpillar: CompiledProgram) -> None:
    robot = Robot(caterpillar, snake(8), seed=11)
    robot.run(100)
    assert types(robot) == ["head"] + ["body"] * 6 + ["tail"]
    for cuts, pieces in (([3], 2), ([1, 5], 4), ([0, 2, 4, 6], 8)):
        for m in cuts:
            robot.cut(m, BACK)
        heads = [m + 1 for m in cuts]
        robot.run(2)
        # within 2 cycles every piece's front module is head, and no type is stale
        assert types(robot) == expected_types(robot)
        assert sum(t == "head" for t in types(robot)) == pieces
        for h in heads:
            assert robot.engine(h).topo_type.name == "head"
        # every new head starts its own wave within one ClockCycle (unless it is alone)
        got = waves_started(robot, [h for h in heads if h < 7 and (h, BACK) in robot.peer], 2 * caterpillar.clock_cycle)
        assert all(count >= 4 for count in got.values()), got
    assert types(robot) == ["head"] * 8


def test_octopod_cut_into_two_quadrupeds_that_keep_walking(locomotion: CompiledProgram) -> None:
    topo = parse_spec("octopod")
    robot = Robot(locomotion, topo, seed=5)
    robot.run(60)
    spine1 = topo.module_index("spine1")
    robot.cut(spine1, BACK)
    robot.run(2)
    assert types(robot) == expected_types(robot)
    assert robot.engine(topo.module_index("spine2")).topo_type.name == "spine_front"
    assert robot.engine(spine1).topo_type.name == "spine_rear"
    # the new front spine stands its half up, then starts the rhythm at its next LocalTimer 0
    robot.run(locomotion.clock_cycle)
    # both halves: every leg keeps receiving its rhythm and moving, one leg hormone per slot
    legs = [i for i, n in enumerate(topo.names) if "leg" in n]
    robot.record = True
    received = dict.fromkeys(legs, 0)
    moves: dict[int, set[tuple[float, ...]]] = {m: set() for m in legs}
    cycles = 5 * locomotion.clock_cycle
    for _ in robot.iter_cycles(cycles):
        for rec in robot.records:
            if rec.module in received:
                received[rec.module] += len(rec.received)
                moves[rec.module].add(tuple(robot.engine(rec.module).dof))
        robot.records.clear()
    for m in legs:
        assert abs(received[m] - cycles // locomotion.clock_cycle * SLOTS) <= 1, (topo.names[m], received[m])
        assert len(moves[m]) >= 4, topo.names[m]
    # a spine module's two legs move as mirror images (same pitch, opposite yaw), in both halves
    for i in range(4):
        ea, eb = robot.engine(topo.module_index(f"left_leg{i}")), robot.engine(topo.module_index(f"right_leg{i}"))
        assert ea.dof[0] == eb.dof[0] and ea.dof[1] == -eb.dof[1], (i, ea.dof, eb.dof)
