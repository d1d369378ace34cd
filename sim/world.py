"""A PyBullet world holding one robot of CONRO modules (or several pieces of one).

``World(topology)`` builds every module (see :mod:`sim.conro`), poses them on the ground so
that docked connectors coincide, and docks each link with a fixed constraint. Placement walks
the link graph from module 0 (and from the lowest unplaced module of every further connected
piece): each link fixes the child's pose relative to its parent, mated faces touching, normals
opposite, both modules upright with straight joints. Pieces that are not linked to each other
are laid side by side along +y. A link that closes a cycle (``ring:N``) is still docked, but
the straight layout cannot satisfy it, so its constraint pulls the ends together as hard as
``dock_force_n`` allows.

Every PyBullet call names the World's own physics client, so Worlds coexist in one process.
``seed`` turns the whole robot by a random yaw and shifts it by up to 5 mm (seed 0: no
perturbation), so tests can check that behaviour does not depend on the heading.
"""

from __future__ import annotations

import math
import random
from collections import deque
from dataclasses import dataclass
from typing import Any

import pybullet as p

from dh2rt.closing import Closing
from dh2rt.errors import PhysicsWorldError, SimulationError
from dh2rt.topology import Link, Topology
from drivers.pybullet_driver import PyBulletDriver
from firmware.motion.body import BACK, CENTRE, DEFAULT_MODEL, FRONT, ConroModel, Vec3
from sim.conro import ModuleBody, build_module

Quat = tuple[float, float, float, float]
_IDENTITY: Quat = (0.0, 0.0, 0.0, 1.0)
_GROUND_HALF = 50.0  # metres: the floor is a 100 m square


@dataclass(frozen=True, slots=True)
class _Dock:
    link: Link
    constraint: int


def _yaw_quat(yaw: float) -> Quat:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def _rot_z(yaw: float, v: Vec3) -> Vec3:
    c, s = math.cos(yaw), math.sin(yaw)
    return (c * v[0] - s * v[1], s * v[0] + c * v[1], v[2])


class World(Closing):
    """A robot of CONRO modules on a flat floor, stepped at ``physics_hz``.

    Use as a context manager, or call :meth:`close`.
    """

    def __init__(
        self,
        topology: Topology,
        *,
        gui: bool = False,
        physics_hz: float = 240.0,
        seed: int = 0,
        model: ConroModel = DEFAULT_MODEL,
        solver_iterations: int = 20,
        dock_force_n: float = 40.0,
    ) -> None:
        if not math.isfinite(physics_hz) or not 30.0 <= physics_hz <= 10_000.0:
            raise PhysicsWorldError(f"physics_hz must be between 30 and 10000, got {physics_hz}")
        if solver_iterations < 1:
            raise PhysicsWorldError(f"solver_iterations must be >= 1, got {solver_iterations}")
        if dock_force_n <= 0:
            raise PhysicsWorldError(f"dock_force_n must be > 0, got {dock_force_n}")
        self._check_profile(topology, model)
        self.topology = topology
        self.model = model
        self.seed = seed
        self.dock_force_n = dock_force_n
        self._hz = float(physics_hz)
        self._dt = 1.0 / self._hz
        self._steps = 0
        #: Modules without power (killed): their infrared emitters are dark, so no pair sees
        #: their faces (sim.sensors); their bodies stay where they lie.
        self.unpowered: set[int] = set()
        self.client: int = p.connect(p.GUI if gui else p.DIRECT)
        if self.client < 0:
            raise SimulationError("PyBullet: could not connect a physics client" + (" (GUI)" if gui else ""))
        try:
            self._setup_physics(solver_iterations)
            self._modules: list[ModuleBody] = []
            self._drivers: list[PyBulletDriver] = []
            self._docks: dict[tuple[int, int], _Dock] = {}
            self._build(topology)
        except BaseException:
            p.disconnect(physicsClientId=self.client)
            raise

    # -- construction ------------------------------------------------------------------

    @staticmethod
    def _check_profile(topology: Topology, model: ConroModel) -> None:
        prof = topology.profile
        for c in model.connectors:
            if (
                c.index > prof.connector_count
                or prof.connector_name(c.index) != c.name
                or prof.gender(c.index) != c.gender
            ):
                raise PhysicsWorldError(
                    f"topology profile {prof.name!r} does not match the module model at connector "
                    f"{c.index} ({c.name}, {c.gender})"
                )

    def _setup_physics(self, solver_iterations: int) -> None:
        cid = self.client
        p.setGravity(0.0, 0.0, -9.81, physicsClientId=cid)
        p.setTimeStep(self._dt, physicsClientId=cid)
        p.setPhysicsEngineParameter(
            numSolverIterations=solver_iterations,
            # Pyramid friction, as the paper's ODE setup, and cheaper than the cone here.
            enableConeFriction=0,
            deterministicOverlappingPairs=1,
            physicsClientId=cid,
        )
        plane = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=cid)
        look = p.createVisualShape(
            p.GEOM_BOX,
            halfExtents=(_GROUND_HALF, _GROUND_HALF, 0.001),
            visualFramePosition=(0.0, 0.0, -0.001),
            rgbaColor=(0.82, 0.84, 0.8, 1.0),
            physicsClientId=cid,
        )
        self.ground: int = p.createMultiBody(0.0, plane, look, physicsClientId=cid)
        f = self.model.friction
        p.changeDynamics(self.ground, -1, lateralFriction=1.0, restitution=f.restitution, physicsClientId=cid)

    def _module_connector(self, conn: int) -> Vec3:
        """A connector's position in its module's base frame, joints straight."""
        spec = self.model.connector(conn)
        if spec.link == FRONT:
            offset = self.model.centre.half[0] + self.model.front.half[0]
        elif spec.link == BACK:
            offset = -(self.model.centre.half[0] + self.model.back.half[0])
        else:
            offset = 0.0
        return (spec.position[0] + offset, spec.position[1], spec.position[2])

    def _normal_angle(self, conn: int) -> float:
        n = self.model.connector(conn).normal
        return math.atan2(n[1], n[0])

    def _layout(self, topology: Topology) -> list[tuple[float, float, float]]:
        """(x, y, yaw) of every module; pieces side by side along +y."""
        adjacency: dict[int, list[Link]] = {m: [] for m in range(topology.size)}
        for link in topology.links:
            adjacency[link.a].append(link)
            adjacency[link.b].append(link)
        poses: dict[int, tuple[float, float, float]] = {}
        next_y = 0.0
        half_w = max(self.model.front.size[1], self.model.centre.size[1], self.model.back.size[1]) / 2
        for root in range(topology.size):
            if root in poses:
                continue
            piece = {root: (0.0, 0.0, 0.0)}
            queue = deque([root])
            while queue:
                m = queue.popleft()
                for link in adjacency[m]:
                    (pa, pc), (ca, cc) = link.ends() if link.a == m else link.ends()[::-1]
                    if ca in piece:
                        continue
                    x, y, yaw = piece[pa]
                    anchor = _rot_z(yaw, self._module_connector(pc))
                    facing = yaw + self._normal_angle(pc)
                    child_yaw = facing + math.pi - self._normal_angle(cc)
                    offset = _rot_z(child_yaw, self._module_connector(cc))
                    piece[ca] = (x + anchor[0] - offset[0], y + anchor[1] - offset[1], child_yaw)
                    queue.append(ca)
            # Lay this piece beside the previous ones with a 10 cm gap.
            ys = [pose[1] for pose in piece.values()]
            shift = next_y - (min(ys) - self.model.length / 2) if poses else 0.0
            for m, (x, y, yaw) in piece.items():
                poses[m] = (x, y + shift, yaw)
            next_y = max(y for _, y, _ in poses.values()) + self.model.length / 2 + half_w + 0.1
        return [poses[m] for m in range(topology.size)]

    def _build(self, topology: Topology) -> None:
        rng = random.Random(self.seed)
        turn = 0.0 if self.seed == 0 else rng.uniform(-math.pi, math.pi)
        shift = (0.0, 0.0) if self.seed == 0 else (rng.uniform(-0.005, 0.005), rng.uniform(-0.005, 0.005))
        z = self.model.height / 2 + 0.001
        for x, y, yaw in self._layout(topology):
            rx, ry, _ = _rot_z(turn, (x, y, 0.0))
            body = build_module(p, self.client, self.model, (rx + shift[0], ry + shift[1], z), _yaw_quat(yaw + turn))
            self._modules.append(body)
            self._drivers.append(PyBulletDriver(self.client, body.body, body.joints, self.model.limits))
        for drv in self._drivers:
            drv.set_targets(0.0, 0.0)
        for link in topology.links:
            self._attach(link)
        nx, ny, _ = self.connector_pose(0, 1)[1]
        norm = math.hypot(nx, ny) or 1.0
        self._forward: Vec3 = (nx / norm, ny / norm, 0.0)

    # -- docking -----------------------------------------------------------------------

    def _attach(self, link: Link) -> None:
        cid = self.client
        ca, cb = self.model.connector(link.a_conn), self.model.connector(link.b_conn)
        # In the mated state body b is body a turned about z so that the normals oppose.
        theta = math.atan2(ca.normal[1], ca.normal[0]) + math.pi - math.atan2(cb.normal[1], cb.normal[0])
        body_a, body_b = self._modules[link.a].body, self._modules[link.b].body
        constraint = p.createConstraint(
            body_a,
            ca.link,
            body_b,
            cb.link,
            p.JOINT_FIXED,
            (0.0, 0.0, 0.0),
            ca.position,
            cb.position,
            parentFrameOrientation=_IDENTITY,
            childFrameOrientation=_yaw_quat(-theta),
            physicsClientId=cid,
        )
        p.changeConstraint(constraint, maxForce=self.dock_force_n, physicsClientId=cid)
        self._set_collisions(link.a, link.b, enabled=False)
        dock = _Dock(link, constraint)
        self._docks[(link.a, link.a_conn)] = dock
        self._docks[(link.b, link.b_conn)] = dock

    def _set_collisions(self, a: int, b: int, *, enabled: bool) -> None:
        # Mated modules never collide: the faces touch exactly and the neighbouring bodies
        # come close when a joint bends.
        body_a, body_b = self._modules[a].body, self._modules[b].body
        for la in (CENTRE, FRONT, BACK):
            for lb in (CENTRE, FRONT, BACK):
                p.setCollisionFilterPair(body_a, body_b, la, lb, int(enabled), physicsClientId=self.client)

    def dock(
        self,
        a: int,
        a_conn: int,
        b: int,
        b_conn: int,
        tolerance_m: float = 0.01,
        tolerance_deg: float = 10.0,
    ) -> bool:
        """Dock two free connectors if they are aligned within tolerance; True if docked.

        Aligned means: face centres at most ``tolerance_m`` apart, and the relative attitude
        of the two bodies within ``tolerance_deg`` of the mated one (normals opposite, tops
        the same way up). The genders must be able to link (male-female). The constraint
        then pulls the faces into exact contact.
        """
        self._check_ends(a, a_conn, b, b_conn)
        if (a, a_conn) in self._docks or (b, b_conn) in self._docks:
            return False
        if not self.aligned(a, a_conn, b, b_conn, tolerance_m, tolerance_deg):
            return False
        self._attach(Link(a, a_conn, b, b_conn))
        return True

    def aligned(
        self,
        a: int,
        a_conn: int,
        b: int,
        b_conn: int,
        tolerance_m: float = 0.01,
        tolerance_deg: float = 10.0,
    ) -> bool:
        """Whether two connectors of different gender are aligned within tolerance (see :meth:`dock`)."""
        self._check_ends(a, a_conn, b, b_conn)
        if a == b or not self.topology.profile.can_link(a_conn, b_conn):
            return False
        pa, _ = self.connector_pose(a, a_conn)
        pb, _ = self.connector_pose(b, b_conn)
        if math.dist(pa, pb) > tolerance_m:
            return False
        return self.attitude_error_deg(a, a_conn, b, b_conn) <= tolerance_deg

    def attitude_error_deg(self, a: int, a_conn: int, b: int, b_conn: int) -> float:
        """How far (degrees) the two connectors' parts are from the mated attitude."""
        ca, cb = self.model.connector(a_conn), self.model.connector(b_conn)
        _, qa = self._body_pose(a, ca.link)
        _, qb = self._body_pose(b, cb.link)
        theta = math.atan2(ca.normal[1], ca.normal[0]) + math.pi - math.atan2(cb.normal[1], cb.normal[0])
        wanted = p.multiplyTransforms((0, 0, 0), qa, (0, 0, 0), _yaw_quat(theta))[1]
        diff = p.getDifferenceQuaternion(wanted, qb)
        w = min(1.0, abs(diff[3]))
        return math.degrees(2 * math.acos(w))

    def undock(self, a: int, a_conn: int) -> bool:
        """Remove the constraint at connector ``a_conn`` of module ``a``; False if none."""
        self._check_module(a)
        self._check_connector(a_conn)
        dock = self._docks.get((a, a_conn))
        if dock is None:
            return False
        link = dock.link
        p.removeConstraint(dock.constraint, physicsClientId=self.client)
        for end in link.ends():
            del self._docks[end]
        still = any({d.link.a, d.link.b} == {link.a, link.b} for d in self._docks.values())
        if not still:
            self._set_collisions(link.a, link.b, enabled=True)
        return True

    def links(self) -> set[Link]:
        """The links docked now."""
        return {d.link for d in self._docks.values()}

    # -- stepping and joints ----------------------------------------------------------

    @property
    def physics_hz(self) -> float:
        return self._hz

    @property
    def time(self) -> float:
        """Simulated seconds since the World was built."""
        return self._steps * self._dt

    @property
    def size(self) -> int:
        return len(self._modules)

    def step(self, n: int = 1) -> None:
        """Advance the physics ``n`` steps of ``1 / physics_hz`` seconds."""
        if n < 0:
            raise PhysicsWorldError(f"step: n must be >= 0, got {n}")
        step, cid = p.stepSimulation, self.client
        for _ in range(n):
            step(physicsClientId=cid)
        self._steps += n

    def driver(self, module: int) -> PyBulletDriver:
        """The stand-in servo driver of ``module``."""
        self._check_module(module)
        return self._drivers[module]

    def body(self, module: int) -> int:
        """The PyBullet body id of ``module`` (in :attr:`client`)."""
        self._check_module(module)
        return self._modules[module].body

    def set_targets(self, module: int, dof1_deg: float, dof2_deg: float) -> None:
        self.driver(module).set_targets(dof1_deg, dof2_deg)

    def joint_angles(self, module: int) -> tuple[float, float]:
        return self.driver(module).read_positions()

    # -- poses ------------------------------------------------------------------------

    def module_position(self, module: int) -> Vec3:
        """Position (metres) of the module's centre body."""
        self._check_module(module)
        pos = p.getBasePositionAndOrientation(self._modules[module].body, physicsClientId=self.client)[0]
        return (float(pos[0]), float(pos[1]), float(pos[2]))

    def positions(self) -> list[Vec3]:
        return [self.module_position(m) for m in range(self.size)]

    @property
    def forward(self) -> Vec3:
        """Horizontal unit vector module 0's front connector faced when the World was built."""
        return self._forward

    def travel(self, start: Vec3, end: Vec3 | None = None) -> float:
        """Signed distance (m) from ``start`` to ``end`` along :attr:`forward`.

        ``end`` defaults to the centroid now.
        """
        end = self.centroid() if end is None else end
        return (end[0] - start[0]) * self._forward[0] + (end[1] - start[1]) * self._forward[1]

    def centroid(self) -> Vec3:
        """Mean of the modules' centre-body positions."""
        pts = self.positions()
        n = len(pts)
        return (sum(q[0] for q in pts) / n, sum(q[1] for q in pts) / n, sum(q[2] for q in pts) / n)

    def _body_pose(self, module: int, link: int) -> tuple[Vec3, Quat]:
        body = self._modules[module].body
        if link == CENTRE:
            pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=self.client)
        else:
            state = p.getLinkState(body, link, computeForwardKinematics=True, physicsClientId=self.client)
            pos, orn = state[0], state[1]
        return (
            (float(pos[0]), float(pos[1]), float(pos[2])),
            (float(orn[0]), float(orn[1]), float(orn[2]), float(orn[3])),
        )

    def part_pose(self, module: int, link: int) -> tuple[Vec3, Quat]:
        """A body part's pose (its centre-of-mass frame): position and quaternion (x, y, z, w)."""
        self._check_module(module)
        return self._body_pose(module, link)

    def part_transform(self, module: int, link: int) -> Any:
        """A body part's pose (its centre-of-mass frame) as a 4x4 numpy transform."""
        import numpy as np

        pos, orn = self._body_pose(module, link)
        t = np.eye(4)
        t[:3, :3] = np.array(p.getMatrixFromQuaternion(orn, physicsClientId=self.client)).reshape(3, 3)
        t[:3, 3] = pos
        return t

    def connector_pose(self, module: int, connector: int | str) -> tuple[Vec3, Vec3]:
        """(position, outward unit normal) of a connector face, in world coordinates."""
        self._check_module(module)
        conn = self._connector_index(connector)
        spec = self.model.connector(conn)
        pos, orn = self._body_pose(module, spec.link)
        world_pos = p.multiplyTransforms(pos, orn, spec.position, _IDENTITY)[0]
        world_n = p.multiplyTransforms((0, 0, 0), orn, spec.normal, _IDENTITY)[0]
        return (
            (float(world_pos[0]), float(world_pos[1]), float(world_pos[2])),
            (float(world_n[0]), float(world_n[1]), float(world_n[2])),
        )

    def set_module_pose(self, module: int, position: Vec3, yaw_deg: float) -> None:
        """Teleport an undocked module: upright, joints straight and at rest."""
        self._check_module(module)
        if any(m == module for m, _ in self._docks):
            raise PhysicsWorldError(f"set_module_pose: module {module} is docked; undock it first")
        body = self._modules[module].body
        p.resetBasePositionAndOrientation(body, position, _yaw_quat(math.radians(yaw_deg)), physicsClientId=self.client)
        p.resetBaseVelocity(body, (0, 0, 0), (0, 0, 0), physicsClientId=self.client)
        for j in self._modules[module].joints:
            p.resetJointState(body, j, 0.0, 0.0, physicsClientId=self.client)

    # -- checks and lifetime ----------------------------------------------------------

    def _check_ends(self, a: int, a_conn: int, b: int, b_conn: int) -> None:
        self._check_module(a)
        self._check_module(b)
        self._check_connector(a_conn)
        self._check_connector(b_conn)

    def _check_module(self, module: int) -> None:
        if not isinstance(module, int) or not 0 <= module < len(self._modules):
            raise PhysicsWorldError(f"no module {module!r}: this world has modules 0..{len(self._modules) - 1}")

    def _check_connector(self, conn: int) -> None:
        if not isinstance(conn, int) or not 1 <= conn <= self.topology.profile.connector_count:
            names = ", ".join(f"{i + 1}={n}" for i, n in enumerate(self.topology.profile.connectors))
            raise PhysicsWorldError(f"no connector {conn!r} (connectors: {names})")

    def _connector_index(self, connector: int | str) -> int:
        if isinstance(connector, str):
            try:
                return self.topology.profile.connector_index(connector)
            except ValueError:
                names = ", ".join(self.topology.profile.connectors)
                raise PhysicsWorldError(f"no connector {connector!r} (connectors: {names})") from None
        self._check_connector(connector)
        return connector

    def close(self) -> None:
        """Disconnect the physics client; the World is unusable afterwards."""
        if self.client >= 0:
            for drv in self._drivers:
                drv.close()
            p.disconnect(physicsClientId=self.client)
            self.client = -1

    def __del__(self) -> None:
        # A forgotten World must not leave a physics server behind.
        try:
            if getattr(self, "client", -1) >= 0 and p.isConnected(physicsClientId=self.client):
                p.disconnect(physicsClientId=self.client)
        except Exception:
            pass
