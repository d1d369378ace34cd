"""World: placement, docking, undocking, bookkeeping, and bad input."""

from __future__ import annotations

import math

import pybullet as p
import pytest

from dh2rt.errors import PhysicsWorldError
from dh2rt.profile import CONRO
from dh2rt.topology import Link, Topology, parse_spec
from sim.world import World

FRONT, BACK, LEFT, RIGHT = 1, 2, 3, 4


def _loose(n: int) -> Topology:
    return Topology(CONRO, tuple(f"m{i}" for i in range(n)), (), "loose")


def _gap(world: World, link: Link) -> float:
    return math.dist(world.connector_pose(link.a, link.a_conn)[0], world.connector_pose(link.b, link.b_conn)[0])


@pytest.mark.parametrize("spec", ["snake:8", "quadruped", "t-shape"])
@pytest.mark.parametrize("seed", [0, 7])
def test_docked_connectors_coincide(spec: str, seed: int) -> None:
    topo = parse_spec(spec)
    with World(topo, seed=seed) as w:
        assert w.links() == set(topo.links)
        for link in topo.links:
            (pa, na), (pb, nb) = w.connector_pose(link.a, link.a_conn), w.connector_pose(link.b, link.b_conn)
            assert math.dist(pa, pb) < 1e-5, topo.describe(link)
            assert sum(x * y for x, y in zip(na, nb, strict=True)) == pytest.approx(-1.0, abs=1e-5)
        for _, _, z in w.positions():
            assert z == pytest.approx(w.model.height / 2, abs=0.002)  # everyone on the floor
        w.step(120)
        for link in topo.links:
            assert _gap(w, link) < 0.002, topo.describe(link)
        # Nothing overlaps badly enough to explode: the robot stays on the floor.
        assert all(abs(z - w.model.height / 2) < 0.01 for _, _, z in w.positions())


def test_legs_hang_from_the_spine_sides() -> None:
    topo = parse_spec("quadruped")
    with World(topo) as w:
        spine0 = w.module_position(0)
        left0 = w.module_position(topo.names.index("left_leg0"))
        right0 = w.module_position(topo.names.index("right_leg0"))
        # Left is +y of the spine (facing +x); each leg points away from it.
        assert left0[1] > spine0[1] + 0.05
        assert right0[1] < spine0[1] - 0.05


def test_unlinked_pieces_are_laid_apart() -> None:
    with World(_loose(3)) as w:
        pts = w.positions()
        for i in range(3):
            for j in range(i + 1, 3):
                assert math.dist(pts[i], pts[j]) > w.model.length


def test_time_steps_and_joint_api() -> None:
    with World(parse_spec("snake:2"), physics_hz=200.0) as w:
        assert w.physics_hz == 200.0
        w.step(100)
        assert w.time == pytest.approx(0.5)
        # tip up (negative pitch): a free motion; tip down would meet the floor first
        w.set_targets(0, -30.0, -15.0)
        w.step(200)
        d1, d2 = w.joint_angles(0)
        assert d1 == pytest.approx(-30.0, abs=3.0)
        assert d2 == pytest.approx(-15.0, abs=3.0)
        assert w.driver(1).read_positions()[0] == pytest.approx(0.0, abs=3.0)


def test_two_worlds_coexist() -> None:
    with World(parse_spec("snake:2")) as a, World(parse_spec("snake:3")) as b:
        assert a.client != b.client
        before = b.positions()
        a.set_targets(0, 60.0, 0.0)
        a.step(240)
        assert a.time == pytest.approx(1.0) and b.time == 0.0
        assert b.positions() == before
        assert b.size == 3 and a.size == 2


def _bring_front_to_back(w: World, offset: float, yaw_error_deg: float = 0.0) -> None:
    """Pose module 1 so that its front faces module 0's back, ``offset`` metres apart."""
    back_pos, back_n = w.connector_pose(0, BACK)
    yaw0 = math.degrees(math.atan2(-back_n[1], -back_n[0]))
    dist = w.model.length / 2 + offset  # centre to front face is half a module
    centre = (back_pos[0] + back_n[0] * dist, back_pos[1] + back_n[1] * dist, w.module_position(1)[2])
    w.set_module_pose(1, centre, yaw0 + yaw_error_deg)


def test_dock_within_tolerance_and_refuse_outside() -> None:
    with World(_loose(2)) as w:
        assert w.links() == set()
        _bring_front_to_back(w, 0.03)
        assert not w.dock(0, BACK, 1, FRONT)  # 3 cm apart: too far
        _bring_front_to_back(w, 0.004, yaw_error_deg=30.0)
        assert not w.dock(0, BACK, 1, FRONT)  # close, but turned 30 degrees
        _bring_front_to_back(w, 0.004)
        assert not w.dock(0, BACK, 1, BACK)  # male to male never links
        assert not w.dock(0, BACK, 0, FRONT)  # not to itself
        assert w.dock(0, BACK, 1, FRONT, tolerance_m=0.01, tolerance_deg=10.0)
        assert w.links() == {Link(0, BACK, 1, FRONT)}
        assert not w.dock(0, BACK, 1, FRONT)  # already docked
        w.step(120)
        assert _gap(w, Link(0, BACK, 1, FRONT)) < 0.002  # the latch pulled the faces together


def _push_apart(w: World, seconds: float, force: float) -> None:
    _, n = w.connector_pose(0, BACK)
    body = w.body(1)
    for _ in range(round(seconds * w.physics_hz)):
        pos = w.module_position(1)
        p.applyExternalForce(body, -1, (n[0] * force, n[1] * force, 0.0), pos, p.WORLD_FRAME, physicsClientId=w.client)
        w.step()


def test_undock_lets_the_modules_separate() -> None:
    topo = parse_spec("snake:2")
    link = topo.links[0]
    with World(topo) as w:
        w.step(60)
        _push_apart(w, 0.5, 3.0)
        assert _gap(w, link) < 0.003  # docked: the push drags both modules along
        assert not w.undock(0, FRONT)  # nothing docked there
        assert w.undock(1, FRONT)  # either end names the link
        assert w.links() == set()
        _push_apart(w, 0.5, 3.0)
        assert _gap(w, link) > 0.02
        assert not w.undock(0, BACK)


def test_set_module_pose_refuses_docked_modules() -> None:
    with World(parse_spec("snake:2")) as w, pytest.raises(PhysicsWorldError, match="docked"):
        w.set_module_pose(1, (0.0, 0.0, 0.03), 0.0)


def test_bad_input_names_the_value() -> None:
    topo = parse_spec("snake:2")
    with pytest.raises(PhysicsWorldError, match="physics_hz"):
        World(topo, physics_hz=0.0)
    with World(topo) as w:
        with pytest.raises(PhysicsWorldError, match="no module 5"):
            w.module_position(5)
        with pytest.raises(PhysicsWorldError, match="'nose'"):
            w.connector_pose(0, "nose")
        with pytest.raises(PhysicsWorldError, match="no connector 7"):
            w.dock(0, 7, 1, 1)
        with pytest.raises(PhysicsWorldError, match="n must be"):
            w.step(-1)
        assert w.connector_pose(0, "front") == w.connector_pose(0, FRONT)


def test_close_disconnects_the_client() -> None:
    w = World(parse_spec("snake:1"))
    cid = w.client
    assert p.isConnected(physicsClientId=cid)
    w.close()
    assert not p.isConnected(physicsClientId=cid)
    w.close()  # idempotent


def test_forward_is_where_the_head_faces() -> None:
    with World(parse_spec("snake:3"), seed=3) as w:
        _, n = w.connector_pose(0, FRONT)
        assert w.forward[0] == pytest.approx(n[0], abs=1e-6)
        assert w.forward[1] == pytest.approx(n[1], abs=1e-6)
        head, tail = w.module_position(0), w.module_position(2)
        assert w.travel(tail, head) == pytest.approx(2 * w.model.length, abs=1e-4)
