"""The floor filter (firmware.motion.floor_filter) on plain numbers: a still part's noise is
cut, a moving part is followed without lag, a dropped report coasts then holds, a late report
is carried forward, headings wrap, and bad gains are refused."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firmware.motion.floor_filter import MAX_COAST, FloorFilter, benedict_bordner
from firmware.motion.readings import FloorPoses, ModulePose, PartPose


def module(x: float, y: float, heading: float, age: int = 0) -> ModulePose:
    part = PartPose(x, y, heading)
    return ModulePose(part, PartPose(x + 0.05, y, heading), PartPose(x - 0.05, y, heading), age)


def centre(poses: FloorPoses, m: int = 0) -> tuple[float, float, float]:
    c = poses.modules[m].centre
    return c.x, c.y, c.heading


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_still_part_s_noise_is_about_halved(seed: int) -> None:
    rng = np.random.default_rng(seed)
    f = FloorFilter(0.3)
    raw, smooth = [], []
    for cycle in range(600):
        noise = rng.normal(0.0, 0.005, 2)
        out = f.update(cycle, FloorPoses({0: module(1.0 + noise[0], 2.0 + noise[1], 0.5)}))
        if cycle >= 50:  # past the filter's start
            raw.append(noise[0])
            smooth.append(centre(out)[0] - 1.0)
    ratio = float(np.std(smooth) / np.std(raw))
    # theory for alpha 0.3 with Benedict-Bordner's beta: sqrt(0.237) = 0.49
    assert 0.35 < ratio < 0.62, ratio


@pytest.mark.parametrize("speed", [0.0005, 0.002, -0.004])
def test_a_part_moving_steadily_is_followed_without_lag(speed: float) -> None:
    f = FloorFilter(0.3)
    for cycle in range(200):
        out = f.update(cycle, FloorPoses({0: module(speed * cycle, 0.0, 0.0)}))
    assert abs(centre(out)[0] - speed * 199) < 1e-6


def test_a_dropped_report_coasts_then_holds() -> None:
    f = FloorFilter(0.5)
    speed = 0.001
    for cycle in range(100):
        f.update(cycle, FloorPoses({0: module(speed * cycle, 0.0, 0.0)}))
    last = module(speed * 99, 0.0, 0.0)
    xs = []
    for ahead in range(1, 12):  # the tracker repeats its last pose, aging it
        aged = ModulePose(last.centre, last.front, last.back, ahead)
        xs.append(centre(f.update(99 + ahead, FloorPoses({0: aged})))[0])
    expected = [speed * (99 + min(a, MAX_COAST)) for a in range(1, 12)]
    assert xs == pytest.approx(expected, abs=1e-6)


@pytest.mark.parametrize("latency", [1, 3, 5])
def test_a_late_report_is_carried_forward_to_now(latency: int) -> None:
    speed = 0.002
    ahead = FloorFilter(0.3, predict=True)
    behind = FloorFilter(0.3, predict=False)
    for cycle in range(latency, 200):
        report = FloorPoses({0: module(speed * (cycle - latency), 0.0, 0.0, latency)})
        now, then = ahead.update(cycle, report), behind.update(cycle, report)
    assert centre(now)[0] == pytest.approx(speed * 199, abs=1e-6)
    assert centre(then)[0] == pytest.approx(speed * (199 - latency), abs=1e-6)


def test_headings_wrap_across_pi() -> None:
    f = FloorFilter(0.3)
    step = math.radians(1.0)
    for cycle in range(400):  # turning steadily through +-pi more than once
        heading = (math.pi - 0.2 + step * cycle + math.pi) % (2 * math.pi) - math.pi
        out = f.update(cycle, FloorPoses({0: module(0.0, 0.0, heading)}))
        error = (centre(out)[2] - heading + math.pi) % (2 * math.pi) - math.pi
        assert -math.pi <= centre(out)[2] <= math.pi
    assert abs(error) < 1e-6


def test_a_module_unheard_of_for_long_starts_afresh() -> None:
    f = FloorFilter(0.3)
    for cycle in range(50):
        f.update(cycle, FloorPoses({0: module(0.001 * cycle, 0.0, 0.0)}))
    out = f.update(500, FloorPoses({0: module(3.0, 1.0, 0.2)}))  # carried away meanwhile
    assert centre(out) == pytest.approx((3.0, 1.0, 0.2))


def test_each_module_has_its_own_track() -> None:
    f = FloorFilter(0.3)
    out = f.update(0, FloorPoses({0: module(0.0, 0.0, 0.0), 4: module(1.0, 1.0, 1.0)}))
    assert set(out.modules) == {0, 4} and centre(out, 4) == pytest.approx((1.0, 1.0, 1.0))


def test_benedict_bordner_and_bad_gains() -> None:
    assert benedict_bordner(0.3) == pytest.approx(0.09 / 1.7)
    for alpha in (0.0, -0.1, 1.5):
        with pytest.raises(ValueError, match="alpha"):
            FloorFilter(alpha)
    with pytest.raises(ValueError, match="beta"):
        FloorFilter(0.3, 2.5)
