"""The overhead camera over the PyBullet arena (sim.overhead): frames are deterministic, the
marker plates are visual only (the physics is the same with them), and the calibration it
writes is the camera's."""

from __future__ import annotations

import math

import numpy as np
import pybullet as p
import pytest

from dh2rt.topology import parse_spec
from sim.overhead import MarkerPlates, OverheadCamera, bare_arena, marker_texture
from sim.world import World


def test_renders_are_deterministic_and_show_the_plate() -> None:
    camera = OverheadCamera(width_px=320, height_px=240)
    client = bare_arena()
    try:
        plates = MarkerPlates(client, [5])
        plates.place(5, 0.0, 0.0, 0.0254, 30.0)
        first, second = camera.render(client), camera.render(client)
    finally:
        p.disconnect(physicsClientId=client)
    assert first.shape == (240, 320, 3) and np.array_equal(first, second)
    assert first.min() < 40 and first.max() > 230  # the marker's black and its plate's white


def test_plates_leave_the_physics_alone() -> None:
    def walk(with_plates: bool) -> list[tuple[float, float, float]]:
        with World(parse_spec("snake:3"), seed=2) as world:
            if with_plates:
                plates = MarkerPlates(world.client, [0, 1, 2])
            for step in range(4):
                world.set_targets(1, 40.0 * (-1) ** step, 0.0)
                world.step(60)
                if with_plates:
                    plates.follow(world, {0: 0, 1: 1, 2: 2})
            return world.positions()

    assert walk(True) == walk(False)


def test_calibration_is_the_pinhole_pybullet_draws() -> None:
    camera = OverheadCamera(centre_m=(0.1, -0.2), height_m=1.5, width_px=640, height_px=480, fov_deg=50.0)
    cal = camera.calibration(20.0)
    assert cal["fx"] == cal["fy"] == pytest.approx(240 / math.tan(math.radians(25)))
    assert cal["camera_pose"]["translation_mm"] == pytest.approx([100.0, -200.0, 1500.0])
    assert cal["image_size"] == [640, 480] and cal["marker_height_mm"] == 20.0


def test_marker_texture_has_a_white_margin() -> None:
    texture = marker_texture(0, 20.0, 25.4)
    assert texture.shape == (203, 203)
    assert texture[:20].min() == 255 and texture[:, :20].min() == 255 and texture[100].min() == 0
    with pytest.raises(ValueError, match="does not fit"):
        MarkerPlates(-1, [0], marker_mm=26.0)
