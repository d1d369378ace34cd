"""Smoothing the overhead tracker's reports before a motion steers by them.

A camera's pose of a marker jitters from frame to frame (a few millimetres and a degree or so
for ArUco at a metre); a motion that steers by every raw report chases that jitter. docs/physics.md
measured how much legs to snake takes unfiltered: it forms up to about 5 mm or 1 degree of
noise a report, not at 10 mm or 4 degrees.

:class:`FloorFilter` runs an alpha-beta filter (the fixed-gain steady state of a Kalman filter
with a constant-velocity model, as radar trackers have used since the 1950s) on each part's
x, y and heading, one step per control cycle:

* predict: ``x += v``; a report taken this cycle corrects it: ``r = z - x``,
  ``x += alpha * r``, ``v += beta * r`` (headings: the residual wrapped to +-pi);
* a report that is not new (the tracker dropped the module this frame and repeats its last
  pose, its age counting up) corrects nothing: the filter coasts on its velocity, at most
  :data:`MAX_COAST` cycles, then holds;
* a report that arrives ``age`` cycles late (the tracker's latency) is the part's pose
  ``age`` cycles ago: with ``predict`` the filter hands the motion its estimate carried
  forward by ``age`` cycles of its velocity.

The gains default to Benedict and Bordner's pair (``beta = alpha**2 / (2 - alpha)``): with
``alpha`` 0.3 a still part's noise falls to about half, and a part moving at constant velocity
is followed without lag. A part the filter has not heard of for :data:`RESET_GAP` cycles starts
afresh from its next report (its velocity is no longer known).

Sans-IO: reports in, reports out (:class:`firmware.motion.readings.FloorPoses`), numpy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from firmware.motion.readings import FloorPoses, ModulePose, PartPose

#: Cycles a part may go unreported before its track starts afresh.
RESET_GAP = 20
#: Cycles a track coasts on its velocity through dropped reports before it holds still.
MAX_COAST = 5


def benedict_bordner(alpha: float) -> float:
    """The beta that goes with ``alpha`` for a constant-velocity track (Benedict-Bordner)."""
    return alpha * alpha / (2.0 - alpha)


@dataclass
class _Track:
    """One module's three parts, as estimated at the cycle its last report was taken: rows
    centre, front, back; columns x, y (m), heading (rad); ``v`` per cycle."""

    x: np.ndarray
    v: np.ndarray
    taken: int


def _wrap(a: np.ndarray) -> np.ndarray:
    out: np.ndarray = (a + math.pi) % (2.0 * math.pi) - math.pi
    return out


def _matrix(pose: ModulePose) -> np.ndarray:
    return np.array([[p.x, p.y, p.heading] for p in (pose.centre, pose.front, pose.back)])


class FloorFilter:
    """An alpha-beta filter over every module the tracker reports (see the module docs)."""

    def __init__(self, alpha: float = 0.3, beta: float | None = None, *, predict: bool = True) -> None:
        if not 0.0 < alpha <= 1.0:
            raise ValueError(f"floor filter alpha must be in (0, 1], got {alpha}")
        beta = benedict_bordner(alpha) if beta is None else beta
        if not 0.0 <= beta < 2.0:
            raise ValueError(f"floor filter beta must be in [0, 2), got {beta}")
        self.alpha = alpha
        self.beta = beta
        self.predict = predict
        self._tracks: dict[int, _Track] = {}

    def update(self, cycle: int, poses: FloorPoses) -> FloorPoses:
        """The filtered poses at control cycle ``cycle`` of the tracker's reading ``poses``."""
        return FloorPoses({m: self._module(m, cycle, pose) for m, pose in poses.modules.items()})

    def _module(self, module: int, cycle: int, pose: ModulePose) -> ModulePose:
        taken = cycle - pose.age
        track = self._tracks.get(module)
        if track is None or taken - track.taken > RESET_GAP or taken < track.taken:
            track = self._tracks[module] = _Track(_matrix(pose), np.zeros((3, 3)), taken)
        elif taken > track.taken:  # a new report: correct the prediction by it
            gap = taken - track.taken
            predicted = track.x + track.v * min(gap, MAX_COAST)
            residual = _matrix(pose) - predicted
            residual[:, 2] = _wrap(residual[:, 2])
            track.x = predicted + self.alpha * residual
            track.x[:, 2] = _wrap(track.x[:, 2])
            track.v = track.v + (self.beta / gap) * residual
            track.taken = taken
        ahead = min(cycle - track.taken, MAX_COAST) if self.predict else 0
        estimate = track.x + track.v * ahead
        estimate[:, 2] = _wrap(estimate[:, 2])
        parts = [PartPose(float(r[0]), float(r[1]), float(r[2])) for r in estimate]
        return ModulePose(parts[0], parts[1], parts[2], pose.age)
