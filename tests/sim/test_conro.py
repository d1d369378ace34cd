"""The CONRO module model and its PyBullet stand-in driver, on real PyBullet."""

from __future__ import annotations

import math
import subprocess
import sys
from collections.abc import Iterator

import pybullet as p
import pytest

from dh2rt.errors import DriverError
from dh2rt.profile import CONRO
from drivers.pybullet_driver import PyBulletDriver
from firmware.motion.body import BACK, CENTRE, DEFAULT_MODEL, FRONT, ConnectorSpec, ConroModel
from sim.conro import build_module


@pytest.fixture
def client() -> Iterator[int]:
    cid = p.connect(p.DIRECT)
    p.setGravity(0, 0, -9.81, physicsClientId=cid)
    p.setTimeStep(1 / 240, physicsClientId=cid)
    yield cid
    p.disconnect(physicsClientId=cid)


def _hung_module(client: int) -> tuple[int, PyBulletDriver]:
    """A module whose centre is welded in mid-air, so DOF1 carries the front body's weight."""
    m = build_module(p, client, DEFAULT_MODEL, (0.0, 0.0, 0.5), (0.0, 0.0, 0.0, 1.0))
    p.createConstraint(m.body, -1, -1, -1, p.JOINT_FIXED, (0, 0, 0), (0, 0, 0), (0, 0, 0.5), physicsClientId=client)
    return m.body, PyBulletDriver(client, m.body, m.joints, DEFAULT_MODEL.limits)


def test_model_dimensions_and_connectors_match_the_profile() -> None:
    model = DEFAULT_MODEL
    assert model.length == pytest.approx(0.035 + 0.045 + 0.0254)
    assert model.back.size == (0.0254, 0.0254, 0.0254)  # the published 1 x 1 inch passive connector
    assert model.mass == pytest.approx(0.115)
    assert [c.name for c in model.connectors] == list(CONRO.connectors)
    assert [c.gender for c in model.connectors] == list(CONRO.genders)
    front, back = model.connector(1), model.connector(2)
    assert front.link == FRONT and front.normal == (1.0, 0.0, 0.0)
    assert back.link == BACK and back.normal == (-1.0, 0.0, 0.0)
    assert model.connector(3).normal == (0.0, 1.0, 0.0)  # left is +y in the module frame
    with pytest.raises(KeyError, match="no connector index 9"):
        model.connector(9)


def test_a_connector_with_a_tilted_normal_is_refused() -> None:
    bad = ConnectorSpec("front", 1, "female", FRONT, (0.0175, 0.0, 0.0), (0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="front"):
        ConroModel(connectors=(bad,))


def test_built_module_has_three_boxes_and_pitch_then_yaw(client: int) -> None:
    m = build_module(p, client, DEFAULT_MODEL, (0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 1.0))
    assert p.getNumJoints(m.body, physicsClientId=client) == 2
    dof1 = p.getJointInfo(m.body, 0, physicsClientId=client)
    dof2 = p.getJointInfo(m.body, 1, physicsClientId=client)
    assert dof1[2] == dof2[2] == p.JOINT_REVOLUTE
    assert tuple(dof1[13]) == (0.0, 1.0, 0.0)  # pitch
    assert tuple(dof2[13]) == (0.0, 0.0, 1.0)  # yaw
    # Joint frames sit on the hinges, the shared faces of the boxes.
    assert dof1[14][0] == pytest.approx(DEFAULT_MODEL.centre.size[0] / 2)
    assert dof2[14][0] == pytest.approx(-DEFAULT_MODEL.centre.size[0] / 2)
    for link in (CENTRE, FRONT, BACK):
        lo, hi = p.getAABB(m.body, link, physicsClientId=client)
        size = DEFAULT_MODEL.body(link).size
        for axis in range(3):
            assert hi[axis] - lo[axis] == pytest.approx(size[axis], abs=0.003)
    # The three boxes lie end to end along x: front, centre, back.
    front_lo = p.getAABB(m.body, FRONT, physicsClientId=client)[0][0]
    back_hi = p.getAABB(m.body, BACK, physicsClientId=client)[1][0]
    assert front_lo == pytest.approx(DEFAULT_MODEL.centre.size[0] / 2, abs=0.002)
    assert back_hi == pytest.approx(-DEFAULT_MODEL.centre.size[0] / 2, abs=0.002)


def test_joints_reach_targets_at_the_servo_speed(client: int) -> None:
    _, drv = _hung_module(client)
    drv.set_targets(30.0, -20.0)
    for _ in range(12):  # 0.05 s: at 400 deg/s the joint can have turned 20 deg at most
        p.stepSimulation(physicsClientId=client)
    early = drv.read_positions()
    assert abs(early[0]) <= 400.0 * 0.05 + 2.0
    for _ in range(240):
        p.stepSimulation(physicsClientId=client)
    dof1, dof2 = drv.read_positions()
    assert dof1 == pytest.approx(30.0, abs=2.0)
    assert dof2 == pytest.approx(-20.0, abs=2.0)


def test_targets_are_clamped_to_the_joint_limits(client: int) -> None:
    _, drv = _hung_module(client)
    drv.set_targets(200.0, -200.0)
    assert drv.targets == (90.0, -90.0)
    for _ in range(240):
        p.stepSimulation(physicsClientId=client)
    dof1, dof2 = drv.read_positions()
    assert dof1 == pytest.approx(90.0, abs=3.0)
    assert dof2 == pytest.approx(-90.0, abs=3.0)


def test_torque_off_makes_the_joints_limp(client: int) -> None:
    _, drv = _hung_module(client)
    drv.set_targets(0.0, 0.0)
    for _ in range(120):
        p.stepSimulation(physicsClientId=client)
    assert abs(drv.read_positions()[0]) < 3.0  # the servo holds the front body level
    drv.set_torque(False)
    assert not drv.torque_enabled
    for _ in range(240):
        p.stepSimulation(physicsClientId=client)
    assert drv.read_positions()[0] > 60.0  # limp: the front body droops (positive = tip down)
    drv.set_torque(True)
    drv.set_targets(0.0, 0.0)
    for _ in range(240):
        p.stepSimulation(physicsClientId=client)
    assert abs(drv.read_positions()[0]) < 3.0
    assert drv.health().ok
    assert "dof1_torque_nm" in drv.health().details


def test_driver_rejects_bad_joints_and_use_after_close(client: int) -> None:
    m = build_module(p, client, DEFAULT_MODEL, (0.0, 0.0, 0.5), (0.0, 0.0, 0.0, 1.0))
    with pytest.raises(DriverError, match="no joint 5"):
        PyBulletDriver(client, m.body, (0, 5))
    with pytest.raises(DriverError, match="2 joints"):
        PyBulletDriver(client, m.body, (0,))
    drv = PyBulletDriver(client, m.body)
    drv.close()
    assert not drv.health().ok
    with pytest.raises(DriverError, match="closed"):
        drv.read_positions()


def test_importing_drivers_does_not_import_pybullet() -> None:
    code = "import sys, drivers, drivers.pybullet_driver; sys.exit('pybullet' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], check=False, cwd=".").returncode == 0


def test_pitch_angle_sign_tips_the_front_down(client: int) -> None:
    body, drv = _hung_module(client)
    drv.set_targets(45.0, 0.0)
    for _ in range(240):
        p.stepSimulation(physicsClientId=client)
    front = p.getLinkState(body, FRONT, physicsClientId=client)[0]
    assert front[2] < 0.5 - 0.01
    assert math.isclose(drv.read_positions()[0], 45.0, abs_tol=2.0)
