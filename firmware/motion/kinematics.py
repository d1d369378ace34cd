"""The chain's forward kinematics, from the body's description and the chain's joint angles.

A dock request names the asking connector (a free face of one module) and a target (a free
face of a module the route leads to, through docked links). The modules between them form a
kinematic chain: every pitch (DOF1) and yaw (DOF2) joint the route passes through. The chain
is known from the robot's own geometry (:mod:`firmware.motion.body`: the three boxes, the
hinges, the connector faces; a docked pair's faces coincide, normals opposite) and its joint
angles, which each module measures itself (``pos1``, ``pos2``): where the target face is
relative to the asking face follows from proprioception alone.

:class:`Chain` is that forward kinematics in numpy (4x4 transforms), with a numerical
Jacobian; :func:`solve` is damped least squares over the chain's joints within their limits,
pitch joints held near 0 (the robot lies on the floor; yaws do the bending when they can);
:func:`plan` tries a few starting curls; :func:`dls_step` is one correction step.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from dh2rt.docking import End
from firmware.motion.body import BACK, CENTRE, FRONT, ConroModel

#: Joint targets are kept this far inside the servo range (degrees).
LIMIT_MARGIN_DEG = 5.0
#: How many metres one radian of attitude error counts as in the least squares. At 0.05 a
#: chain of two yaws (which cannot place and square a face at once) traded attitude for
#: position and drifted onto another branch: 1 of 40 layouts stalled, none at 0.1
#: (tests/sim/test_docking_sweep.py's layouts, seed 7).
ROT_WEIGHT_M = 0.1

Joint = tuple[int, int]  # (module, dof index 0 = DOF1 pitch, 1 = DOF2 yaw)


def _tx(x: float, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    t = np.eye(4)
    t[:3, 3] = (x, y, z)
    return t


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    t = np.eye(4)
    t[0, 0], t[0, 1], t[1, 0], t[1, 1] = c, -s, s, c
    return t


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    t = np.eye(4)
    t[0, 0], t[0, 2], t[2, 0], t[2, 2] = c, s, -s, c
    return t


def _log_rot(r: np.ndarray) -> np.ndarray:
    """The rotation vector (axis times angle) of a 3x3 rotation matrix."""
    cos = max(-1.0, min(1.0, (float(np.trace(r)) - 1.0) / 2.0))
    angle = math.acos(cos)
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if angle < 1e-9:
        return 0.5 * v
    s = math.sin(angle)
    if s < 1e-6:  # near 180 degrees: the axis from the symmetric part
        axis = np.sqrt(np.maximum((np.diag(r) + 1.0) / 2.0, 0.0))
        return np.asarray(axis * angle)
    return np.asarray(v * (angle / (2.0 * s)))


def mated_turn(model: ConroModel, a_conn: int, b_conn: int) -> float:
    """The yaw (radians) from a's part to b's part when a.a_conn and b.b_conn are mated."""
    na, nb = model.connector(a_conn).normal, model.connector(b_conn).normal
    return math.atan2(na[1], na[0]) + math.pi - math.atan2(nb[1], nb[0])


# A step of the chain: a constant transform, or a joint (module, dof) with how it enters.
@dataclass(frozen=True, slots=True)
class _Step:
    const: np.ndarray | None = None
    joint: Joint | None = None
    axis: str = ""  # "y" or "z"
    sign: float = 1.0


@dataclass
class Chain:
    """The forward kinematics from an asking face to a target face along a route.

    Frames are the parts' centre-of-mass frames (:mod:`firmware.motion.body`: box centres). Everything is
    relative to the asking connector's part, so the chain needs no world pose at all.
    """

    model: ConroModel
    asking: End
    target: End
    steps: list[_Step] = field(default_factory=list)
    joints: list[Joint] = field(default_factory=list)
    #: For a target on another robot (no route to it): the module whose part the chain ends
    #: at, and that part; the owner measures :attr:`beyond`, the target part in that frame.
    anchor: tuple[int, int] | None = None
    beyond: np.ndarray = field(default_factory=lambda: np.eye(4))
    #: The distance along the asking face's normal is not the chain's to close: the target
    #: creeps towards the face itself (:class:`firmware.motion.crawl.Creep`), and :meth:`error_of` counts
    #: only how far the target is off the face's axis and how far off square. A chain lying
    #: straight cannot lengthen: asked to put its face 3 cm (:data:`STANDOFF_M`) in front of
    #: a foot parked 4 to 6 cm behind, two tail modules that were feet docked a little askew
    #: swung their yaws to the limits (+85 and -85 degrees) and turned the face away from the
    #: foot; 3 of the 4 legs to snake runs in 25 that did not form ended so (docs/physics.md).
    free_distance: bool = False

    @classmethod
    def to_other(
        cls,
        model: ConroModel,
        asking: End,
        route: Sequence[int],
        peer_of: Callable[[End], End | None],
        target: End,
        *,
        free_distance: bool = False,
    ) -> Chain:
        """The chain of ``asking``'s own robot along ``route`` (the joints that move the asking
        face), aimed at ``target`` on a body the route does not reach: the chain ends at the
        part of the last module that the route enters, and :attr:`beyond` must be set to the
        target part's pose in that part's frame before each use. With ``free_distance`` the
        target closes the distance itself (:attr:`free_distance`)."""
        chain = cls(model, asking, target, free_distance=free_distance)
        chain.anchor = chain._follow(model, asking, route, peer_of)
        return chain

    @classmethod
    def to_own_centre(cls, model: ConroModel, asking: End) -> Chain:
        """The asking module's own centre part, seen from its asking face's part: no dock on
        the way, only the module's own joint (if the face is not on the centre)."""
        chain = cls(model, asking, asking)
        chain._inside(asking[0], model.connector(asking[1]).link, CENTRE)
        return chain

    @classmethod
    def along(
        cls,
        model: ConroModel,
        asking: End,
        route: Sequence[int],
        peer_of: Callable[[End], End | None],
        target_conn: int,
    ) -> Chain:
        """The chain from ``asking`` (module, connector) along ``route`` (the connector to
        leave through at each hop) to connector ``target_conn`` of the module it leads to."""
        chain = cls(model, asking, asking)
        module, entry = chain._follow(model, asking, route, peer_of)
        chain._inside(module, entry, model.connector(target_conn).link)
        chain.target = (module, target_conn)
        return chain

    def _follow(
        self, model: ConroModel, asking: End, route: Sequence[int], peer_of: Callable[[End], End | None]
    ) -> tuple[int, int]:
        """Add the steps from ``asking`` (module, connector) along ``route`` (the connector to
        leave through at each hop); the module the route leads to and the part it enters."""
        module, conn = asking
        entry = model.connector(conn).link
        for c in route:
            self._inside(module, entry, model.connector(c).link)
            peer = peer_of((module, c))
            if peer is None:
                raise ValueError(f"route leaves module {module} through connector {c}, which has no link")
            self._across(c, peer[1])
            module, entry = peer[0], model.connector(peer[1]).link
        return module, entry

    def _inside(self, module: int, entry: int, leave: int) -> None:
        """Steps from part ``entry`` to part ``leave`` of one module (through the centre)."""
        m = self.model
        cx, fx, bx = m.centre.half[0], m.front.half[0], m.back.half[0]
        if entry == leave:
            return
        if entry == FRONT:  # front -> centre: undo T(cx) Ry(q1) T(fx)
            self._const(_tx(-fx))
            self._joint((module, 0), "y", -1.0)
            self._const(_tx(-cx))
        elif entry == BACK:  # back -> centre: undo T(-cx) Rz(q2) T(-bx)
            self._const(_tx(bx))
            self._joint((module, 1), "z", -1.0)
            self._const(_tx(cx))
        if leave == FRONT:
            self._const(_tx(cx))
            self._joint((module, 0), "y", 1.0)
            self._const(_tx(fx))
        elif leave == BACK:
            self._const(_tx(-cx))
            self._joint((module, 1), "z", 1.0)
            self._const(_tx(-bx))
        elif leave != CENTRE:
            raise ValueError(f"unknown part {leave}")

    def _across(self, a_conn: int, b_conn: int) -> None:
        """From the part holding a_conn to the mated part holding b_conn."""
        pa = np.array(self.model.connector(a_conn).position)
        pb = np.array(self.model.connector(b_conn).position)
        turn = _rz(mated_turn(self.model, a_conn, b_conn))
        t = turn.copy()
        t[:3, 3] = pa - turn[:3, :3] @ pb
        self._const(t)

    def _const(self, t: np.ndarray) -> None:
        self.steps.append(_Step(const=t))

    def _joint(self, joint: Joint, axis: str, sign: float) -> None:
        if joint not in self.joints:
            self.joints.append(joint)
        self.steps.append(_Step(joint=joint, axis=axis, sign=sign))

    def limits_rad(self) -> np.ndarray:
        """Each joint's range (radians, symmetric), :data:`LIMIT_MARGIN_DEG` inside the servo's."""
        lims = [self.model.limits[dof] for _m, dof in self.joints]
        return np.array([math.radians(min(-lim.min_deg, lim.max_deg) - LIMIT_MARGIN_DEG) for lim in lims])

    # -- kinematics --

    def target_part(self, q: np.ndarray) -> np.ndarray:
        """The target connector's part, in the asking connector's part frame, at angles ``q``
        (radians, in :attr:`joints` order)."""
        index = {j: i for i, j in enumerate(self.joints)}
        t = np.eye(4)
        for s in self.steps:
            if s.const is not None:
                t = t @ s.const
            else:
                assert s.joint is not None
                a = s.sign * float(q[index[s.joint]])
                t = t @ (_ry(a) if s.axis == "y" else _rz(a))
        return t @ self.beyond if self.anchor is not None else t

    def error(self, q: np.ndarray, standoff: float = 0.0) -> np.ndarray:
        """6-vector: where the target face is less where it should be (metres), and the
        attitude error as a rotation vector scaled by :data:`ROT_WEIGHT_M`. The target face
        should sit ``standoff`` in front of the asking face, square to it."""
        return self.error_of(self.target_part(q), standoff)

    def error_of(self, t: np.ndarray, standoff: float = 0.0) -> np.ndarray:
        """:meth:`error` for the target part at ``t`` (in the asking part's frame)."""
        a = self.model.connector(self.asking[1])
        b = self.model.connector(self.target[1])
        face = t[:3, :3] @ np.array(b.position) + t[:3, 3]
        wanted = np.array(a.position) + standoff * np.array(a.normal)
        turn = _rz(mated_turn(self.model, self.asking[1], self.target[1]))[:3, :3]
        rot = _log_rot(t[:3, :3] @ turn.T)
        off = face - wanted
        if self.free_distance:
            normal = np.array(a.normal)
            off = off - float(off @ normal) * normal
        return np.concatenate([off, ROT_WEIGHT_M * rot])

    def jacobian(self, q: np.ndarray, standoff: float = 0.0, h: float = 1e-5) -> np.ndarray:
        e0 = self.error(q, standoff)
        jac = np.empty((6, len(q)))
        for i in range(len(q)):
            dq = q.copy()
            dq[i] += h
            jac[:, i] = (self.error(dq, standoff) - e0) / h
        return jac


def dls_step(
    chain: Chain, q: np.ndarray, e: np.ndarray, standoff: float, damping: float, pitch_weight: float
) -> np.ndarray:
    """One damped least squares step that lowers error ``e`` at angles ``q``, pitch joints
    pulled towards 0 with ``pitch_weight``."""
    pitches = np.array([1.0 if dof == 0 else 0.0 for _, dof in chain.joints])
    jac = chain.jacobian(q, standoff)
    rows = np.vstack([jac, math.sqrt(pitch_weight) * np.diag(pitches)])
    rhs = np.concatenate([-e, -math.sqrt(pitch_weight) * pitches * q])
    lhs = rows.T @ rows + damping**2 * np.eye(len(q))
    out: np.ndarray = np.linalg.solve(lhs, rows.T @ rhs)
    return out


def solve(
    chain: Chain,
    q0: np.ndarray,
    limits_rad: np.ndarray,
    standoff: float = 0.0,
    iterations: int = 60,
    damping: float = 0.01,
    pitch_weight: float = 0.02,
) -> np.ndarray:
    """Joint angles (radians) near ``q0`` that put the target face ``standoff`` in front of the
    asking face, square, within ``limits_rad`` (per joint, symmetric); pitch joints are pulled
    towards 0 with ``pitch_weight`` (the chain lies on the floor)."""
    q = q0.copy()
    pitches = np.array([1.0 if dof == 0 else 0.0 for _, dof in chain.joints])
    for _ in range(iterations):
        e = chain.error(q, standoff)
        if float(np.linalg.norm(e)) < 1e-5:
            break
        jac = chain.jacobian(q, standoff)
        # damped least squares with a penalty on pitch: rows for sqrt(w) * q_pitch -> 0
        rows = np.vstack([jac, math.sqrt(pitch_weight) * np.diag(pitches)])
        rhs = np.concatenate([-e, -math.sqrt(pitch_weight) * pitches * q])
        lhs = rows.T @ rows + damping**2 * np.eye(len(q))
        dq = np.linalg.solve(lhs, rows.T @ rhs)
        step = float(np.max(np.abs(dq)))
        if step > 0.3:
            dq *= 0.3 / step
        q = np.clip(q + dq, -limits_rad, limits_rad)
    return q


def plan(chain: Chain, q0: np.ndarray, limits_rad: np.ndarray, standoff: float) -> np.ndarray:
    """A configuration that closes the chain: :func:`solve` from the present angles and from
    uniform curls either way round, the one with the smallest remaining error."""
    yaws = np.array([1.0 if dof == 1 else 0.0 for _, dof in chain.joints])
    best, best_err = q0, math.inf
    for curl in (0.0, 0.8, -0.8, 0.4, -0.4, 1.2, -1.2):
        start = q0 if curl == 0.0 else curl * yaws
        q = solve(chain, start, limits_rad, standoff)
        err = float(np.linalg.norm(chain.error(q, standoff)))
        if err < best_err:
            best, best_err = q, err
    return best
