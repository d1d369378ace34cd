"""The CONRO module's body as data: three boxes, two hinges, four connector faces, two servos.

One description of the body that both sides build from: the simulator's PyBullet model
(:func:`sim.conro.build_module`) and the firmware's own kinematics (:mod:`firmware.motion.kinematics`),
so the two cannot disagree about where a face is. Numbers and their sources: sim/conro.py's
module docs (the ISI CONRO prototype's 25.4 mm passive connector cube; the rest assumed).

Module frame: x points forward (out of the front connector), z up, y to the module's left.
DOF1 (pitch, about y) hinges the front body to the centre at their shared face; DOF2 (yaw,
about z) hinges the back body to the centre. Positive DOF1 turns the front body's tip down;
positive DOF2 turns the back body counter-clockwise seen from above.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from drivers.base import JointLimits

#: Link indices of the three bodies in the PyBullet multibody.
CENTRE = -1  # the base
FRONT = 0
BACK = 1

Vec3 = tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class BoxSpec:
    """One rigid body of the module: size (metres, full extents) and mass (kg)."""

    name: str
    size: Vec3
    mass: float

    @property
    def half(self) -> Vec3:
        return (self.size[0] / 2, self.size[1] / 2, self.size[2] / 2)


@dataclass(frozen=True, slots=True)
class ConnectorSpec:
    """A docking face: profile index, gender, the body it sits on, and its frame.

    ``position`` is the face centre and ``normal`` the outward unit normal, both in the
    frame of the body's centre of mass (which is the box centre).
    """

    name: str
    index: int
    gender: str
    link: int
    position: Vec3
    normal: Vec3


@dataclass(frozen=True, slots=True)
class Friction:
    """Contact friction of every body (PyBullet ``changeDynamics`` terms)."""

    lateral: float = 0.9
    spinning: float = 0.002
    rolling: float = 0.0005
    #: Anisotropic scaling of lateral friction along the body's x, y, z axes (1 = isotropic).
    anisotropic: Vec3 = (1.0, 1.0, 1.0)
    restitution: float = 0.0


def _default_connectors(front: BoxSpec, back: BoxSpec) -> tuple[ConnectorSpec, ...]:
    fx = front.half[0]
    bx, by = back.half[0], back.half[1]
    return (
        ConnectorSpec("front", 1, "female", FRONT, (fx, 0.0, 0.0), (1.0, 0.0, 0.0)),
        ConnectorSpec("back", 2, "male", BACK, (-bx, 0.0, 0.0), (-1.0, 0.0, 0.0)),
        ConnectorSpec("left", 3, "male", BACK, (0.0, by, 0.0), (0.0, 1.0, 0.0)),
        ConnectorSpec("right", 4, "male", BACK, (0.0, -by, 0.0), (0.0, -1.0, 0.0)),
    )


#: The passive connector's body is "a 1 x 1 inch cube" (ISI, second CONRO prototype hardware).
CROSS_SECTION_M = 0.0254
_FRONT = BoxSpec("front", (0.035, CROSS_SECTION_M, CROSS_SECTION_M), 0.030)
_CENTRE = BoxSpec("centre", (0.045, CROSS_SECTION_M, CROSS_SECTION_M), 0.055)
_BACK = BoxSpec("back", (CROSS_SECTION_M, CROSS_SECTION_M, CROSS_SECTION_M), 0.030)
_SERVO = JointLimits(min_deg=-90.0, max_deg=90.0, max_speed_dps=400.0, max_torque_nm=0.3)


@dataclass(frozen=True)
class ConroModel:
    """Everything the simulator needs to build one module. Defaults: see the module docs."""

    front: BoxSpec = _FRONT
    centre: BoxSpec = _CENTRE
    back: BoxSpec = _BACK
    dof1: JointLimits = _SERVO
    dof2: JointLimits = _SERVO
    friction: Friction = field(default_factory=Friction)
    connectors: tuple[ConnectorSpec, ...] = _default_connectors(_FRONT, _BACK)
    colors: tuple[tuple[float, float, float, float], ...] = (
        (0.85, 0.35, 0.2, 1.0),
        (0.25, 0.45, 0.8, 1.0),
        (0.3, 0.3, 0.3, 1.0),
    )

    def __post_init__(self) -> None:
        for c in self.connectors:
            if abs(c.normal[2]) > 1e-9 or abs(math.hypot(c.normal[0], c.normal[1]) - 1.0) > 1e-9:
                # Placement and docking pose children by a yaw about z; that needs flat normals.
                raise ValueError(f"connector {c.name}: normal {c.normal} must be a horizontal unit vector")

    @property
    def limits(self) -> tuple[JointLimits, JointLimits]:
        return (self.dof1, self.dof2)

    @property
    def mass(self) -> float:
        return self.front.mass + self.centre.mass + self.back.mass

    @property
    def length(self) -> float:
        return self.front.size[0] + self.centre.size[0] + self.back.size[0]

    @property
    def height(self) -> float:
        return max(self.front.size[2], self.centre.size[2], self.back.size[2])

    def connector(self, index: int) -> ConnectorSpec:
        """The connector with profile index ``index`` (1-based)."""
        for c in self.connectors:
            if c.index == index:
                return c
        raise KeyError(f"CONRO model has no connector index {index}")

    def body(self, link: int) -> BoxSpec:
        return {CENTRE: self.centre, FRONT: self.front, BACK: self.back}[link]


DEFAULT_MODEL = ConroModel()
