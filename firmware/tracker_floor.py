"""The floor a module's docking motions steer by, from the overhead tracker it hears itself.

With a ``[tracker]`` in its module.toml (:class:`firmware.config.TrackerSpec`), a module opens
a :class:`firmware.tracker_feed.TrackerFeed` on the tracker's UDP port, drains it once a
cycle (no thread, no wait) and builds its :class:`~firmware.motion.readings.FloorPoses` from
it: marker ``3 m + k`` is module ``m``'s part ``k`` (0 centre, 1 front, 2 back, as
``dh2rt tracker`` and tools/tracker/sim_camera.py number them), for every module index below
``modules``. A module is reported only when all three of its parts have a pose within
``max_age_s``; one with a part older than that, or never seen, is left out, and a motion that
needs it raises :class:`~firmware.motion.readings.TrackerMissing`, as on a robot.
"""

from __future__ import annotations

import math

from firmware.config import TrackerSpec
from firmware.motion.readings import FloorPoses, ModulePose, PartPose
from firmware.tracker_feed import TrackedPose, TrackerFeed

#: The parts of a module in marker order (3 m, 3 m + 1, 3 m + 2).
PART_NAMES = ("centre", "front", "back")


def part_name(module: int, part: int) -> str:
    """The feed's name of ``module``'s part ``part`` (0 centre, 1 front, 2 back)."""
    return f"m{module}.{PART_NAMES[part]}"


def markers(modules: int) -> dict[int, str]:
    """Marker id -> part name for modules ``0 .. modules - 1``."""
    return {3 * m + k: part_name(m, k) for m in range(modules) for k in range(3)}


def open_feed(spec: TrackerSpec, module: int) -> TrackerFeed:
    """The feed ``spec`` names, bound for ``module`` (OSError if the port cannot be bound)."""
    return TrackerFeed(
        markers(spec.modules), part_name(module, 0), bind=(spec.bind, spec.port), max_age_s=spec.max_age_s
    )


def _part(tracked: TrackedPose) -> PartPose:
    heading = math.remainder(math.radians(tracked.heading_deg), 2 * math.pi)  # within +-pi
    return PartPose(tracked.x_mm / 1000, tracked.y_mm / 1000, heading)


def floor_from_feed(feed: TrackerFeed, modules: int, cycle_period: float) -> FloorPoses:
    """Every module whose three parts have a fresh pose in ``feed``, its age the oldest part's
    in control cycles of ``cycle_period`` seconds (taken at the poll before this cycle: 0; at
    the one before: 1)."""
    fresh = feed.fresh()
    out: dict[int, ModulePose] = {}
    for m in range(modules):
        parts = [fresh.get(part_name(m, k)) for k in range(3)]
        if any(p is None for p in parts):
            continue
        seen = [p for p in parts if p is not None]
        age = round(max(p.age_s for p in seen) / cycle_period)
        centre, front, back = (_part(p) for p in seen)
        out[m] = ModulePose(centre, front, back, age)
    return FloorPoses(out)
