"""A PyBullet model of one CONRO module.

Shape, after the paper's Section 6 (Krivokon, Will, Shen: "a module is composed of three
rectangular bodies joint by two actuators with pitch and yaw DOFs"): a *front* body that
carries the female connector, a *centre* body (the module's base: processor and batteries)
and a *back* body that carries the three male connectors. DOF1 (pitch, about the module's
y axis) hinges the front body to the centre; DOF2 (yaw, about z) hinges the back body to
the centre. Each joint frame sits on its hinge, at the shared face of the two boxes.

Module frame: x points forward (out of the front connector), z up, y to the module's left.
Positive DOF1 turns the front body's tip down (right-hand rule about +y); positive DOF2
turns the back body towards the module's left... seen from above, counter-clockwise.

Sources
-------
* Krivokon, Will, Shen, the DH2 paper (the project's specification), Section 6: three
  boxes, pitch and yaw, masses and servo force/speed "from measurements and documentation",
  ODE with a pyramid friction model, contact slip in both directions, friction direction kept
  in the module's frame. The paper publishes none of the numbers.
* Castano, Behar, Will, "The Conro Modules for Reconfigurable Robots", IEEE/ASME Trans.
  Mechatronics 7(4):403-409, 2002: self-contained modules, pitch and yaw servos, one female
  and three male docking connectors, palm-sized. Its figures were not available to this
  build as text.
* USC/ISI, "Second CONRO prototype (HARDWARE)", www.isi.edu/robots/conro/proto2H.html: the
  module has three parts, a passive connector (pins and an infrared pair on three faces; its
  body "a 1"x1" cube" that also holds the battery), a motor housing for the two servos, and
  an active connector (an arm on the pitch motor and the face with the latch). **Published
  figure used: the passive connector (the back body, with the three male faces) is a
  25.4 mm cube, and the module's cross-section is taken from it.**

Assumptions (every other number here)
-------------------------------------
* All bodies share the 25.4 mm cross-section; lengths 35 mm (front: active connector and
  arm), 45 mm (centre: motor housing), 25.4 mm (back): a 105.4 mm module.
* Mass 115 g: 30 g front, 55 g centre (batteries, processor), 30 g back.
* Servos: hobby micro servos of the kind CONRO used, 0.3 N*m stall torque and
  about 0.15 s per 60 deg (400 deg/s); joint range -90..+90 deg.
* Friction: rubber-ish feet on a hard floor, lateral coefficient 0.9, small spinning and
  rolling terms that damp pivoting; see docs/physics.md for the gap to the paper's model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

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


@dataclass(frozen=True, slots=True)
class ModuleBody:
    """A module built in one physics client: its body id and joint indices (DOF1, DOF2)."""

    client: int
    body: int
    joints: tuple[int, int] = (0, 1)


def build_module(
    p: Any,
    client: int,
    model: ConroModel,
    position: Vec3,
    orientation: tuple[float, float, float, float],
) -> ModuleBody:
    """Create one module as a ``createMultiBody`` of three boxes in ``client``.

    ``p`` is the imported ``pybullet`` module. The base is the centre body; link 0 is the
    front body on DOF1 (pitch), link 1 the back body on DOF2 (yaw). Link frames sit on the
    hinges; collision and inertial frames are offset to the box centres.
    """
    shapes = {}
    visuals = {}
    for link, color in zip((CENTRE, FRONT, BACK), model.colors, strict=True):
        box = model.body(link)
        # Shapes are placed relative to the link frame (the hinge), so shift them to the box.
        offset = (0.0, 0.0, 0.0) if link == CENTRE else (box.half[0] if link == FRONT else -box.half[0], 0.0, 0.0)
        shapes[link] = p.createCollisionShape(
            p.GEOM_BOX, halfExtents=box.half, collisionFramePosition=offset, physicsClientId=client
        )
        visuals[link] = p.createVisualShape(
            p.GEOM_BOX,
            halfExtents=box.half,
            visualFramePosition=offset,
            rgbaColor=color,
            physicsClientId=client,
        )
    cx = model.centre.half[0]
    fx = model.front.half[0]
    bx = model.back.half[0]
    body = p.createMultiBody(
        baseMass=model.centre.mass,
        baseCollisionShapeIndex=shapes[CENTRE],
        baseVisualShapeIndex=visuals[CENTRE],
        basePosition=position,
        baseOrientation=orientation,
        linkMasses=[model.front.mass, model.back.mass],
        linkCollisionShapeIndices=[shapes[FRONT], shapes[BACK]],
        linkVisualShapeIndices=[visuals[FRONT], visuals[BACK]],
        # Hinges at the shared faces: the joint pivots at the link frame's origin.
        linkPositions=[(cx, 0.0, 0.0), (-cx, 0.0, 0.0)],
        linkOrientations=[(0.0, 0.0, 0.0, 1.0)] * 2,
        linkInertialFramePositions=[(fx, 0.0, 0.0), (-bx, 0.0, 0.0)],
        linkInertialFrameOrientations=[(0.0, 0.0, 0.0, 1.0)] * 2,
        linkParentIndices=[0, 0],
        linkJointTypes=[p.JOINT_REVOLUTE, p.JOINT_REVOLUTE],
        linkJointAxis=[(0.0, 1.0, 0.0), (0.0, 0.0, 1.0)],
        physicsClientId=client,
    )
    # createMultiBody ignores joint limits; changeDynamics sets them (in radians).
    for joint, lim in zip((0, 1), model.limits, strict=True):
        p.changeDynamics(
            body,
            joint,
            jointLowerLimit=math.radians(lim.min_deg),
            jointUpperLimit=math.radians(lim.max_deg),
            physicsClientId=client,
        )
    f = model.friction
    for link in (CENTRE, FRONT, BACK):
        p.changeDynamics(
            body,
            link,
            lateralFriction=f.lateral,
            spinningFriction=f.spinning,
            rollingFriction=f.rolling,
            restitution=f.restitution,
            anisotropicFriction=list(f.anisotropic),
            linearDamping=0.0,
            angularDamping=0.0,
            physicsClientId=client,
        )
    return ModuleBody(client, body)
