"""The paper's caterpillar schedule (Table I) makes simulated snakes of 5, 8 and 20 crawl forward."""

from __future__ import annotations

import pytest

from dh2rt.errors import GaitError
from dh2rt.topology import parse_spec
from firmware.motion.gaits import caterpillar_schedule, delay_wave_schedule
from sim.gaits import CLOCK_CYCLE, STEPS_PER_CYCLE, run_caterpillar
from sim.world import World


def test_head_follows_table_one() -> None:
    cc = 16
    head = [caterpillar_schedule(1, c, cc)[0] for c in range(2 * cc)]
    # +45 at LocalTimer 0, -45 at CC/4, -45 at CC/2, +45 at 3CC/4, holding in between.
    assert head[:cc] == [45.0] * 4 + [-45.0] * 8 + [45.0] * 4
    assert head[cc:] == head[:cc]


def test_body_takes_the_angle_of_the_next_hormone_one_cycle_later() -> None:
    cc = 16
    rows = [caterpillar_schedule(4, c, cc) for c in range(cc + 4)]
    # Before the first hormone arrives a module holds 0.
    assert [rows[0][k] for k in range(4)] == [45.0, 0.0, 0.0, 0.0]
    # Module 1 receives A at cycle 1 and sets -45 (Table I: (X,A) -> -45, emits B).
    assert rows[1][1] == -45.0
    # Module 2 receives B at cycle 2 -> -45; module 3 receives C at cycle 3 -> +45.
    assert rows[2][2] == -45.0
    assert rows[3][3] == 45.0
    # Module k at cycle c + k takes the head's angle one quarter period ahead of cycle c.
    q = cc // 4
    for c in range(cc):
        for k in range(1, 4):
            assert rows[c + k][k] == caterpillar_schedule(1, c + k * q, cc)[0]


def test_delay_wave_copies_the_front_neighbour() -> None:
    for c in range(1, 40):
        now, before = delay_wave_schedule(5, c, 16), delay_wave_schedule(5, c - 1, 16)
        assert now[1:] == before[:-1]


@pytest.mark.parametrize(("n", "cycle", "cc"), [(0, 0, 16), (3, -1, 16), (3, 0, 10), (3, 0, 0)])
def test_schedule_rejects_bad_parameters(n: int, cycle: int, cc: int) -> None:
    with pytest.raises(GaitError):
        caterpillar_schedule(n, cycle, cc)


# Two gait periods after one period to settle into the gait.
SETTLE_CYCLES = CLOCK_CYCLE
MEASURE_PERIODS = 2


def _travel_per_period(n: int, seed: int) -> tuple[float, float]:
    with World(parse_spec(f"snake:{n}"), seed=seed) as w:
        run_caterpillar(w, SETTLE_CYCLES)
        start = w.centroid()
        run_caterpillar(w, MEASURE_PERIODS * CLOCK_CYCLE, first_cycle=SETTLE_CYCLES)
        end = w.centroid()
        forward = w.travel(start, end) / MEASURE_PERIODS
        fx, fy, _ = w.forward
        sideways = abs(-(end[0] - start[0]) * fy + (end[1] - start[1]) * fx) / MEASURE_PERIODS
        return forward, sideways


@pytest.mark.parametrize("n", [5, 8, 20])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_snakes_crawl_forward(n: int, seed: int) -> None:
    forward, sideways = _travel_per_period(n, seed)
    # Clear margin: at least 2.5 cm per gait period (the model moves 4-10 cm), in the
    # direction the head's free front connector faced, whatever the initial heading.
    assert forward > 0.025, f"snake:{n} seed {seed}: {forward:.4f} m per period"
    assert sideways < forward / 2


def test_constants_are_a_sane_gait() -> None:
    # A quarter period must leave the servo time to swing 90 degrees (400 deg/s).
    quarter_s = CLOCK_CYCLE / 4 * STEPS_PER_CYCLE / 240.0
    assert quarter_s >= 90.0 / 400.0
