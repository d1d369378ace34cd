"""Docking by motion, swept over layouts and seeds (firmware.motion.reach through sim.runner.PhysicsRun).

A snake and a module lying apart. Each layout picks the asking face (the snake's tail
``back``, a male face, or its head's ``front``, the female one), the lone module's face it
docks to (of the other gender), how far the chain is bent where the target lies, and how far
the target is out, aside and turned from where the bent chain puts its face; the chain then
straightens and has to find its way back by its own motion. Layouts and seeds are drawn from
a fixed random generator, so the sweep is the same each run and covers both ends, both ways
round and each of the lone module's faces.

For every layout the test checks what the issue asks of every link made by motion: it
formed (the motion latched), only when the two faces' world poses were within the runner's
tolerance at that moment (the :class:`sim.motion_readings.Contact` recorded then, checked against its
own world positions), with the asking face's infrared pair seeing the target, male to female.
Male to male and female to female are refused before anything moves.
"""

from __future__ import annotations

import io
import json
import math
import random

import pytest

from dh2rt.compiler import compile_source
from dh2rt.profile import CONRO
from dh2rt.robot import Robot
from dh2rt.topology import Link, Topology
from dh2rt.trace import TraceWriter
from sim.command import traced
from sim.runner import DOCK_TOLERANCE_DEG, DOCK_TOLERANCE_M, PhysicsRun
from tools.trace_reading import parse_record

C = CONRO.connector_index
FRONT, BACK, LEFT, RIGHT = C("front"), C("back"), C("left"), C("right")
#: A program that holds every joint where it is: only the docking motion moves.
STILL = compile_source("program still\nconst ClockCycle = 40\n")
#: Cycles a layout may take (the motion itself gives up after 400).
BUDGET = 450
#: How far beyond where the bent chain put its face the target may lie (metres).
OUT_M = 0.015


def topology(n: int) -> Topology:
    names = (*(f"m{i}" for i in range(n)), "lone")
    return Topology(CONRO, names, tuple(Link(i, BACK, i + 1, FRONT) for i in range(n - 1)), f"{n}+1")


def scene(
    n: int,
    tail: bool,
    target_conn: int,
    seed: int,
    bend: tuple[float, float],
    out_m: float,
    aside_m: float,
    turn: float,
) -> tuple[PhysicsRun, int, int, tuple[int, ...]]:
    """An n-module snake and a lone module (index n). The asking end (the tail's back or the
    head's front) and its neighbour bend their yaws by ``bend``; where the asking face is then,
    the lone module's ``target_conn`` face is put (``out_m`` out along the face's normal,
    ``aside_m`` across it, turned ``turn`` degrees from square), and the snake straightens.
    Returns the run, the asking module and connector, and the route up the snake."""
    run = PhysicsRun(Robot(STILL, topology(n), seed=seed))
    w = run.world
    hops = 2  # the two modules nearest the asking end bend; the rest of the snake lies still
    if tail:
        asking, conn, route, movers = n - 1, BACK, (FRONT,) * hops, (n - 1, n - 2)
    else:
        asking, conn, route, movers = 0, FRONT, (BACK,) * hops, (0, 1)
    for m, yaw in zip(movers, bend, strict=True):
        w.set_targets(m, 0.0, yaw)
    w.step(480)
    face, normal = w.connector_pose(asking, conn)
    for m in movers:
        w.set_targets(m, 0.0, 0.0)
    w.step(480)
    # where the lone module's target face sits relative to its body when it lies at the origin
    lone = n
    w.set_module_pose(lone, (0.0, 0.0, w.model.height / 2 + 0.001), 0.0)
    f0, n0 = w.connector_pose(lone, target_conn)
    yaw = math.atan2(normal[1], normal[0]) + math.pi + math.radians(turn) - math.atan2(n0[1], n0[0])
    want = (face[0] + normal[0] * out_m - normal[1] * aside_m, face[1] + normal[1] * out_m + normal[0] * aside_m)
    c, s = math.cos(yaw), math.sin(yaw)
    x = want[0] - (c * f0[0] - s * f0[1])
    y = want[1] - (s * f0[0] + c * f0[1])
    w.set_module_pose(lone, (x, y, w.model.height / 2 + 0.001), math.degrees(yaw))
    w.step(60)
    return run, asking, conn, route


def layouts(count: int, seed: int) -> list[tuple[int, bool, int, int, tuple[float, float], float, float, float]]:
    rng = random.Random(seed)
    out = []
    for i in range(count):
        tail = i % 2 == 0
        target = FRONT if tail else (LEFT, RIGHT, BACK)[(i // 2) % 3]
        first = rng.choice((-1.0, 1.0)) * rng.uniform(30.0, 60.0)
        out.append(
            (
                rng.choice((3, 4)),
                tail,
                target,
                rng.randrange(1000),
                (first, rng.uniform(-45.0, 45.0)),
                rng.uniform(0.0, OUT_M),
                rng.uniform(-0.005, 0.005),
                rng.uniform(-10.0, 10.0),
            )
        )
    return out


LAYOUTS = layouts(12, seed=13)


def layout_id(layout: tuple[int, bool, int, int, tuple[float, float], float, float, float]) -> str:
    n, tail, target, seed, bend = layout[:5]
    end = "back" if tail else "front"
    return f"{n}-{end}-to-{CONRO.connector_name(target)}-s{seed}-bend{bend[0]:.0f},{bend[1]:.0f}"


@pytest.mark.parametrize(
    ("n", "tail", "target", "seed", "bend", "out", "aside", "turn"), LAYOUTS, ids=[layout_id(x) for x in LAYOUTS]
)
def test_every_latch_within_tolerance_at_that_moment(
    n: int, tail: bool, target: int, seed: int, bend: tuple[float, float], out: float, aside: float, turn: float
) -> None:
    run, asking, conn, route = scene(n, tail, target, seed, bend, out, aside, turn)
    lone = n
    try:
        before = run.world.links()
        assert not run.aligned(asking, conn, lone, target)  # the chain has to move
        assert run.docking.reach_other(asking, conn, route, (lone, target))
        for _ in range(BUDGET):
            run.cycle()
            if not run.docking.motions:
                break
        assert not run.docking.motions and not run.failed, run.robot.log[-5:]
        assert run.world.links() - before == {Link(asking, conn, lone, target)}
        assert run.robot.peer_of((asking, conn)) == (lone, target)
        (contact,) = run.contacts
        assert contact.asking == (asking, conn) and contact.target == (lone, target)
        # within tolerance at the latch, by the world's poses recorded then
        assert math.isclose(contact.distance_m, math.dist(contact.asking_face, contact.target_face), abs_tol=1e-9)
        assert contact.distance_m <= DOCK_TOLERANCE_M and contact.attitude_deg <= DOCK_TOLERANCE_DEG
        # the faces looked at each other (normals opposite within the tolerance)
        dot = sum(a * b for a, b in zip(contact.asking_normal, contact.target_normal, strict=True))
        assert dot <= -math.cos(math.radians(DOCK_TOLERANCE_DEG)) + 1e-9
        # and the asking face's infrared pair saw the target
        assert 0 < contact.ir_mm <= DOCK_TOLERANCE_M * 1000 and contact.ir_align_deg <= DOCK_TOLERANCE_DEG
        # male to female
        assert CONRO.gender(conn) != CONRO.gender(target)
    finally:
        run.close()


@pytest.mark.parametrize(
    ("tail", "target"),
    [(True, BACK), (True, LEFT), (True, RIGHT), (False, FRONT)],
    ids=["mm-back", "mm-left", "mm-right", "ff"],
)
def test_same_gender_is_refused_and_nothing_moves(tail: bool, target: int) -> None:
    run, asking, conn, route = scene(3, tail, target, 0, (40.0, 20.0), 0.0, 0.0, 0.0)
    try:
        before = run.world.links()
        assert not run.docking.reach_other(asking, conn, route, (3, target))
        assert not run.docking.motions
        assert any("both connectors are" in line for line in run.robot.log)
        for _ in range(20):
            run.cycle()
        assert run.world.links() == before and not run.contacts
    finally:
        run.close()


def test_the_latch_is_in_the_trace_with_both_faces_poses() -> None:
    """``dh2rt run --sim pybullet --trace``: the asking module's record of the cycle its
    motion latched carries ``dock`` (both faces' world poses and errors at that moment)."""
    run, asking, conn, route = scene(3, True, FRONT, 5, (45.0, 20.0), 0.005, 0.0, 5.0)
    stream = io.StringIO()
    trace = TraceWriter(stream, run.robot, extra=lambda m: traced(run, m, list(run.world.module_position(m))))
    try:
        assert run.docking.reach_other(asking, conn, route, (3, FRONT))
        run.run(BUDGET, [], lambda _c: trace.write_cycle())
        (contact,) = run.contacts
        records = [json.loads(line) for line in stream.getvalue().splitlines()]
        docks = [r for r in records if "dock" in r]
        assert len(docks) == 1
        (rec,) = docks
        assert rec["module"] == asking and rec["cycle"] == contact.cycle
        assert rec["dock"] == contact.as_dict()
        assert rec["dock"]["distance_mm"] <= DOCK_TOLERANCE_M * 1000
        assert rec["dock"]["attitude_deg"] <= DOCK_TOLERANCE_DEG
        # the trace is still one record per module per cycle, readable by the tools
        assert all({"cycle", "module", "pos"} <= r.keys() for r in records)
        for i, line in enumerate(stream.getvalue().splitlines(), 1):
            parse_record(line, "trace", i)
    finally:
        run.close()
