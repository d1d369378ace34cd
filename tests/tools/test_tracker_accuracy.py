"""The tracker's accuracy on frames PyBullet renders from 1 m over the arena, against the
simulator's truth (tools.tracker.accuracy): the issue's target is 1 cm and 2 degrees. The
figures docs/tracker.md quotes come from ``python -m benchmarks.bench_tracker``."""

from __future__ import annotations

import pytest

from tests.marks import LONG
from tools.tracker.accuracy import measure_free, measure_robot

TARGET_MM, TARGET_DEG = 10.0, 2.0


def test_free_markers_all_over_the_field_are_within_the_target() -> None:
    """24 markers at random poses (8 a frame), out to the frame's edges."""
    found = measure_free(frames=3, markers=8, seed=0)
    assert found.missed == 0 and len(found.position_mm) == 24
    assert max(found.position_mm) < TARGET_MM and max(found.heading_deg) < TARGET_DEG


def test_modules_of_a_robot_are_within_the_target() -> None:
    """A snake as sim.world.World lays it out, turned by its seed, a marker on each module."""
    found = measure_robot("snake:4", frames=1, seed=3)
    assert found.missed == 0 and len(found.position_mm) == 4
    assert max(found.position_mm) < TARGET_MM and max(found.heading_deg) < TARGET_DEG


@LONG
@pytest.mark.parametrize("topology", ["dragon", "quadruped", "t-shape"])
def test_robots_of_every_shape_are_within_the_target(topology: str) -> None:
    found = measure_robot(topology, frames=3, seed=1)
    assert found.missed == 0
    assert max(found.position_mm) < TARGET_MM and max(found.heading_deg) < TARGET_DEG


@LONG
def test_many_free_markers_are_within_the_target() -> None:
    found = measure_free(frames=20, markers=12, seed=7)
    assert found.missed == 0
    assert max(found.position_mm) < TARGET_MM and max(found.heading_deg) < TARGET_DEG
