"""An overhead camera over the PyBullet arena, and ArUco markers on the modules' tops: frames
that ``dh2rt tracker`` reads in place of a real camera's, with the simulator's truth beside them.

* :class:`OverheadCamera` renders top-down frames with PyBullet's TinyRenderer (no GPU, no
  window; deterministic) from a pinhole camera ``height_m`` over the floor, looking straight
  down, image up = arena +y; :meth:`OverheadCamera.calibration` is the intrinsics and camera
  pose that PyBullet's view and projection matrices imply, in ``dh2rt tracker``'s calibration
  format (docs/tracker.md).
* :class:`MarkerPlates` puts a thin visual plate with an ArUco marker (drawn by
  ``cv2.aruco.generateImageMarker``) on each module's centre body, the marker's top edge
  towards the module's front connector: plates are visual only (no mass, no collision), so
  the physics is the same with or without them. Free plates can be placed anywhere too.

``python -m sim.overhead OUT --topology snake:4 --frames 3`` writes ``frame-NNN.png``,
``calibration.json`` and ``truth.json`` (each frame's marker poses, from the simulator).
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pybullet as p

from dh2rt.errors import TopologyError
from dh2rt.topology import parse_spec
from firmware.motion.body import DEFAULT_MODEL
from sim.world import World

Image = npt.NDArray[np.uint8]
#: Texture resolution of a plate (pixels per millimetre).
TEXTURE_PX_PER_MM = 8
#: How far a plate's face sits over the module's top (m): it must not vanish into the box.
PLATE_LIFT_M = 0.0002
DEFAULT_MARKER_MM = 20.0
DEFAULT_PLATE_MM = 25.4


@dataclass(frozen=True)
class MarkerTruth:
    """Where a marker really is: its centre on the floor (mm) and heading (degrees CCW from +x)."""

    marker: int
    x_mm: float
    y_mm: float
    heading_deg: float

    def to_json(self) -> dict[str, Any]:
        return {"marker": self.marker, "x_mm": self.x_mm, "y_mm": self.y_mm, "heading_deg": self.heading_deg}


@dataclass(frozen=True)
class OverheadCamera:
    """A pinhole camera ``height_m`` over ``centre_m``, looking straight down; ``fov_deg`` is
    the vertical field of view."""

    centre_m: tuple[float, float] = (0.0, 0.0)
    height_m: float = 1.0
    width_px: int = 1280
    height_px: int = 960
    fov_deg: float = 40.0
    #: Each pixel is the mean of supersample x supersample rendered ones: TinyRenderer draws
    #: no antialiasing, a lens and a sensor blur every edge.
    supersample: int = 1

    @property
    def focal_px(self) -> float:
        return (self.height_px / 2) / math.tan(math.radians(self.fov_deg) / 2)

    def calibration(self, marker_height_mm: float) -> dict[str, Any]:
        """The camera as ``dh2rt tracker --calibration`` reads it (no distortion: a pinhole).
        Camera frame (OpenCV's) -> arena: x stays, y and z turn over."""
        f = self.focal_px
        return {
            "fx": f,
            "fy": f,
            "cx": self.width_px / 2,
            # measured: TinyRenderer draws the optical axis on row height/2 - 1 (on column width/2)
            "cy": self.height_px / 2 - 1,
            "distortion": [],
            "image_size": [self.width_px, self.height_px],
            "marker_height_mm": marker_height_mm,
            "camera_pose": {
                "rotation": [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]],
                "translation_mm": [self.centre_m[0] * 1000, self.centre_m[1] * 1000, self.height_m * 1000],
            },
        }

    def render(self, client: int) -> Image:
        """One frame of ``client``'s scene, RGB, ``height_px`` x ``width_px`` x 3."""
        x, y = self.centre_m
        k = self.supersample
        width, height = self.width_px * k, self.height_px * k
        view = p.computeViewMatrix((x, y, self.height_m), (x, y, 0.0), (0.0, 1.0, 0.0), physicsClientId=client)
        projection = p.computeProjectionMatrixFOV(
            self.fov_deg, self.width_px / self.height_px, 0.05, self.height_m + 1.0, physicsClientId=client
        )
        _, _, rgba, _, _ = p.getCameraImage(
            width,
            height,
            view,
            projection,
            shadow=0,
            lightDirection=(0.0, 0.0, 1.0),
            lightAmbientCoeff=0.8,
            lightDiffuseCoeff=0.2,
            lightSpecularCoeff=0.0,
            renderer=p.ER_TINY_RENDERER,
            physicsClientId=client,
        )
        pixels = np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[:, :, :3]
        binned = pixels.reshape(self.height_px, k, self.width_px, k, 3).mean(axis=(1, 3))
        return np.ascontiguousarray(np.round(binned).astype(np.uint8))


def marker_texture(marker: int, marker_mm: float, plate_mm: float, dictionary: str = "DICT_4X4_50") -> Image:
    """A plate's picture: the marker (``marker_mm`` wide) centred on white (``plate_mm``)."""
    import cv2

    side = round(plate_mm * TEXTURE_PX_PER_MM)
    inner = round(marker_mm * TEXTURE_PX_PER_MM)
    chosen = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    drawn = np.asarray(cv2.aruco.generateImageMarker(chosen, marker, inner), dtype=np.uint8)
    plate = np.full((side, side), 255, dtype=np.uint8)
    start = (side - inner) // 2
    plate[start : start + inner, start : start + inner] = drawn
    return plate


class MarkerPlates:
    """Visual plates carrying ArUco markers in one physics client (see the module docs)."""

    def __init__(
        self,
        client: int,
        markers: Sequence[int],
        *,
        marker_mm: float = DEFAULT_MARKER_MM,
        plate_mm: float = DEFAULT_PLATE_MM,
        dictionary: str = "DICT_4X4_50",
    ) -> None:
        from PIL import Image as PilImage

        if marker_mm >= plate_mm:
            raise ValueError(f"a {marker_mm} mm marker does not fit a {plate_mm} mm plate with a white margin")
        self.client = client
        self.marker_mm = marker_mm
        self.plate_mm = plate_mm
        self.bodies: dict[int, int] = {}
        half = plate_mm / 2000
        # the picture's top edge on the plate's +x side, its left edge on +y (seen from above)
        vertices = [(half, half, 0.0), (half, -half, 0.0), (-half, -half, 0.0), (-half, half, 0.0)]
        with tempfile.TemporaryDirectory(prefix="dh2rt-markers-") as folder:
            for marker in markers:
                path = Path(folder) / f"marker-{marker}.png"
                PilImage.fromarray(marker_texture(marker, marker_mm, plate_mm, dictionary)).convert("RGB").save(path)
                texture = p.loadTexture(str(path), physicsClientId=client)
                shape = p.createVisualShape(
                    p.GEOM_MESH,
                    vertices=vertices,
                    indices=[0, 2, 1, 0, 3, 2],
                    uvs=[(0.0, 1.0), (1.0, 1.0), (1.0, 0.0), (0.0, 0.0)],
                    normals=[(0.0, 0.0, 1.0)] * 4,
                    physicsClientId=client,
                )
                body = p.createMultiBody(0.0, -1, shape, (0.0, 0.0, -1.0), physicsClientId=client)
                p.changeVisualShape(body, -1, textureUniqueId=texture, rgbaColor=(1, 1, 1, 1), physicsClientId=client)
                self.bodies[marker] = body

    def place(self, marker: int, x_m: float, y_m: float, z_m: float, heading_deg: float) -> None:
        """Put a free plate flat at (x, y, z), its marker's top edge towards ``heading_deg``."""
        yaw = math.radians(heading_deg)
        orientation = (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
        p.resetBasePositionAndOrientation(
            self.bodies[marker], (x_m, y_m, z_m), orientation, physicsClientId=self.client
        )

    def follow(self, world: World, markers: dict[int, int]) -> list[MarkerTruth]:
        """Put plate ``markers[m]`` on module ``m``'s centre body, as it is now; the truth."""
        top = world.model.centre.half[2] + PLATE_LIFT_M
        found = []
        for module, marker in sorted(markers.items(), key=lambda item: item[1]):
            body = world.body(module)
            position, orientation = p.getBasePositionAndOrientation(body, physicsClientId=world.client)
            plate_at = p.multiplyTransforms(position, orientation, (0.0, 0.0, top), (0, 0, 0, 1))[0]
            p.resetBasePositionAndOrientation(self.bodies[marker], plate_at, orientation, physicsClientId=self.client)
            forward = p.multiplyTransforms((0, 0, 0), orientation, (1.0, 0.0, 0.0), (0, 0, 0, 1))[0]
            heading = math.degrees(math.atan2(forward[1], forward[0])) % 360.0
            found.append(MarkerTruth(marker, plate_at[0] * 1000, plate_at[1] * 1000, heading))
        return found


def module_marker_height_mm() -> float:
    """The markers' plane on a module standing upright on the floor (mm)."""
    return (DEFAULT_MODEL.centre.size[2] + PLATE_LIFT_M) * 1000


def bare_arena() -> int:
    """A physics client with nothing but a light floor, for free plates."""
    client = int(p.connect(p.DIRECT))
    look = p.createVisualShape(
        p.GEOM_BOX, halfExtents=(5.0, 5.0, 0.001), rgbaColor=(0.82, 0.84, 0.8, 1.0), physicsClientId=client
    )
    p.createMultiBody(0.0, -1, look, (0.0, 0.0, -0.001), physicsClientId=client)
    return client


@dataclass(frozen=True)
class Shot:
    """One rendered frame (RGB), the markers' truth in it, the camera that took it and the
    seconds it took."""

    image: Image
    truth: list[MarkerTruth]
    camera: OverheadCamera
    seconds: float


def robot_frames(
    topology_spec: str, frames: int, seed: int, camera: OverheadCamera, *, centred: bool = False
) -> Iterator[Shot]:
    """Frame k: a World of ``topology_spec`` built with seed ``seed + k`` (turned and shifted)
    and let settle for a quarter of a second, markers 0..n-1 on modules 0..n-1. ``centred``:
    the camera moved over the robot's centroid (to the millimetre) for each frame, so that a
    large robot, which a seed turns about module 0, stays in the field."""
    for k in range(frames):
        started = time.perf_counter()
        with World(parse_spec(topology_spec), seed=seed + k) as world:
            world.step(round(world.physics_hz / 4))
            plates = MarkerPlates(world.client, list(range(world.size)))
            truth = plates.follow(world, {m: m for m in range(world.size)})
            x, y, _ = world.centroid()
            taking = replace(camera, centre_m=(round(x, 3), round(y, 3))) if centred else camera
            image = taking.render(world.client)
        yield Shot(image, truth, taking, time.perf_counter() - started)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m sim.overhead OUT``: rendered frames of a robot, their calibration and truth."""
    parser = argparse.ArgumentParser(prog="python -m sim.overhead", description=main.__doc__)
    parser.add_argument("out", type=Path, help="folder to write frame-NNN.png, calibration.json, truth.json into")
    parser.add_argument("--topology", default="snake:4", help="the robot (default: snake:4)")
    parser.add_argument("--frames", type=int, default=3, help="frames, each of the robot turned anew (default: 3)")
    parser.add_argument("--seed", type=int, default=1, help="the first frame's World seed (default: 1)")
    ns = parser.parse_args(argv)
    if ns.frames < 1:
        parser.error(f"argument --frames: expected 1 or more, got {ns.frames}")
    try:
        parse_spec(ns.topology)
    except TopologyError as exc:
        parser.error(f"argument --topology: {exc}")
    ns.out.mkdir(parents=True, exist_ok=True)
    from PIL import Image as PilImage

    camera = OverheadCamera()
    truth = []
    for k, shot in enumerate(robot_frames(ns.topology, ns.frames, ns.seed, camera)):
        name = f"frame-{k:03d}.png"
        PilImage.fromarray(shot.image).save(ns.out / name)
        truth.append({"file": name, "markers": [m.to_json() for m in shot.truth]})
    (ns.out / "calibration.json").write_text(json.dumps(camera.calibration(module_marker_height_mm()), indent=2) + "\n")
    (ns.out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
