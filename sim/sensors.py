"""Sensors of CONRO modules in the physics stand-in: IMU, infrared, ground contact, joints.

:class:`PhysicsSensors` reads from a :class:`sim.world.World` the sensors of the profile's
table (``dh2rt.profile.CONRO``, *Sensors* in docs/language.md) that physics can provide, as
floats in the table's units; whoever hands them to a module rounds and clamps them
(``SensorSpec.reading``). Only the sensors named at construction are computed, so a program
that reads none costs nothing, and one that reads only ``roll`` casts no ray.

* ``roll``, ``pitch``: an emulated IMU on the centre body (the module's base): the Z-Y-X
  Euler angles of its attitude, which are exactly the tilt a resting accelerometer measures
  (independent of heading). Roll is about the module's x axis (forward), positive when its
  left side is up; pitch about its y axis, positive when its front end is down (the sense
  of a positive DOF1). No noise, no drift.
* ``yaw``: the same IMU's heading as its gyro integrates it: how far the module has turned
  about the vertical since this object first read it (degrees, left > 0), unwrapped from
  one reading to the next (each step taken the shorter way round, so a module read at
  least every half turn counts whole turns). No drift either.
* ``ir_<c>`` and ``ir_<c>_align``: CONRO's infrared pairs, an emitter and a receiver on each
  docking face. Face C of a module sees face D of another module when their centres are at
  most :data:`IR_RANGE_M` apart, each lies within :data:`IR_CONE_DEG` of the other's outward
  normal (each emitter reaches the other receiver), and nothing stands between them: a ray
  cast from C towards D (all of a reading's rays in one ``rayTestBatch``) first meets D's
  own body part. Faces closer than :data:`IR_NEAR_M` (docked ones, which the dock's soft
  constraint lets part by a few millimetres and twist as the robot moves) see each other
  when their normals are opposed within the cone, whatever the direction between their
  centres: the LED and the receiver are spread over the face, and no module fits between.
  ``ir_<c>`` is the distance between the face centres of the nearest face C sees, in mm, at
  least 1 (faces flush read 1), and 0 when C sees none;
  ``ir_<c>_align`` the angle between C's normal and D's reversed normal, in degrees: 0 when
  the faces are square to each other, 180 when C sees none. Every face of every module in the
  world is a target, docked neighbours' included, but those of a module without power
  (``World.unpowered``, a killed one): its emitters are dark.
* ``contact``: 1 when any part of the module touched the ground plane in the last step.
* ``pos1``, ``pos2``: the joints' angles (degrees); ``load1``, ``load2``: the torque each
  joint motor applied in the last step, as a percentage of the servo's maximum torque
  (the model's limits), signed like the joint angle: one ``getJointStates`` per module.

:class:`ModuleSensors` is one module's share as a :class:`drivers.base.SensorSource`: what a
module's own IMU or infrared board would give its runtime, with the physics behind it.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterable, Sequence
from contextlib import AbstractContextManager
from typing import Any

import numpy as np
import pybullet as p

from dh2rt.errors import PhysicsWorldError
from drivers.base import SensorSource
from firmware.motion.body import CENTRE, ConroModel
from sim.world import World

#: How far a CONRO infrared pair reaches (face centre to face centre), metres.
IR_RANGE_M = 0.100
#: Half-angle of an infrared emitter's and receiver's cone, degrees.
IR_CONE_DEG = 30.0
#: Faces closer than this are as good as in contact (a docked pair in motion parts by up to
#: about 8 mm): the direction between their centres says nothing and nothing fits between
#: them, so they see each other when their normals are opposed within the cone.
IR_NEAR_M = 0.010
#: Rays start this far outside the emitting face and end this far inside the target body.
RAY_MARGIN_M = 0.001
#: ``ir_<c>_align`` when nothing is in view: no face is less square than that.
NOTHING_IN_VIEW_DEG = 180.0

IMU_SENSORS = ("roll", "pitch", "yaw")
CONTACT_SENSOR = "contact"
JOINT_SENSORS = ("pos1", "pos2", "load1", "load2")

Readings = dict[str, float]


def physics_sensor_names(model: ConroModel) -> tuple[str, ...]:
    """Every sensor the physics provides for modules built from ``model``."""
    ir = tuple(name for c in model.connectors for name in (f"ir_{c.name}", f"ir_{c.name}_align"))
    return (*IMU_SENSORS, *ir, CONTACT_SENSOR, *JOINT_SENSORS)


_YZX, _ZXY = [1, 2, 0], [2, 0, 1]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross products along the last axis (np.cross is several times slower on small arrays)."""
    out: np.ndarray = a[..., _YZX] * b[..., _ZXY] - a[..., _ZXY] * b[..., _YZX]
    return out


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectors ``v`` (..., 3) turned by unit quaternions ``q`` (..., 4, as x y z w)."""
    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * _cross(u, v)
    out: np.ndarray = v + w * t + _cross(u, t)
    return out


class PhysicsSensors:
    """The sensors ``names`` (those of them physics provides) of a World's modules.

    ``names`` may list anything, e.g. every sensor a program declares: :attr:`names` keeps
    those physics provides, in the table's order, and :meth:`read` computes only them.
    """

    def __init__(
        self,
        world: World,
        names: Iterable[str],
        *,
        ir_range_m: float = IR_RANGE_M,
        ir_cone_deg: float = IR_CONE_DEG,
    ) -> None:
        if not ir_range_m > 0 or not 0 < ir_cone_deg < 90:
            raise PhysicsWorldError(
                f"infrared range must be > 0 m and cone within 0..90 degrees, got {ir_range_m}, {ir_cone_deg}"
            )
        wanted = set(names)
        model = world.model
        self.world = world
        self.names: tuple[str, ...] = tuple(n for n in physics_sensor_names(model) if n in wanted)
        self._imu = any(n in wanted for n in IMU_SENSORS)
        #: Each module's heading (radians, unwrapped) at its first read and at its last.
        self._yaw_first: dict[int, float] = {}
        self._yaw_last: dict[int, float] = {}
        self._contact = CONTACT_SENSOR in wanted
        self._joints = any(n in wanted for n in JOINT_SENSORS)
        self._max_torque = tuple(lim.max_torque_nm for lim in model.limits)
        self._bodies = [world.body(m) for m in range(world.size)]
        self._joint_ids = [world.driver(m).joints for m in range(world.size)]
        self.ir_range_m = ir_range_m
        self._cos_cone = math.cos(math.radians(ir_cone_deg))
        # Connector geometry, in the order of model.connectors: the body part each sits on, the
        # parts that carry any (CONRO: front and back; only their poses are read), each one's
        # part among those, and its face centre and outward normal in its part's frame.
        self._links = [c.link for c in model.connectors]
        self._parts = sorted(set(self._links))
        self._slots = np.array([self._parts.index(link) for link in self._links])
        self._local = np.array([(c.position, c.normal) for c in model.connectors])  # (connectors, 2, 3)
        self._rows: tuple[tuple[int, ...], np.ndarray, np.ndarray, np.ndarray] | None = None
        #: (connector position in model.connectors, distance sensor, alignment sensor)
        self._emitters = [
            (i, f"ir_{c.name}", f"ir_{c.name}_align")
            for i, c in enumerate(model.connectors)
            if f"ir_{c.name}" in wanted or f"ir_{c.name}_align" in wanted
        ]
        self._nothing_in_view = {
            name: value for _, d, a in self._emitters for name, value in ((d, 0.0), (a, NOTHING_IN_VIEW_DEG))
        }

    def read(self, modules: Sequence[int]) -> dict[int, Readings]:
        """Each listed module's readings (name -> value in the table's unit)."""
        out: dict[int, Readings] = {m: {} for m in modules}
        if not self.names:
            return out
        if self._imu or self._joints:
            for m in modules:
                self._read_body(m, out[m])
        if self._contact:
            self._ground_contact(modules, out)
        if self._emitters and modules:
            self._infrared(modules, out)
        return out

    # -- one body at a time: IMU, joints; the ground's contacts all at once --

    def _read_body(self, module: int, into: Readings) -> None:
        cid = self.world.client
        body = self._bodies[module]
        if self._imu:
            orn = p.getBasePositionAndOrientation(body, physicsClientId=cid)[1]
            roll, pitch, yaw = p.getEulerFromQuaternion(orn, physicsClientId=cid)
            into["roll"], into["pitch"] = math.degrees(roll), math.degrees(pitch)
            last = self._yaw_last.get(module)
            if last is None:
                self._yaw_first[module] = last = yaw
            yaw = last + (yaw - last + math.pi) % (2 * math.pi) - math.pi  # the turn since the last read
            self._yaw_last[module] = yaw
            into["yaw"] = math.degrees(yaw - self._yaw_first[module])
        if self._joints:
            states = p.getJointStates(body, self._joint_ids[module], physicsClientId=cid)
            into["pos1"], into["pos2"] = math.degrees(states[0][0]), math.degrees(states[1][0])
            into["load1"] = 100.0 * states[0][3] / self._max_torque[0]
            into["load2"] = 100.0 * states[1][3] / self._max_torque[1]

    def _ground_contact(self, modules: Sequence[int], out: dict[int, Readings]) -> None:
        """One query for every contact with the ground (one per module costs three times as much)."""
        w = self.world
        points = p.getContactPoints(bodyA=w.ground, physicsClientId=w.client)
        touching = {point[2] for point in points}  # bodyUniqueIdB: the other body
        for m in modules:
            out[m][CONTACT_SENSOR] = 1.0 if self._bodies[m] in touching else 0.0

    # -- infrared --

    def connector_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Face centres and outward normals of every connector of every module, in world
        coordinates: two arrays (modules, connectors, 3)."""
        cid = self.world.client
        parts = self._parts
        links = [link for link in parts if link != CENTRE]
        pos: list[Any] = []
        orn: list[Any] = []
        for body in self._bodies:  # the poses of each module's parts, in _parts order
            if parts[0] == CENTRE:  # the base (-1) sorts first
                base = p.getBasePositionAndOrientation(body, physicsClientId=cid)
                pos.append(base[0])
                orn.append(base[1])
            if links:
                for state in p.getLinkStates(body, links, computeForwardKinematics=1, physicsClientId=cid):
                    pos.append(state[0])
                    orn.append(state[1])
        n, k = len(self._bodies), len(parts)
        slots = self._slots
        turned = _rotate(np.array(orn).reshape(n, k, 1, 4)[:, slots], self._local)  # (modules, connectors, 2, 3)
        return np.array(pos).reshape(n, k, 3)[:, slots] + turned[:, :, 0], turned[:, :, 1]

    def _infrared(self, modules: Sequence[int], out: dict[int, Readings]) -> None:
        faces, normals = self.connector_poses()
        k = faces.shape[1]
        targets, target_n = faces.reshape(-1, 3), normals.reshape(-1, 3)
        row_module, row_conn, other = self._row_layout(modules, len(targets), k)
        src, src_n = faces[row_module, row_conn], normals[row_module, row_conn]
        # pairs within range, on different modules: usually few, so the cones are tested on them
        # only (squared distances as |s|^2 + |t|^2 - 2 s.t: one matrix product, no (rows,
        # targets, 3) array; its rounding moves the range's edge by far less than a micrometre)
        sq = np.einsum("tj,tj->t", targets, targets)
        dist2 = sq[row_module * k + row_conn][:, None] + sq[None, :] - 2.0 * (src @ targets.T)
        rows, cols = np.nonzero(other & (dist2 <= self.ir_range_m**2))
        if self.world.unpowered:  # a module without power emits nothing: its faces are dark
            lit = ~np.isin(cols // k, sorted(self.world.unpowered))
            rows, cols = rows[lit], cols[lit]
        d, e_n, t_n = targets[cols] - src[rows], src_n[rows], target_n[cols]
        dist = np.sqrt(np.einsum("pj,pj->p", d, d))
        reach = self._cos_cone * dist  # within the cone: cos(angle) * dist >= cos(cone) * dist
        opposed = -np.einsum("pj,pj->p", e_n, t_n)
        in_cones = (np.einsum("pj,pj->p", e_n, d) >= reach) & (-np.einsum("pj,pj->p", t_n, d) >= reach)
        near = dist <= IR_NEAR_M
        seen = np.where(near, opposed >= self._cos_cone, in_cones)
        columns = (rows[seen], cols[seen], dist[seen], near[seen], opposed[seen])
        pairs: list[tuple[int, int, float, bool, float]] = list(zip(*(c.tolist() for c in columns), strict=True))
        found = self._nearest_in_sight(pairs, src, src_n, targets, target_n, k)
        for m in modules:
            out[m].update(self._nothing_in_view)
        per_row = len(self._emitters)
        for row, (distance, cos) in found.items():
            _, dist_name, align_name = self._emitters[row % per_row]
            readings = out[modules[row // per_row]]
            readings[dist_name] = max(1.0, distance * 1000.0)
            readings[align_name] = math.degrees(math.acos(max(-1.0, min(1.0, cos))))

    def _row_layout(self, modules: Sequence[int], targets: int, per_module: int) -> tuple[np.ndarray, ...]:
        """One row per (listed module, emitter), modules in the order listed: each row's
        module and connector, and which targets are on another module (kept for the next
        reading of the same modules)."""
        key = tuple(modules)
        if self._rows is None or self._rows[0] != key:
            row_module = np.repeat(np.asarray(key), len(self._emitters))
            row_conn = np.tile([i for i, _, _ in self._emitters], len(key))
            other = (np.arange(targets) // per_module)[None, :] != row_module[:, None]
            self._rows = (key, row_module, row_conn, other)
        return self._rows[1:]

    def _nearest_in_sight(
        self,
        pairs: list[tuple[int, int, float, bool, float]],
        src: np.ndarray,
        src_n: np.ndarray,
        targets: np.ndarray,
        target_n: np.ndarray,
        per_module: int,
    ) -> dict[int, tuple[float, float]]:
        """For each emitter row with faces in view (``pairs``: row, target, distance, near
        or not, cosine of the faces' angle off square), the nearest in clear line of sight,
        as (distance, cosine); one ray batch for every candidate not near."""
        by_row: dict[int, list[tuple[int, int, float, bool, float]]] = {}
        for pair in sorted(pairs, key=lambda q: q[2]):
            by_row.setdefault(pair[0], []).append(pair)
        rays: list[tuple[int, int]] = []
        for row, candidates in by_row.items():
            if candidates[0][3]:
                by_row[row] = candidates[:1]  # nothing can come between faces this near
            else:
                rays.extend((row, t) for _, t, _, _, _ in candidates)
        clear = self._line_of_sight(rays, src, src_n, targets, target_n, per_module)
        found: dict[int, tuple[float, float]] = {}
        for row, candidates in by_row.items():
            for _, t, d, near, cos in candidates:
                if near or clear[(row, t)]:
                    found[row] = (d, cos)
                    break
        return found

    def _line_of_sight(
        self,
        rays: list[tuple[int, int]],
        src: np.ndarray,
        src_n: np.ndarray,
        targets: np.ndarray,
        target_n: np.ndarray,
        per_module: int,
    ) -> dict[tuple[int, int], bool]:
        """Whether each (emitter row, target) ray first meets the target face's own body part
        (or nothing at all)."""
        if not rays:
            return {}
        starts = [tuple(src[r] + RAY_MARGIN_M * src_n[r]) for r, _ in rays]
        ends = [tuple(targets[t] - RAY_MARGIN_M * target_n[t]) for _, t in rays]
        hits: list[Any] = p.rayTestBatch(starts, ends, physicsClientId=self.world.client)
        clear: dict[tuple[int, int], bool] = {}
        for (row, t), hit in zip(rays, hits, strict=True):
            module, conn = divmod(t, per_module)
            body, link = hit[0], hit[1]
            clear[(row, t)] = body == -1 or (body == self._bodies[module] and link == self._links[conn])
        return clear


class ModuleSensors(SensorSource):
    """One module's physics sensors as a :class:`drivers.base.SensorSource`.

    ``lock``, when given, is held around each reading (PyBullet is not thread-safe: the loop's
    physics stand-in steps the world under a lock while its servo emulators read joints).
    """

    def __init__(self, sensors: PhysicsSensors, module: int, lock: AbstractContextManager[Any] | None = None) -> None:
        self.sensors = sensors
        self.module = module
        self._lock: AbstractContextManager[Any] = lock if lock is not None else contextlib.nullcontext()

    @property
    def names(self) -> tuple[str, ...]:
        return self.sensors.names

    def read(self) -> dict[str, float]:
        with self._lock:
            return self.sensors.read([self.module])[self.module]
