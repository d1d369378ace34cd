"""What a docking motion reads: the readings a module has on a real robot, and nothing else.

A motion (:mod:`firmware.motion.reach`, :mod:`firmware.motion.crawl`,
:mod:`firmware.motion.clearing`) is stepped once a control cycle with a :class:`Readings`:

``joints``
    each module's own joint angles (its ``pos1``/``pos2`` sensors, degrees), for the modules
    of the chain that moves;
``infrared``
    a connector's infrared pair: ``ir_<c>`` (mm, 0 when nothing is in view) and
    ``ir_<c>_align`` (degrees off square, 180 when nothing is in view), by module;
``floor``
    the overhead tracker's last broadcast (:class:`FloorPoses`): where each module lies on the
    floor, as a camera over the arena sees it;
``attitude``
    a module's IMU: its ``roll`` and ``pitch`` (degrees), which tilt the tracker's planar
    pose of its centre (:meth:`PartPose.transform`).

The tracker reports, for every module it sees, the planar pose of each of its three parts
(:class:`PartPose`: the part's centre on the floor and the heading of its x axis there),
because a module's joints move its faces relative to its centre and a marker on each part's
top gives each part's pose directly (ArUco and AprilTag markers give a full pose each; the
floor plane keeps x, y and the heading). A face's place on the floor is its part's pose
applied to the face's position in the part (:meth:`FloorPoses.face`): exact while the part
lies flat, off by at most ``half length * (1 - cos pitch)`` while a pitch joint lifts it
(the front body's face: 5 mm at 45 degrees).

A module the tracker has never reported is an error (:class:`TrackerMissing`), never a
silent zero: a motion that needs the floor cannot guess it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from dh2rt.docking import End
from firmware.motion.body import BACK, CENTRE, FRONT, ConnectorSpec, ConroModel


class TrackerMissing(LookupError):
    """A motion asked the tracker for a module it has not reported."""


@dataclass(frozen=True, slots=True)
class PartPose:
    """One part of a module on the floor: its centre (m) and its x axis's heading (radians,
    counter-clockwise from the arena's x axis)."""

    x: float
    y: float
    heading: float

    def transform(self, roll_deg: float = 0.0, pitch_deg: float = 0.0) -> np.ndarray:
        """The part's frame as a 4x4 transform on the floor plane (z = 0), tilted by an IMU's
        ``roll`` and ``pitch`` if given (Z-Y-X Euler angles, as the IMU reads them)."""
        c, s = math.cos(self.heading), math.sin(self.heading)
        cp, sp = math.cos(math.radians(pitch_deg)), math.sin(math.radians(pitch_deg))
        cr, sr = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
        t = np.eye(4)
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
        rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
        t[:3, :3] = rz @ ry @ rx
        t[0, 3], t[1, 3] = self.x, self.y
        return t


@dataclass(frozen=True, slots=True)
class ModulePose:
    """A module on the floor: its three parts (:data:`firmware.motion.body.CENTRE`,
    ``FRONT``, ``BACK``) and how many cycles old the report is (0: this cycle's)."""

    centre: PartPose
    front: PartPose
    back: PartPose
    age: int = 0

    def part(self, link: int) -> PartPose:
        return {CENTRE: self.centre, FRONT: self.front, BACK: self.back}[link]


@dataclass(frozen=True)
class FloorPoses:
    """The overhead tracker's reading: every module it has seen, by module index."""

    modules: Mapping[int, ModulePose] = field(default_factory=dict)

    def pose(self, module: int) -> ModulePose:
        try:
            return self.modules[module]
        except KeyError:
            raise TrackerMissing(
                f"the overhead tracker has not reported module {module} (is `dh2rt tracker` running, "
                "and does the module carry its markers?)"
            ) from None

    def centre(self, module: int) -> tuple[float, float]:
        """The module's centre on the floor (m)."""
        c = self.pose(module).centre
        return c.x, c.y

    def heading(self, module: int) -> float:
        """The module's heading: its centre part's x axis (radians)."""
        return self.pose(module).centre.heading

    def part(self, module: int, link: int) -> PartPose:
        return self.pose(module).part(link)

    def face(self, model: ConroModel, module: int, connector: int | str) -> tuple[float, float, float, float]:
        """A connector face on the floor: its centre (x, y, m) and outward normal (nx, ny)."""
        spec = model.connector(connector) if isinstance(connector, int) else _named(model, connector)
        part = self.part(module, spec.link)
        c, s = math.cos(part.heading), math.sin(part.heading)
        px, py = spec.position[0], spec.position[1]
        nx, ny = spec.normal[0], spec.normal[1]
        return part.x + c * px - s * py, part.y + s * px + c * py, c * nx - s * ny, s * nx + c * ny


def _named(model: ConroModel, name: str) -> ConnectorSpec:
    for c in model.connectors:
        if c.name == name:
            return c
    raise KeyError(f"CONRO model has no connector {name!r}")


@dataclass(frozen=True)
class Readings:
    """One control cycle's readings for the motions (see the module docs)."""

    #: module -> (pos1, pos2), degrees
    joints: Mapping[int, tuple[float, float]] = field(default_factory=dict)
    #: module -> {``ir_<c>``: mm, ``ir_<c>_align``: degrees}
    infrared: Mapping[int, Mapping[str, float]] = field(default_factory=dict)
    #: the overhead tracker's last broadcast
    floor: FloorPoses = field(default_factory=FloorPoses)
    #: module -> (roll, pitch), degrees: its IMU (the ``roll``, ``pitch`` sensors)
    attitude: Mapping[int, tuple[float, float]] = field(default_factory=dict)
    #: ORACLE, for measuring only: (asking, target) -> the target face's part in the asking
    #: face's part frame as the simulator has it exactly (4x4). No module senses this; it
    #: is filled only when an owner is told to (``sim.runner.PhysicsRun.oracle_poses``), to
    #: measure what reading the chain by proprioception costs. Empty on a robot.
    oracle: Mapping[tuple[End, End], np.ndarray] = field(default_factory=dict)

    def joint(self, module: int, dof: int) -> float:
        """A module's joint angle (degrees); KeyError naming the module if it was not read."""
        try:
            return self.joints[module][dof]
        except KeyError:
            raise KeyError(f"no joint reading of module {module}") from None

    def ir(self, module: int, name: str) -> float:
        """A module's infrared reading ``name`` (``ir_<c>`` or ``ir_<c>_align``)."""
        try:
            return float(self.infrared[module][name])
        except KeyError:
            raise KeyError(f"no {name} reading of module {module}") from None
