"""Table I on snakes of 1, 5, 8 and 20 modules: the head's quarters, one hop per cycle."""

from __future__ import annotations

import pytest

from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.topology import snake

# Table I: what a body/tail module sets on each hormone, and what it sends on.
TABLE_BODY = {"A": (-45.0, "B"), "B": (-45.0, "C"), "C": (45.0, "D"), "D": (45.0, "A")}
TABLE_HEAD = {0: (45.0, "A"), 10: (-45.0, "B"), 20: (-45.0, "C"), 30: (45.0, "D")}


def run_and_record(program: CompiledProgram, n: int, cycles: int, seed: int) -> Robot:
    robot = Robot(program, snake(n), seed=seed, record=True)
    robot.run(cycles)
    return robot


@pytest.mark.parametrize("n", [1, 5, 8, 20])
def test_head_quarters_and_one_hop_per_cycle(caterpillar: CompiledProgram, n: int) -> None:
    robot = Robot(caterpillar, snake(n), seed=n)
    head_timer0 = robot.engine(0).timer
    sent_at: dict[tuple[int, int], str] = {}  # (module, cycle) -> phase sent
    angles: dict[tuple[int, int], float] = {}
    for cycle in range(400):
        timer = robot.engine(0).timer
        robot.record = True
        robot.step()
        for rec in robot.records:
            for em in rec.sent:
                sent_at[(rec.module, cycle)] = str(em.hormone.args[0])
            angles[(rec.module, cycle)] = robot.engine(rec.module).dof[0]
        robot.records.clear()
        # the head: +45, -45, -45, +45 at the quarters of its own LocalTimer
        if timer in TABLE_HEAD:
            angle, phase = TABLE_HEAD[timer]
            assert angles[(0, cycle)] == angle
            assert sent_at[(0, cycle)] == phase
        else:
            assert (0, cycle) not in sent_at
    assert robot.engine(0).topo_type.name == "head" and robot.engine(0).topo_type.alias == 1
    assert head_timer0 == robot.engine(0).timer  # 400 cycles = 10 ClockCycles, no drift
    # module k acts exactly one cycle after module k-1, with Table I's angle for what it got
    for (m, cycle), phase in sent_at.items():
        if m + 1 < n and cycle + 1 < 400:
            angle, nxt = TABLE_BODY[phase]
            assert sent_at[(m + 1, cycle + 1)] == nxt
            assert angles[(m + 1, cycle + 1)] == angle
    if n > 1:
        assert robot.engine(n - 1).topo_type.name == "tail"
    for m in range(1, n - 1):
        assert robot.engine(m).topo_type.name == "body"


def test_wave_runs_thousands_of_cycles_without_drift_or_loss(caterpillar: CompiledProgram) -> None:
    n, cycles = 20, 6000
    robot = run_and_record(caterpillar, n, 0, seed=3)
    counts = [0] * n
    robot.run(cycles)
    for m in range(n):
        counts[m] = robot.engine(m).counters["sent"]
    # the head sends 4 per ClockCycle; every module downstream sends exactly what it received
    assert counts[0] == cycles // 40 * 4
    for m in range(1, n):
        e = robot.engine(m)
        assert e.counters["received"] == robot.engine(m - 1).counters["sent"] - (1 if _in_flight(robot, m) else 0)
        assert e.counters["faults"] == 0 and e.counters["dropped_hops"] == 0


def _in_flight(robot: Robot, m: int) -> bool:
    return bool(robot.inbox.get(m))


def test_lone_module_is_a_head_and_runs_its_receptors(caterpillar: CompiledProgram) -> None:
    robot = run_and_record(caterpillar, 1, 80, seed=0)
    e = robot.engine(0)
    assert e.topo_type.name == "head" and e.status == [0, 0, 0, 0]
    assert e.counters["sent"] == 8 and e.counters["send_failed"] == 8  # nothing at its back
    assert {a for rec in robot.records for em in rec.sent for a in em.hormone.args} == {"A", "B", "C", "D"}
