"""The docking motions' readings, from physics: what each module's sensors would give it.

:class:`MotionSensors` gathers a :class:`firmware.motion.readings.Readings` for the motions
under way from a :class:`sim.world.World`: the joint angles of the modules named (``pos1``,
``pos2``, as :class:`sim.sensors.PhysicsSensors` reads them), the infrared pairs of the
modules named (``ir_<c>``, ``ir_<c>_align``, every connector's), and the overhead tracker's
reading (:class:`sim.tracker.OverheadTracker`). Nothing else of the world reaches a motion.

:func:`contact` is the trace's record of a latch or a give-up: both faces' world poses and
errors at that moment, read from the world by the owner (never by the motion);
:class:`Verdicts` keeps them, for each motion the docking sequence ended.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from dh2rt.docking import End
from firmware.motion.floor_filter import FloorFilter
from firmware.motion.readings import FloorPoses, Readings
from firmware.motion.underway import Motion
from sim.sensors import PhysicsSensors
from sim.tracker import FloorTracker, OverheadTracker
from sim.world import World

#: ``name.connector`` of a module's connector, for log lines.
Where = Callable[[int, int], str]


class MotionSensors:
    """The sensors the docking motions read in ``world``, with ``tracker`` over the arena."""

    def __init__(
        self, world: World, tracker: FloorTracker | None = None, floor_filter: FloorFilter | None = None
    ) -> None:
        self.world = world
        self.tracker: FloorTracker = tracker or OverheadTracker(world)
        #: what the modules' firmware smooths the tracker's reports with (None: raw reports)
        self.floor_filter = floor_filter
        model = world.model
        self.ir = PhysicsSensors(world, [f"ir_{c.name}{s}" for c in model.connectors for s in ("", "_align")])
        self.imu = PhysicsSensors(world, ["roll", "pitch"])

    def read(
        self,
        cycle: int,
        joints: Iterable[int] = (),
        infrared: Iterable[int] = (),
        *,
        floor: bool,
        oracle: Iterable[tuple[End, End]] = (),
        attitude: Iterable[int] = (),
    ) -> Readings:
        """This cycle's readings: the joint angles of ``joints``, the infrared pairs of
        ``infrared``, and (with ``floor``) the tracker's poses. ``oracle`` (measuring only,
        :attr:`firmware.motion.readings.Readings.oracle`): the face pairs whose exact relative
        pose the world adds; ``attitude``: the modules whose IMU (roll, pitch) is read."""
        angles = {m: self.world.joint_angles(m) for m in set(joints)}
        wanted = sorted(set(infrared))
        ir = dict(self.ir.read(wanted)) if wanted else {}
        poses = self.tracker.reading(cycle) if floor else FloorPoses()
        if floor and self.floor_filter is not None:
            poses = self.floor_filter.update(cycle, poses)
        exact = {pair: self._exact(*pair) for pair in oracle}
        tilted = sorted(set(attitude))
        imu = {m: (r["roll"], r["pitch"]) for m, r in self.imu.read(tilted).items()} if tilted else {}
        return Readings(angles, ir, poses, attitude=imu, oracle=exact)

    def _exact(self, asking: End, target: End) -> np.ndarray:
        """The target face's part in the asking face's part frame, from the world (an oracle)."""
        model = self.world.model
        a = self.world.part_transform(asking[0], model.connector(asking[1]).link)
        b = self.world.part_transform(target[0], model.connector(target[1]).link)
        out: np.ndarray = np.linalg.solve(a, b)
        return out


@dataclass(frozen=True, slots=True)
class Contact:
    """Where the two faces were when a latch closed (or a reach gave up): world poses and
    errors, for the trace."""

    cycle: int
    asking: End
    target: End
    asking_face: tuple[float, float, float]
    target_face: tuple[float, float, float]
    asking_normal: tuple[float, float, float]
    target_normal: tuple[float, float, float]
    distance_m: float
    attitude_deg: float
    ir_mm: float
    ir_align_deg: float

    def as_dict(self) -> dict[str, object]:
        return {
            "cycle": self.cycle,
            "asking": list(self.asking),
            "target": list(self.target),
            "asking_face": [round(v, 5) for v in self.asking_face],
            "target_face": [round(v, 5) for v in self.target_face],
            "asking_normal": [round(v, 4) for v in self.asking_normal],
            "target_normal": [round(v, 4) for v in self.target_normal],
            "distance_mm": round(self.distance_m * 1000, 2),
            "attitude_deg": round(self.attitude_deg, 2),
            "ir_mm": round(self.ir_mm, 1),
            "ir_align_deg": round(self.ir_align_deg, 1),
        }


def contact(world: World, cycle: int, asking: End, target: End, infrared: tuple[float, float]) -> Contact:
    """The trace's record of two faces at ``cycle``, with the asking face's infrared reading."""
    (a, ac), (b, bc) = asking, target
    pa, na = world.connector_pose(a, ac)
    pb, nb = world.connector_pose(b, bc)
    return Contact(
        cycle,
        (a, ac),
        (b, bc),
        pa,
        pb,
        na,
        nb,
        math.dist(pa, pb),
        world.attitude_error_deg(a, ac, b, bc),
        infrared[0],
        infrared[1],
    )


@dataclass
class Verdicts:
    """How each docking motion ended, read from the world by its owner: every link formed
    (:attr:`contacts`) and every motion that gave up (:attr:`failed`), each a :class:`Contact`."""

    contacts: list[Contact] = field(default_factory=list)
    failed: list[Contact] = field(default_factory=list)

    def record(
        self, world: World, cycle: int, motion: Motion, linked: bool, readings: Readings, where: Where, took: str
    ) -> str:
        """Record how ``motion`` ended at ``cycle`` (``readings``: its last cycle's); the log
        line, which says how long it ``took`` and where the faces were."""
        reach = motion.reach
        (a, ac), (b, bc) = reach.chain.asking, reach.chain.target
        record = contact(world, cycle, (a, ac), (b, bc), reach.infrared(readings))
        how = (
            f"{record.distance_m * 1000:.1f} mm, {record.attitude_deg:.1f} deg apart; infrared "
            f"{record.ir_mm:.1f} mm, {record.ir_align_deg:.1f} deg"
        )
        if linked:
            self.contacts.append(record)
            return f"{where(a, ac)} docked to {where(b, bc)} by motion after {took} ({how})"
        self.failed.append(record)
        return f"reach_dock {motion.where} gave up after {took} ({how})"
