"""The overhead tracker's PyBullet stand-in: where each module lies on the floor, as a sensor.

On a real robot a camera over the arena sees a marker on each part of each module (ArUco or
AprilTag on the parts' tops) and `dh2rt tracker` publishes every module's pose over UDP once
a frame; each module's firmware receives it as its ``floor_x``, ``floor_y``,
``floor_heading`` sensors (its own centre, docs/language.md *Sensors*) and its docking
motions as :class:`firmware.motion.readings.FloorPoses` (every module's three parts). This
stand-in fills the same reading from the simulator's bodies, with what a camera adds:

* Gaussian noise on each part's position (``noise_m``, metres, per axis) and heading
  (``noise_deg``), drawn independently per part and per frame;
* latency (``latency``, control cycles): a motion reads the frame taken that many cycles
  earlier;
* dropouts (``dropout``, probability per module per frame): a dropped module keeps the pose
  of its last frame, its age counting up; a module's first frame is never dropped (the
  tracker has seen every module once before a motion starts).

Seeded (``seed``): the same run gives the same noise. With noise 0 and latency 0 it is exact:
each part's centre on the floor and its x axis's heading, as the world has them.

The tracker is read lazily (:meth:`OverheadTracker.reading`): a cycle nobody reads costs
nothing. A tracker not read for longer than its latency starts afresh (its old frames would
be older than the latency says).
"""

from __future__ import annotations

import math
import random
from collections import deque
from typing import Protocol

from firmware.motion.body import BACK, CENTRE, FRONT
from firmware.motion.readings import FloorPoses, ModulePose, PartPose
from sim.world import World


class FloorTracker(Protocol):
    """What the motions' sensors read the floor from: this stand-in, or a rendered camera and
    ``dh2rt tracker``'s detector (:class:`tools.tracker.sim_camera.CameraTracker`)."""

    #: frames taken so far, and module (or part) reports a frame lacked
    frames: int
    dropped: int

    def reading(self, cycle: int) -> FloorPoses: ...


class OverheadTracker:
    """A camera over the arena, in a :class:`sim.world.World`."""

    def __init__(
        self,
        world: World,
        *,
        noise_m: float = 0.0,
        noise_deg: float = 0.0,
        latency: int = 0,
        dropout: float = 0.0,
        seed: int = 0,
    ) -> None:
        if noise_m < 0 or noise_deg < 0:
            raise ValueError(f"tracker noise must be >= 0, got {noise_m} m and {noise_deg} deg")
        if latency < 0:
            raise ValueError(f"tracker latency must be >= 0 cycles, got {latency}")
        if not 0.0 <= dropout < 1.0:
            raise ValueError(f"tracker dropout must be a probability below 1, got {dropout}")
        self.world = world
        self.noise_m = noise_m
        self.noise_deg = noise_deg
        self.latency = latency
        self.dropout = dropout
        self._rng = random.Random(seed)
        #: (cycle, frame) of the frames kept for the latency, oldest first
        self._frames: deque[tuple[int, FloorPoses]] = deque()
        #: Frames taken so far, and module reports dropped.
        self.frames = 0
        self.dropped = 0

    @property
    def exact(self) -> bool:
        return self.noise_m == 0 and self.noise_deg == 0 and self.latency == 0 and self.dropout == 0

    def _part(self, module: int, link: int) -> PartPose:
        t = self.world.part_transform(module, link)
        x, y = float(t[0, 3]), float(t[1, 3])
        heading = math.atan2(float(t[1, 0]), float(t[0, 0]))
        if self.noise_m:
            x += self._rng.gauss(0.0, self.noise_m)
            y += self._rng.gauss(0.0, self.noise_m)
        if self.noise_deg:
            heading += math.radians(self._rng.gauss(0.0, self.noise_deg))
        return PartPose(x, y, heading)

    def _frame(self, previous: FloorPoses | None) -> FloorPoses:
        modules: dict[int, ModulePose] = {}
        for m in range(self.world.size):
            before = previous.modules.get(m) if previous is not None else None
            if before is not None and self.dropout and self._rng.random() < self.dropout:
                self.dropped += 1
                modules[m] = ModulePose(before.centre, before.front, before.back, before.age + 1)
                continue
            modules[m] = ModulePose(self._part(m, CENTRE), self._part(m, FRONT), self._part(m, BACK))
        self.frames += 1
        return FloorPoses(modules)

    def reading(self, cycle: int) -> FloorPoses:
        """What the tracker has published by control cycle ``cycle``: the frame taken
        :attr:`latency` cycles earlier (a frame is taken at each cycle it is read)."""
        frames = self._frames
        if frames and frames[-1][0] < cycle - self.latency - 1:
            frames.clear()  # not read for a while: its frames are older than the latency
        if not frames or frames[-1][0] < cycle:
            frames.append((cycle, self._frame(frames[-1][1] if frames else None)))
        while len(frames) > 1 and frames[1][0] <= cycle - self.latency:
            frames.popleft()
        taken, frame = frames[0]
        if taken == cycle:
            return frame
        return FloorPoses({m: _aged(pose, cycle - taken) for m, pose in frame.modules.items()})


def _aged(pose: ModulePose, cycles: int) -> ModulePose:
    return ModulePose(pose.centre, pose.front, pose.back, pose.age + cycles)
