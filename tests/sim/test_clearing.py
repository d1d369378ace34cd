"""sim.clearing: the robot crawls whole gait cycles of the caterpillar's wave, lies straight,
and looks again, until nothing lies on the spot (or its budget runs out). The crawl in
physics is tested in test_legs_to_snake_physics.py (a foot killed as it docks)."""

from __future__ import annotations

import pytest

from sim.clearing import SETTLE_CYCLES, Clearing
from sim.gaits import caterpillar_schedule

BODY = [4, 7, 2]  # head first: module ids, not positions


def run_until_done(clearing: Clearing, limit: int = 10_000) -> list[dict[int, float]]:
    steps: list[dict[int, float]] = []
    while not clearing.done and len(steps) < limit:
        steps.append(clearing.step())
    return steps


@pytest.mark.parametrize("clear_after", [1, 2, 3])
def test_it_crawls_gait_cycles_until_the_spot_is_clear_and_looks_only_while_lying_straight(clear_after: int) -> None:
    looks: list[int] = []

    def taken() -> bool:
        looks.append(len(steps))
        return len(looks) < clear_after

    clearing = Clearing(BODY, taken, clock_cycle=8)
    steps: list[dict[int, float]] = []
    while not clearing.done:
        steps.append(clearing.step())
    per_gait = 8 + SETTLE_CYCLES
    assert clearing.cleared and clearing.gait_cycles == clear_after
    assert len(steps) == clear_after * per_gait + 1  # the last step hands the joints back: {}
    assert steps[-1] == {}
    wave = 0
    for k in range(clear_after):
        crawl = steps[k * per_gait : k * per_gait + 8]
        settle = steps[k * per_gait + 8 : (k + 1) * per_gait]
        for got in crawl:  # Table I over the body, head first, continuing from gait to gait
            assert got == dict(zip(BODY, caterpillar_schedule(len(BODY), wave, 8), strict=True))
            wave += 1
        assert all(got == dict.fromkeys(BODY, 0.0) for got in settle)
    # it looked once after each gait cycle's settling, never during the wave
    assert looks == [(k + 1) * per_gait for k in range(clear_after)]


def test_a_spot_that_stays_taken_ends_the_crawl_at_its_budget() -> None:
    clearing = Clearing(BODY, lambda: True, clock_cycle=8, max_gait_cycles=3)
    steps = run_until_done(clearing)
    assert clearing.done and not clearing.cleared and clearing.gait_cycles == 3
    assert len(steps) == 3 * (8 + SETTLE_CYCLES) + 1
    assert clearing.step() == {}


def test_an_empty_body_is_refused() -> None:
    with pytest.raises(ValueError, match="at least one module"):
        Clearing([], lambda: True)
