"""A PyBullet model of one CONRO module, built from the body's description.

The body itself (boxes, hinges, connector faces, servo limits) is data in
:mod:`firmware.motion.body`, which the firmware's kinematics read too; this module builds it
in a physics client (:func:`build_module`).

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
from dataclasses import dataclass
from typing import Any

from firmware.motion.body import BACK, CENTRE, FRONT, ConroModel, Vec3


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
