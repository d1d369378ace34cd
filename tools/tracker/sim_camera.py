"""The overhead tracker as a robot has it, in physics: a rendered camera and ``dh2rt tracker``'s
detector, in place of the simulator's state.

:class:`sim.tracker.OverheadTracker` fills the docking motions' floor poses from the
simulator's bodies, with modelled noise. :class:`CameraTracker` fills them as a camera over
the arena would: a plate with an ArUco marker on the top of each of each module's three parts
(:class:`sim.overhead.MarkerPlates`, visual only: the physics is the same; marker ``3 m + k``
on module ``m``'s centre, front and back part, ``k`` 0, 1, 2, the marker's top edge along the
part's x axis), a fixed overhead camera rendered by PyBullet (:class:`sim.overhead.OverheadCamera`)
and :class:`tools.tracker.detect.MarkerDetector` on each frame, exactly as ``dh2rt tracker``
reads a real camera's. What the motions then steer by is what the detector saw: its errors,
a part it missed (out of view, tilted past the fit), a marker on a lifted part read on the
markers' plane.

A part a frame lacks keeps its last detected pose, its age counting up (the stand-in's
dropout rule); a module none of whose parts was ever detected is not reported, and a motion
that needs it raises :class:`firmware.motion.readings.TrackerMissing`, as on a robot. A part
seen only in some frames borrows nothing from the simulator: the pose is the detector's or none.

Frames are taken lazily, at a cycle that reads the floor (as the stand-in's), at most one
every ``every`` control cycles: the camera's frame rate (the physics runner's cycle is 50 ms,
so ``every=2`` is a 10 frames/s camera); between frames a reading is the last frame, aged.
Rendering a 1600 x 1200 frame takes about half a second on one core, and the motions of legs
to snake read the floor at nearly every one of its ~6,000 cycles: a run at ``every=3`` renders
for some 15 minutes.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
import pybullet as p

from firmware.motion.body import BACK, CENTRE, FRONT
from firmware.motion.readings import FloorPoses, ModulePose, PartPose
from sim.overhead import DEFAULT_MARKER_MM, PLATE_LIFT_M, MarkerPlates, OverheadCamera
from sim.world import World
from tools.tracker.accuracy import camera_calibration
from tools.tracker.detect import MarkerDetector

#: The parts a module carries a marker on, in marker order (3 m, 3 m + 1, 3 m + 2).
PARTS = (CENTRE, FRONT, BACK)
#: OpenCV's 4x4 dictionaries by size: the smallest that holds every marker is used.
DICTIONARIES = ((50, "DICT_4X4_50"), (100, "DICT_4X4_100"), (250, "DICT_4X4_250"), (1000, "DICT_4X4_1000"))


#: The arena camera's ground resolution (mm a pixel): a 20 mm marker spans 16 pixels, which the
#: detector reads (at 1.6 mm a pixel, 12.5 pixels, it found none of the dragon's markers).
MM_PER_PX = 1.25


def arena_camera(world: World, margin_m: float = 0.7) -> OverheadCamera:
    """A fixed camera over ``world``'s robot as it starts, its field the robot's extent and
    ``margin_m`` around (where a released foot walks), 50 degrees of vertical field, as many
    pixels (4:3) as keep :data:`MM_PER_PX`."""
    centres = np.array([world.part_transform(m, CENTRE)[:3, 3] for m in range(world.size)])
    low, high = centres[:, :2].min(axis=0) - margin_m, centres[:, :2].max(axis=0) + margin_m
    fov_deg = 50.0
    half_h = max((high[1] - low[1]) / 2, (high[0] - low[0]) / 2 * 3 / 4)
    height_px = 8 * math.ceil(2 * half_h * 1000 / MM_PER_PX / 8)
    height_m = half_h / math.tan(math.radians(fov_deg) / 2)
    centre = ((low + high) / 2).round(3)
    return OverheadCamera(
        centre_m=(float(centre[0]), float(centre[1])),
        height_m=round(float(height_m), 3),
        width_px=height_px * 4 // 3,
        height_px=height_px,
        fov_deg=fov_deg,
    )


class CameraTracker:
    """A camera over ``world``'s arena and the detector on its frames (see the module docs)."""

    def __init__(self, world: World, camera: OverheadCamera | None = None, *, every: int = 1) -> None:
        if every < 1:
            raise ValueError(f"a camera takes a frame at most every {every} cycles: expected 1 or more")
        self.every = every
        count = 3 * world.size
        dictionary = next((name for size, name in DICTIONARIES if count <= size), None)
        if dictionary is None:
            raise ValueError(f"{world.size} modules need {count} markers: more than OpenCV's 4x4 dictionaries hold")
        self.world = world
        self.camera = camera or arena_camera(world)
        self.plates = MarkerPlates(world.client, list(range(count)), dictionary=dictionary)
        self._top = {part: self._half_height(part) + PLATE_LIFT_M for part in PARTS}
        height_mm = (world.model.centre.size[2] + PLATE_LIFT_M) * 1000  # a part lying flat
        self.detector = MarkerDetector(camera_calibration(self.camera, height_mm), DEFAULT_MARKER_MM, dictionary)
        self._last: dict[int, tuple[PartPose, int]] = {}  # marker -> its last pose, the cycle it was seen
        self._frame: tuple[int, FloorPoses] | None = None
        #: frames taken, part reports a frame lacked, and the seconds spent rendering and detecting
        self.frames = 0
        self.dropped = 0
        self.render_s = 0.0
        self.detect_s = 0.0
        #: each detected part's error against the simulator's truth (mm, degrees): measured, never read back
        self.errors_mm: list[float] = []
        self.errors_deg: list[float] = []

    def _half_height(self, part: int) -> float:
        model = self.world.model
        box = {CENTRE: model.centre, FRONT: model.front, BACK: model.back}[part]
        return float(box.size[2]) / 2

    def reading(self, cycle: int) -> FloorPoses:
        """What the camera shows at control cycle ``cycle``: a frame taken now, or the last
        one, aged, if it is fewer than :attr:`every` cycles old."""
        if self._frame is None or not 0 <= cycle - self._frame[0] < self.every:
            self._frame = (cycle, self._take(cycle))
        taken, frame = self._frame
        if taken == cycle:
            return frame
        return FloorPoses({m: replace(pose, age=pose.age + cycle - taken) for m, pose in frame.modules.items()})

    def _take(self, cycle: int) -> FloorPoses:
        truth = self._place_plates()
        started = time.perf_counter()
        image = self.camera.render(self.world.client)
        self.render_s += time.perf_counter() - started
        started = time.perf_counter()
        found = self.detector.detect(np.ascontiguousarray(image[:, :, ::-1]))  # RGB -> BGR
        self.detect_s += time.perf_counter() - started
        self.frames += 1
        for pose in found.poses:
            seen = PartPose(pose.x_mm / 1000, pose.y_mm / 1000, math.radians(pose.heading_deg))
            self._last[pose.marker] = (seen, cycle)
            real = truth.get(pose.marker)
            if real is not None:
                self.errors_mm.append(math.hypot(seen.x - real.x, seen.y - real.y) * 1000)
                turn = (seen.heading - real.heading + math.pi) % (2 * math.pi) - math.pi
                self.errors_deg.append(abs(math.degrees(turn)))
        seen_now = {pose.marker for pose in found.poses}
        modules: dict[int, ModulePose] = {}
        for m in range(self.world.size):
            markers = [3 * m + k for k in range(len(PARTS))]
            self.dropped += sum(1 for marker in markers if marker not in seen_now)
            parts = [self._last[marker] for marker in markers if marker in self._last]
            if len(parts) < len(PARTS):
                continue  # a part never seen: the module is not reported
            (centre, _), (front, _), (back, _) = parts
            modules[m] = ModulePose(centre, front, back, max(cycle - seen_at for _, seen_at in parts))
        return FloorPoses(modules)

    def _place_plates(self) -> dict[int, PartPose]:
        """Each plate on its part's top, as the part lies now; each part's true floor pose."""
        truth: dict[int, PartPose] = {}
        for m in range(self.world.size):
            for k, part in enumerate(PARTS):
                position, orientation = self.world.part_pose(m, part)
                top = p.multiplyTransforms(position, orientation, (0.0, 0.0, self._top[part]), (0, 0, 0, 1))[0]
                p.resetBasePositionAndOrientation(
                    self.plates.bodies[3 * m + k], top, orientation, physicsClientId=self.world.client
                )
                r = p.getMatrixFromQuaternion(orientation)  # row-major: the part's x axis is (r[0], r[3], r[6])
                truth[3 * m + k] = PartPose(position[0], position[1], math.atan2(r[3], r[0]))
        return truth
