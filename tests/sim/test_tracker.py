"""sim.tracker: the overhead tracker's stand-in is exact at noise 0, and noisy, late and
dropping as configured."""

from __future__ import annotations

import math
import statistics

import pytest

from dh2rt.compiler import compile_source
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from firmware.motion.body import BACK, CENTRE, FRONT
from firmware.motion.readings import TrackerMissing
from sim.runner import PhysicsRun
from sim.tracker import OverheadTracker
from sim.world import World


def test_an_exact_tracker_agrees_with_the_world_on_parts_and_faces() -> None:
    with World(parse_spec("snake:3")) as w:
        w.set_targets(1, 0.0, 40.0)
        w.step(120)
        tracker = OverheadTracker(w)
        assert tracker.exact
        floor = tracker.reading(0)
        for m in range(3):
            x, y, _ = w.module_position(m)
            assert floor.centre(m) == pytest.approx((x, y), abs=1e-9)
            for link in (CENTRE, FRONT, BACK):
                t = w.part_transform(m, link)
                part = floor.part(m, link)
                assert (part.x, part.y) == pytest.approx((t[0, 3], t[1, 3]), abs=1e-9)
                assert part.heading == pytest.approx(math.atan2(t[1, 0], t[0, 0]), abs=1e-9)
            for c in ("front", "back", "left", "right"):
                (px, py, _), (nx, ny, _) = w.connector_pose(m, c)
                fx, fy, fnx, fny = floor.face(w.model, m, c)
                # the modules lie flat: the face on the floor is the world's, to a tenth of a mm
                assert (fx, fy) == pytest.approx((px, py), abs=1e-4)
                assert (fnx, fny) == pytest.approx((nx, ny), abs=1e-3)
        with pytest.raises(TrackerMissing, match="has not reported module 7"):
            floor.pose(7)


def test_noise_is_gaussian_with_the_configured_spread_and_seeded() -> None:
    with World(parse_spec("snake:2")) as w:
        truth = OverheadTracker(w).reading(0)
        errors_m, errors_deg = [], []
        tracker = OverheadTracker(w, noise_m=0.005, noise_deg=2.0, seed=3)
        for cycle in range(400):
            floor = tracker.reading(cycle)
            got, want = floor.pose(0).centre, truth.pose(0).centre
            errors_m.append(got.x - want.x)
            errors_deg.append(math.degrees(got.heading - want.heading))
        assert statistics.pstdev(errors_m) == pytest.approx(0.005, rel=0.15)
        assert statistics.pstdev(errors_deg) == pytest.approx(2.0, rel=0.15)
        first, second = (OverheadTracker(w, noise_m=0.005, noise_deg=2.0, seed=3).reading(0) for _ in range(2))
        assert first == second != truth


def test_latency_delays_a_move_by_that_many_cycles() -> None:
    with World(parse_spec("snake:1")) as w:
        tracker = OverheadTracker(w, latency=3)
        for cycle in range(5):
            tracker.reading(cycle)
        w.set_module_pose(0, (0.5, 0.0, 0.02), 0.0)
        seen = []
        for cycle in range(5, 10):
            floor = tracker.reading(cycle)
            seen.append(floor.centre(0)[0] > 0.4)
            assert floor.pose(0).age == 3
        assert seen == [False, False, False, True, True]


def test_dropouts_keep_the_last_pose_and_count_its_age() -> None:
    with World(parse_spec("snake:2")) as w:
        tracker = OverheadTracker(w, dropout=0.5, seed=1)
        first = tracker.reading(0)
        assert set(first.modules) == {0, 1} and tracker.dropped == 0  # a first report is never dropped
        ages = [tracker.reading(c).pose(0).age for c in range(1, 200)]
        assert 60 < tracker.dropped < 140 * 2
        assert max(ages) >= 2 and ages.count(0) > 50


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"noise_m": -0.1}, "noise must be >= 0"),
        ({"latency": -1}, "latency must be >= 0"),
        ({"dropout": 1.0}, "dropout must be a probability below 1"),
    ],
)
def test_bad_settings_are_refused_by_name(kwargs: dict[str, float], message: str) -> None:
    with World(parse_spec("snake:1")) as w, pytest.raises(ValueError, match=message):
        OverheadTracker(w, **kwargs)  # type: ignore[arg-type]


def test_a_program_reads_its_floor_pose_from_the_tracker() -> None:
    program = compile_source("program floor\nconst ClockCycle = 4\nsensor floor_x, floor_y, floor_heading\n")
    robot = Robot(program, parse_spec("snake:2"))
    run = PhysicsRun(robot)
    try:
        run.run(2)
        for m in range(2):
            x, y, _ = run.world.module_position(m)
            e = robot.engines[m]
            assert e is not None
            names = program.sensor_names
            # filled as the last cycle began, before its physics steps: the module lay still
            assert abs(e.sensors[names.index("floor_x")] - x * 1000) <= 1.5
            assert abs(e.sensors[names.index("floor_y")] - y * 1000) <= 1.5
    finally:
        run.close()
