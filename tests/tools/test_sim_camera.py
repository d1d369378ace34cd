"""The camera tracker in physics: a rendered frame over the dragon, read by ``dh2rt tracker``'s
detector, places every part of every module within the issue's target (1 cm, 2 degrees)
against the stand-in's exact report; a part out of view keeps its last pose and ages; a
module never seen is not reported."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import replace

import pytest

from dh2rt.topology import parse_spec
from firmware.motion.body import BACK, CENTRE, FRONT
from firmware.motion.readings import TrackerMissing
from sim.tracker import OverheadTracker
from sim.world import World
from tools.tracker.sim_camera import CameraTracker


@pytest.fixture(scope="module")
def dragon() -> Iterator[World]:
    world = World(parse_spec("dragon"), seed=0)
    world.step(60)
    yield world
    world.close()


def test_every_part_of_the_dragon_is_placed_within_a_centimetre_and_2_degrees(dragon: World) -> None:
    camera = CameraTracker(dragon)
    seen, exact = camera.reading(0), OverheadTracker(dragon).reading(0)
    assert set(seen.modules) == set(range(dragon.size)) and camera.dropped == 0
    for m in range(dragon.size):
        for part in (CENTRE, FRONT, BACK):
            a, b = seen.pose(m).part(part), exact.pose(m).part(part)
            assert math.hypot(a.x - b.x, a.y - b.y) < 0.01, (m, part)
            turn = (a.heading - b.heading + math.pi) % (2 * math.pi) - math.pi
            assert abs(math.degrees(turn)) < 2.0, (m, part)
    assert len(camera.errors_mm) == 3 * dragon.size and max(camera.errors_mm) < 2.0
    assert camera.reading(0) is seen and camera.frames == 1  # one frame a cycle, however often read


def test_a_module_out_of_view_keeps_its_last_pose_and_a_module_never_seen_is_not_reported(dragon: World) -> None:
    camera = CameraTracker(dragon)
    first = camera.reading(0)
    # the camera turned away from the robot: nothing in view, every part keeps its pose and ages
    camera.camera = replace(camera.camera, centre_m=(camera.camera.centre_m[0] + 50.0, 0.0))
    later = camera.reading(3)
    assert later.pose(0).centre == first.pose(0).centre and later.pose(0).age == 3
    assert camera.dropped == 3 * dragon.size
    blind = CameraTracker(dragon, replace(camera.camera))
    with pytest.raises(TrackerMissing):
        blind.reading(0).pose(0)


def test_a_slower_camera_reports_its_last_frame_aged_between_frames(dragon: World) -> None:
    camera = CameraTracker(dragon, every=3)
    camera.reading(10)
    assert [camera.reading(c).pose(0).age for c in (11, 12)] == [1, 2] and camera.frames == 1
    assert camera.reading(13).pose(0).age == 0 and camera.frames == 2
    with pytest.raises(ValueError, match="every 0 cycles"):
        CameraTracker(dragon, every=0)


def test_the_arena_camera_sees_a_turned_dragon_whole() -> None:
    """Seed 1 lays the dragon out turned: the field grows, and the camera keeps its ground
    resolution by its pixels (at a fixed 1600 x 1200 it saw none of the markers)."""
    with World(parse_spec("dragon"), seed=1) as world:
        world.step(60)
        camera = CameraTracker(world)
        field_mm = 2 * camera.camera.height_m * math.tan(math.radians(camera.camera.fov_deg) / 2) * 1000
        assert field_mm / camera.camera.height_px <= 1.25
        assert set(camera.reading(0).modules) == set(range(world.size))
