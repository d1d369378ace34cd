"""Seeing a run: GIF frames of a World streamed to disk, and the samples a plot is made of.

:class:`Recorder` renders with PyBullet's software renderer (``ER_TINY_RENDERER``, no display
needed) and hands each frame to :class:`sim.gif.GifStream`, which writes it at once: memory
does not grow with the length of the run.

What a frame shows:

- a checkered floor (10 cm squares, a darker line every metre) at fixed world coordinates, so
  motion shows against it whatever the camera does. The floor is not rendered: PyBullet's
  software renderer spends nearly all of a frame (15 to 150 ms at 320x240) shading a floor
  that fills the picture, against 1 to 2 ms for the robot alone. So the world's floor is made
  transparent for the render (its look only, restored at once: the physics is the same with
  and without a recording), and the pixels nothing was drawn on (segmentation -1) take a
  painted floor image: where each pixel's ray meets z=0, a few whole-array numpy operations
  (:func:`_floor_image`), made again only when the camera moves. The robot casts no shadow;
- the camera ``fixed`` (default): aimed at the robot's start, high enough that the robot and
  some floor around it fit; when the robot's centroid walks out of the middle of the picture
  the camera jumps to it once and stays there again. ``follow``: aimed at the centroid every
  frame (smoothed), so the floor slides under the robot;
- the head marked (a red triangle over each module whose ``front`` connector is free and which
  is docked to something: the head of each piece), and a caption (the caller's label, e.g. the
  cycle, and the simulated time).

:func:`sample_world` is one sample for :func:`sim.plot.plot_run` (re-exported here).
"""

from __future__ import annotations

import math
from pathlib import Path
from types import TracebackType
from typing import Literal

import numpy as np
import pybullet as p
from numpy.typing import NDArray
from PIL import Image, ImageDraw, ImageFont

from dh2rt.errors import RecordError
from sim.gif import RESERVED, GifStream
from sim.plot import Sample, plot_run
from sim.world import World

__all__ = ["CAMERAS", "Recorder", "Sample", "head_modules", "plot_run", "sample_world"]

Vec3 = tuple[float, float, float]
Camera = Literal["fixed", "follow"]
#: The camera modes (``--camera``).
CAMERAS: tuple[Camera, ...] = ("fixed", "follow")

_SQUARE_M = 0.1  # checker square
_LINE_M = 0.012  # width of the line drawn every metre
_DARK_SQUARE, _LINE = 0.88, 0.55  # brightness of the darker squares and of the lines
_SKY = (255, 255, 255)  # PyBullet's software renderer's background, where no floor is seen
_LIT = 0.94  # the floor's colour as rendered, over its own colour (measured: (196, 201, 191))


def _floor_image(
    view: tuple[float, ...], projection: tuple[float, ...], size: tuple[int, int], colour: tuple[int, int, int]
) -> NDArray[np.uint8]:
    """The floor as the camera sees it, ``colour`` checkered (10 cm squares, a line every metre)
    at fixed world coordinates; the sky where the floor is beyond the far plane.

    Each pixel's NDC depth where its ray meets the floor z=0 is linear in the pixel's NDC
    (x, y), and the world point there a ratio of linear functions: a handful of whole-array
    operations, no per-pixel loop."""
    w, h = size
    # PyBullet's matrices are column-major: reshape gives the transpose
    pv = np.asarray(projection, dtype=np.float64).reshape(4, 4).T @ np.asarray(view, dtype=np.float64).reshape(4, 4).T
    inv = np.linalg.inv(pv)
    nx = ((np.arange(w) + 0.5) / w * 2 - 1)[None, :]
    ny = (1 - (np.arange(h) + 0.5) / h * 2)[:, None]
    if abs(inv[2, 2]) < 1e-12:  # the camera looks along the floor: no floor seen
        return np.broadcast_to(np.asarray(_SKY, dtype=np.uint8), (h, w, 3)).copy()
    nz = -(inv[2, 0] * nx + inv[2, 1] * ny + inv[2, 3]) / inv[2, 2]  # NDC depth of the floor
    wh = inv[3, 0] * nx + inv[3, 1] * ny + inv[3, 2] * nz + inv[3, 3]
    x = (inv[0, 0] * nx + inv[0, 1] * ny + inv[0, 2] * nz + inv[0, 3]) / wh
    y = (inv[1, 0] * nx + inv[1, 1] * ny + inv[1, 2] * nz + inv[1, 3]) / wh
    checker = (np.floor(x / _SQUARE_M) + np.floor(y / _SQUARE_M)) % 2 == 1
    shade = np.where(checker, _DARK_SQUARE, 1.0)
    half = _LINE_M / 2
    line = (np.abs(x - np.round(x)) < half) | (np.abs(y - np.round(y)) < half)
    shade = np.where(line, _LINE, shade)
    floor = (shade[..., None] * np.asarray(colour, dtype=np.float64)).astype(np.uint8)
    # between the near and the far plane (behind the camera is beyond the far plane too)
    seen = (nz >= -1.0) & (nz <= 1.0)
    return np.where(seen[..., None], floor, np.asarray(_SKY, dtype=np.uint8))


def head_modules(world: World) -> list[int]:
    """The head of each piece: modules whose ``front`` connector is free and that are docked
    to something (module 0 if there is none, e.g. a lone module)."""
    profile = world.topology.profile
    front = profile.connector_index("front") if "front" in profile.connectors else 1
    docked: set[int] = set()
    taken: set[tuple[int, int]] = set()
    for link in world.links():
        docked.update((link.a, link.b))
        taken.update(link.ends())
    heads = [m for m in sorted(docked) if (m, front) not in taken]
    return heads or [0]


def _yaw_deg(world: World, module: int) -> float:
    """Where the module's x axis (out of its front) points on the floor, degrees from +x."""
    _, q = p.getBasePositionAndOrientation(world.body(module), physicsClientId=world.client)
    x, y, z, w = q
    return math.degrees(math.atan2(2 * (x * y + z * w), 1 - 2 * (y * y + z * z)))


def sample_world(world: World) -> Sample:
    """(time, each module's (DOF1, DOF2), centroid, head position, head yaw): one plot sample.

    The head is the lowest-numbered of :func:`head_modules`."""
    head = head_modules(world)[0]
    return (
        world.time,
        [world.joint_angles(m) for m in range(world.size)],
        world.centroid(),
        world.module_position(head),
        _yaw_deg(world, head),
    )


def _mat_vec(m: tuple[float, ...], v: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    # PyBullet's matrices are 16 floats, column-major
    return (
        m[0] * v[0] + m[4] * v[1] + m[8] * v[2] + m[12] * v[3],
        m[1] * v[0] + m[5] * v[1] + m[9] * v[2] + m[13] * v[3],
        m[2] * v[0] + m[6] * v[1] + m[10] * v[2] + m[14] * v[3],
        m[3] * v[0] + m[7] * v[1] + m[11] * v[2] + m[15] * v[3],
    )


class Recorder:
    """Captures frames of ``world`` and streams them to ``path`` as an animated GIF.

    Call :meth:`capture` whenever a frame is wanted (:meth:`due` says when, for ``fps`` frames
    per second of playback at ``speed`` times real time) and :meth:`save` at the end; as a
    context manager it saves on a clean exit and removes the partial file otherwise.
    ``distance`` is the camera distance in metres (default: fits the robot).
    """

    def __init__(
        self,
        world: World,
        path: Path,
        fps: int = 10,
        size: tuple[int, int] = (320, 240),
        *,
        camera: Camera = "fixed",
        speed: float = 1.0,
        distance: float | None = None,
        yaw_deg: float | None = None,
        pitch_deg: float = -35.0,
        floor: bool = True,
    ) -> None:
        if not 1 <= fps <= 50:
            raise RecordError(f"fps must be between 1 and 50, got {fps}")
        if len(size) != 2 or not all(16 <= s <= 4096 for s in size):
            raise RecordError(f"size must be (width, height) with each in 16..4096, got {size}")
        if camera not in CAMERAS:
            raise RecordError(f"camera must be one of {', '.join(CAMERAS)}, got {camera!r}")
        if not (math.isfinite(speed) and 0.1 <= speed <= 100.0):
            raise RecordError(f"speed must be between 0.1 and 100, got {speed}")
        self.world = world
        self.path = Path(path)
        self.fps = fps
        self.speed = speed
        self.size = (int(size[0]), int(size[1]))
        self.camera: Camera = camera
        # default: looking across the direction the robot faced at the start, so that
        # forward is to the right of the picture (a little towards the viewer)
        fx, fy, _ = world.forward
        self.yaw_deg = yaw_deg if yaw_deg is not None else math.degrees(math.atan2(fy, fx)) + 20.0
        self.pitch_deg = pitch_deg
        pts = world.positions()
        span = world.model.length + max(math.dist(a, b) for a in pts for b in pts)
        roomy = 1.7 if camera == "fixed" else 1.2  # a fixed camera shows floor to move over
        self.distance = distance if distance is not None else max(0.45, span * roomy)
        c = world.centroid()
        # a fixed camera starts with the robot left of the middle: room to walk into
        lead = 0.25 * self.distance if camera == "fixed" else 0.0
        self._target: Vec3 = (c[0] + lead * fx, c[1] + lead * fy, c[2])
        self._next_time = world.time
        self._stream = GifStream(self.path, self.size, round(1000 / fps))
        w, h = self.size
        self._projection = p.computeProjectionMatrixFOV(fov=50.0, aspect=w / h, nearVal=0.02, farVal=40.0)
        self.floor = floor
        # the floor is painted, not rendered: PyBullet's software renderer costs 15 to 150 ms a
        # frame on a floor that fills the picture, against 1 to 2 ms on the robot alone
        ground = p.getVisualShapeData(world.ground, physicsClientId=world.client)
        self._ground_rgba: tuple[float, float, float, float] = tuple(ground[0][7]) if ground else (0.8, 0.8, 0.8, 1.0)
        r, g, b, _ = self._ground_rgba
        self._floor_colour = (round(255 * _LIT * r), round(255 * _LIT * g), round(255 * _LIT * b))
        self._background: tuple[tuple[float, ...], NDArray[np.uint8]] | None = None  # (view, floor image)
        self._font = ImageFont.load_default()

    @property
    def frame_count(self) -> int:
        return self._stream.frames

    @property
    def frame_interval(self) -> float:
        """Simulated seconds between frames."""
        return self.speed / self.fps

    @property
    def steps_per_frame(self) -> int:
        """Physics steps between frames."""
        return max(1, round(self.world.physics_hz * self.frame_interval))

    def due(self) -> bool:
        """Whether a frame is due at the world's time now (then :meth:`capture` one)."""
        return self.world.time + 1e-9 >= self._next_time

    def _view(self) -> tuple[float, ...]:
        centroid = self.world.centroid()
        if self.camera == "follow":
            a = 0.35  # smoothing: the caterpillar's centroid rocks back and forth each gait cycle
            t = self._target
            self._target = (t[0] + a * (centroid[0] - t[0]), t[1] + a * (centroid[1] - t[1]), centroid[2])
        else:
            x, y = self._pixel(centroid, self._view_at(self._target))
            w, h = self.size
            if not (0.2 * w <= x <= 0.8 * w and 0.2 * h <= y <= 0.8 * h):
                # out of the middle: jump ahead of it, as at the start
                fx, fy, _ = self.world.forward
                lead = 0.25 * self.distance
                self._target = (centroid[0] + lead * fx, centroid[1] + lead * fy, centroid[2])
        return self._view_at(self._target)

    def _view_at(self, target: Vec3) -> tuple[float, ...]:
        return tuple(
            p.computeViewMatrixFromYawPitchRoll(
                cameraTargetPosition=(target[0], target[1], 0.0),
                distance=self.distance,
                yaw=self.yaw_deg,
                pitch=self.pitch_deg,
                roll=0.0,
                upAxisIndex=2,
            )
        )

    def _pixel(self, point: Vec3, view: tuple[float, ...]) -> tuple[float, float]:
        """Where a world point lands in the picture (x right, y down, pixels)."""
        eye = _mat_vec(view, (point[0], point[1], point[2], 1.0))
        clip = _mat_vec(tuple(self._projection), eye)
        wc = clip[3] if abs(clip[3]) > 1e-9 else 1e-9
        w, h = self.size
        return ((clip[0] / wc + 1) / 2 * w, (1 - clip[1] / wc) / 2 * h)

    def capture(self, label: str = "") -> None:
        """Render one frame now and write it: the caption is ``label`` and the simulated time."""
        w, h = self.size
        view = self._view()
        world = self.world
        r, g, b, a = self._ground_rgba
        # the floor is hidden while rendering (a transparent shape is not drawn) and painted
        # where nothing was drawn: its look only, the physics is untouched
        p.changeVisualShape(world.ground, -1, rgbaColor=(r, g, b, 0.0), physicsClientId=world.client)
        try:
            _, _, rgba, _, seg = p.getCameraImage(
                w, h, view, self._projection, renderer=p.ER_TINY_RENDERER, physicsClientId=world.client
            )
        finally:
            p.changeVisualShape(world.ground, -1, rgbaColor=(r, g, b, a), physicsClientId=world.client)
        pixels = np.asarray(rgba, dtype=np.uint8).reshape(h, w, 4)[..., :3]
        if self._background is None or self._background[0] != view:
            if self.floor:
                floor = _floor_image(view, tuple(self._projection), self.size, self._floor_colour)
            else:
                floor = np.empty((h, w, 3), dtype=np.uint8)
                floor[...] = self._floor_colour
            self._background = (view, floor)
        empty = np.asarray(seg).reshape(h, w) < 0
        pixels = np.where(empty[..., None], self._background[1], pixels)
        frame = Image.fromarray(np.ascontiguousarray(pixels), "RGB")
        self._overlay(frame, view, label)
        self._stream.add(frame)
        self._next_time = world.time + self.frame_interval - 1e-9

    def _overlay(self, frame: Image.Image, view: tuple[float, ...], label: str) -> None:
        black, white, red = RESERVED
        draw = ImageDraw.Draw(frame)
        top = self.world.model.height + 0.03
        for m in head_modules(self.world):
            x, y, z = self.world.module_position(m)
            px, py = self._pixel((x, y, z + top), view)
            r = max(4.0, self.size[1] / 48)
            draw.polygon([(px - r, py - 1.6 * r), (px + r, py - 1.6 * r), (px, py)], fill=red, outline=black)
        caption = "  ".join(s for s in (label, f"t = {self.world.time:.1f} s") if s)
        box = draw.textbbox((4, 3), caption, font=self._font)
        draw.rectangle((box[0] - 3, box[1] - 2, box[2] + 3, box[3] + 2), fill=white)
        draw.text((4, 3), caption, fill=black, font=self._font)

    def save(self) -> Path:
        """Finish the GIF and return its path."""
        return self._stream.close()

    def abandon(self) -> None:
        """Stop and remove the partial GIF."""
        self._stream.abandon()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is not None:
            self.abandon()
        elif self.frame_count:
            self.save()
