"""Live surgery at every moment: a cut or a kill at every cycle of two ClockCycles, three
seeds, on several robots. Every piece re-types itself within 2 cycles (no module keeps a
stale type; a snake piece has exactly one head) and keeps moving.

A test at one timing proves little: mail in flight across the cut link used to reach its
receiver after the cut and revive the dead link, freezing the rear piece at 4 cut timings
in 40 (cycles 199, 209, 219, 229 with seed 3 on snake:8).
"""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from dh2rt.events import Event, parse_event
from dh2rt.profile import CONRO
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec

SEEDS = (0, 1, 3)
SNAKE_TYPES = ("head", "body", "tail")


@dataclass(frozen=True)
class Surgery:
    program: str  # fixture name
    topology: str
    events: tuple[str, ...]  # without their cycle: "cut:m3.back", "kill:m3"

    def __str__(self) -> str:
        return f"{self.topology}:{'+'.join(self.events)}"


SURGERIES = [
    Surgery("caterpillar", "snake:8", ("cut:m3.back",)),
    Surgery("caterpillar", "snake:8", ("kill:m3",)),
    Surgery("caterpillar", "snake:13", ("cut:m2.back",)),
    Surgery("caterpillar", "snake:13", ("cut:m7.back",)),
    Surgery("caterpillar", "snake:13", ("cut:m11.back",)),
    Surgery("caterpillar", "snake:13", ("cut:m2.back", "cut:m7.back", "cut:m11.back")),
    Surgery("caterpillar", "snake:13", ("kill:m7",)),
    Surgery("locomotion", "octopod", ("cut:spine1.back",)),
    Surgery("locomotion", "octopod", ("kill:spine1",)),
    Surgery("locomotion", "dragon", ("cut:spine1.back",)),
    Surgery("locomotion", "dragon", ("cut:tail1.back",)),
]


def expected_types(robot: Robot) -> list[str | None]:
    """The type each running module must have given the links docked now (no history)."""
    out: list[str | None] = []
    for m in range(robot.size):
        if not robot.alive(m):
            out.append(None)
            continue
        status = [0] * CONRO.connector_count
        for c in range(1, CONRO.connector_count + 1):
            other = robot.peer.get((m, c))
            if other is not None and robot.alive(other[0]):
                status[c - 1] = other[1]
        out.append(CONRO.type_of(status).name)
    return out


def pieces(robot: Robot) -> list[list[int]]:
    """The running modules grouped by the links between them."""
    seen: set[int] = set()
    out: list[list[int]] = []
    for start in range(robot.size):
        if start in seen or not robot.alive(start):
            continue
        piece, todo = [], [start]
        seen.add(start)
        while todo:
            m = todo.pop()
            piece.append(m)
            for c in range(1, CONRO.connector_count + 1):
                other = robot.peer.get((m, c))
                if other is not None and robot.alive(other[0]) and other[0] not in seen:
                    seen.add(other[0])
                    todo.append(other[0])
        out.append(sorted(piece))
    return out


def movers(robot: Robot, piece: list[int]) -> list[int]:
    """The modules of a piece whose joints the program moves: every module of a snake, the
    legs of a legged robot (a legged robot's tail only passes its rhythm on, as in the paper)."""
    legs = [m for m in piece if "leg" in robot.topology.names[m]]
    if legs:
        return legs
    return [m for m in piece if robot.engine(m).topo_type.name in SNAKE_TYPES]


def check_surgery(robot: Robot, events: list[Event], label: str) -> None:
    """Apply ``events`` (all at the robot's cycle) and check re-typing and motion."""
    cc = robot.program.clock_cycle
    robot.run(2, events)
    types = [robot.engine(m).topo_type.name if robot.alive(m) else None for m in range(robot.size)]
    assert types == expected_types(robot), f"{label}: stale type 2 cycles after the surgery"
    split = pieces(robot)
    for piece in split:
        kinds = [types[m] for m in piece]
        if all(k in SNAKE_TYPES for k in kinds):
            assert kinds.count("head") == 1, f"{label}: piece {piece} has heads {kinds}"
    # every piece keeps moving: each of its moving modules takes several poses in 2 ClockCycles
    poses: dict[int, set[tuple[float, ...]]] = {m: set() for piece in split for m in movers(robot, piece)}
    for _ in robot.iter_cycles(2 * cc, every_cycle=True):
        for m, seen in poses.items():
            seen.add(tuple(robot.engine(m).dof))
    frozen = [robot.topology.names[m] for m, seen in poses.items() if len(seen) < 2]
    assert not frozen, f"{label}: frozen after the surgery: {frozen}"
    assert types == [robot.engine(m).topo_type.name if robot.alive(m) else None for m in range(robot.size)]


@pytest.mark.parametrize("surgery", SURGERIES, ids=str)
def test_surgery_at_every_cycle_of_two_clock_cycles(surgery: Surgery, request: pytest.FixtureRequest) -> None:
    program: CompiledProgram = request.getfixturevalue(surgery.program)
    topo = parse_spec(surgery.topology)
    cc = program.clock_cycle
    warm = 3 * cc
    for seed in SEEDS:
        for cycle in range(warm, warm + 2 * cc):
            robot = Robot(program, topo, seed=seed)
            robot.run(cycle)
            events = [parse_event(f"{cycle}:{e}", topo, program.vocabulary) for e in surgery.events]
            check_surgery(robot, events, f"{surgery} at cycle {cycle}, seed {seed}")


def test_in_flight_mail_is_counted_lost(caterpillar: CompiledProgram) -> None:
    """The cut that used to freeze the rear piece: the hormone on its way across the cut link
    is lost in flight, not delivered."""
    topo = parse_spec("snake:8")
    robot = Robot(caterpillar, topo, seed=3)
    robot.run(199)
    m4 = topo.module_index("m4")
    assert any(a.at == CONRO.connector_index("front") for a in robot.inbox.get(m4, []))
    robot.run(1, [parse_event("199:cut:m3.back", topo, caterpillar.vocabulary)])
    assert robot.lost_in_flight == 1
    assert robot.engine(m4).topo_type.name == "head"
