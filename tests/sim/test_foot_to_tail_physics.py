"""The foot comes to the tail (legs to snake in physics, issue 13 item 3): one round, by motion.

A released foot of the dragon travels by its own gaits (firmware.motion.crawl: back off, turn, crawl
backwards beside the tail past its end, square up behind it) and then docks: the tail's last
two modules square their back face to it (firmware.motion.reach) while the foot creeps front first
(firmware.motion.crawl.Creep) - the tail lying straight cannot lengthen by bending, so the foot has to
close the gap. The foot's trip reads where the tail's end is from the overhead tracker
(sim.tracker, exact here); the dock reads the chain's joint angles, the tracker and the
infrared pairs. Every
latch must have closed with the two faces within the runner's tolerance at that moment (the
record PhysicsRun.contacts keeps, the trace's ``dock`` line). The lone-module gaits are
measured on a 1-module snake; the dock alone with the foot put behind the tail by hand.
The whole reconfiguration, driven by examples/legs_to_snake.dh2, is tested in
tests/sim/test_legs_to_snake_physics.py (docs/physics.md, *Legs to snake in physics*).
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from dh2rt.compiler import compile_source
from dh2rt.profile import CONRO
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from firmware.motion.body import CENTRE
from firmware.motion.docking import BRING_ATTEMPTS
from firmware.motion.gaits import back_off, creep, turn
from sim.runner import DOCK_TOLERANCE_DEG, DOCK_TOLERANCE_M, PhysicsRun
from tests.marks import sweep

FRONT, BACK = CONRO.connector_index("front"), CONRO.connector_index("back")
#: A program that holds every joint where it is: only the motions move.
STILL = compile_source("program still\nconst ClockCycle = 40\n")
DRAGON = parse_spec("dragon")


def lone_travel(seed: int, gait: str, cycles: int = 100) -> float:
    """Metres a lone module's centre moved along its own heading (front first > 0)."""
    run = PhysicsRun(Robot(STILL, parse_spec("snake:1"), seed=seed))
    w = run.world
    try:
        t = w.part_transform(0, CENTRE)
        heading = np.array([t[0, 0], t[1, 0]]) / math.hypot(t[0, 0], t[1, 0])
        start = np.array(w.module_position(0)[:2])
        step = back_off if gait == "back_off" else creep
        for c in range(cycles):
            w.set_targets(0, *step(c))
            run.cycle()
        return float((np.array(w.module_position(0)[:2]) - start) @ heading)
    finally:
        run.close()


def lone_turn(seed: int, direction: int, cycles: int = 200) -> float:
    """Degrees a lone module turned (counter-clockwise > 0) under :func:`firmware.motion.gaits.turn`."""
    run = PhysicsRun(Robot(STILL, parse_spec("snake:1"), seed=seed))
    w = run.world

    def heading() -> float:
        t = w.part_transform(0, CENTRE)
        return math.atan2(t[1, 0], t[0, 0])

    try:
        total, before = 0.0, heading()
        for c in range(cycles):
            w.set_targets(0, *turn(c, direction))
            run.cycle()
            now = heading()
            total += (now - before + math.pi) % (2 * math.pi) - math.pi
            before = now
        return math.degrees(total)
    finally:
        run.close()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_lone_module_backs_off_creeps_and_turns_either_way(seed: int) -> None:
    """Measured (seeds 0 to 5): back_off 7.9 to 9.8 cm backwards in 100 cycles; creep 4.5 to
    6.1 cm forwards in 200 cycles; turn +222 to +254 and -241 to -249 degrees in 200."""
    assert lone_travel(seed, "back_off") < -0.06
    assert lone_travel(seed, "creep", 200) > 0.03
    assert lone_turn(seed, +1) > 150
    assert lone_turn(seed, -1) < -150


def foot_behind_tail(seed: int, leg: str, along_m: float, aside_m: float) -> tuple[PhysicsRun, int, int]:
    """The dragon with ``leg`` released and its front put ``along_m`` behind tail4's back face
    (``aside_m`` to the tail's left), facing it squarely; nothing else has moved."""
    run = PhysicsRun(Robot(STILL, DRAGON, seed=seed))
    w = run.world
    foot, tail = DRAGON.names.index(leg), DRAGON.names.index("tail4")
    for _ in range(10):
        run.cycle()
    run.release(foot, FRONT)
    (px, py, _), (nx, ny, _) = w.connector_pose(tail, BACK)
    u = -np.array([nx, ny]) / math.hypot(nx, ny)  # the tail's heading
    face = np.array([px, py]) - along_m * u + aside_m * np.array([-u[1], u[0]])
    yaw = math.degrees(math.atan2(u[1], u[0]))
    z = w.model.height / 2 + 0.001
    w.set_module_pose(foot, (float(face[0]), float(face[1]), z), yaw)
    (fx, fy, _), _ = w.connector_pose(foot, FRONT)
    c = w.module_position(foot)
    w.set_module_pose(foot, (c[0] + float(face[0]) - fx, c[1] + float(face[1]) - fy, z), yaw)
    for _ in range(20):
        run.cycle()
    return run, foot, tail


def dock(run: PhysicsRun, foot: int, tail: int, *, creeps: bool) -> None:
    assert run.docking.reach_other(tail, BACK, (FRONT, FRONT), (foot, FRONT), timeout=400, creep=creeps)
    for _ in range(420):
        run.cycle()
        if not run.docking.motions:
            break


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(("leg", "along_m", "aside_m"), [("left_leg1", 0.03, 0.0), ("right_leg0", 0.05, 0.02)])
def test_the_foot_creeps_while_the_tail_squares_and_they_dock(
    seed: int, leg: str, along_m: float, aside_m: float
) -> None:
    run, foot, tail = foot_behind_tail(seed, leg, along_m, aside_m)
    robot = run.robot
    try:
        dock(run, foot, tail, creeps=True)
        assert robot.peer_of((tail, BACK)) == (foot, FRONT), robot.log[-1]
        (contact,) = run.contacts
        assert contact.asking == (tail, BACK) and contact.target == (foot, FRONT)
        assert contact.distance_m <= DOCK_TOLERANCE_M and contact.attitude_deg <= DOCK_TOLERANCE_DEG
        assert 0 < contact.ir_mm <= DOCK_TOLERANCE_M * 1000
        # the world's own check, after the latch pulled the faces together
        pa, _ = run.world.connector_pose(tail, BACK)
        pb, _ = run.world.connector_pose(foot, FRONT)
        assert math.dist(pa, pb) < DOCK_TOLERANCE_M
        # the foot is the dragon's new tail, tail4 a body module
        new_tail, old_tail = robot.engines[foot], robot.engines[tail]
        assert new_tail is not None and new_tail.topo_type.name == "tail"
        assert old_tail is not None and old_tail.topo_type.name == "body"
    finally:
        run.close()


@pytest.mark.parametrize("seed", sweep([0, 1, 2]))
def test_without_the_creep_the_straight_tail_cannot_reach(seed: int) -> None:
    """A chain lying straight cannot lengthen: with the foot still, the tail gives up about
    30 mm away (measured 29.8 to 31.3 mm, 2 and 3 hops, seeds 0 to 2) and links nothing."""
    run, foot, tail = foot_behind_tail(seed, "left_leg1", 0.03, 0.0)
    try:
        dock(run, foot, tail, creeps=False)
        assert run.robot.peer_of((tail, BACK)) is None
        assert not run.contacts and len(run.failed) == 1
        assert run.failed[0].distance_m > DOCK_TOLERANCE_M
    finally:
        run.close()


@pytest.mark.slow
@pytest.mark.parametrize("seed", sweep([0, 1, 2]))
@pytest.mark.parametrize("leg", ["left_leg1", "right_leg1"])
def test_a_released_rear_foot_comes_to_the_tail_and_docks(seed: int, leg: str) -> None:
    """The first round with a rear foot (the program's feet win front first). Measured with
    today's trip (the diagonal past the face) and dock: 938 to 1,197 cycles from the release
    to the latch (python -m benchmarks.bench_trips). Before the diagonal, right_leg1 at seed 0
    turned about behind the tail and pressed its back on it until its budget ran out (a
    strict xfail here then)."""
    run = PhysicsRun(Robot(STILL, DRAGON, seed=seed))
    robot, w = run.robot, run.world
    foot, tail = DRAGON.names.index(leg), DRAGON.names.index("tail4")
    try:
        for _ in range(10):
            run.cycle()
        start, _ = w.connector_pose(foot, FRONT)
        run.bring_home(foot, (tail, BACK), (FRONT, FRONT), 3200)
        assert robot.peer_of((tail, BACK)) == (foot, FRONT), robot.log[-1]
        (contact,) = run.contacts
        assert contact.asking == (tail, BACK) and contact.target == (foot, FRONT)
        assert contact.distance_m <= DOCK_TOLERANCE_M and contact.attitude_deg <= DOCK_TOLERANCE_DEG
        assert 0 < contact.ir_mm <= DOCK_TOLERANCE_M * 1000
        # it came by itself, from beside the spine to behind the tail's end
        assert math.dist(start, contact.target_face) > 0.45
        new_tail, old_tail = robot.engines[foot], robot.engines[tail]
        assert new_tail is not None and new_tail.topo_type.name == "tail"
        assert old_tail is not None and old_tail.topo_type.name == "body"
        # the arrival's note says where the trip's cycles went, phase by phase, and they add up
        (arrival,) = [line for line in robot.log if "arrived after" in line]
        found = re.search(r"arrived after (\d+) cycles \(.*; (.*)\)$", arrival)
        assert found is not None, arrival
        spent = dict(re.findall(r"(back off|along|aside|square) (\d+)", found[2]))
        assert "back off" in spent and "square" in spent, arrival
        assert sum(int(n) for n in spent.values()) == int(found[1]), arrival
        # and the finished trip keeps the same account
        (trip,) = run.docking.trips_done
        assert trip.arrived and {k: str(v) for k, v in trip.spent.items()} == spent
    finally:
        run.close()


def test_a_trip_that_gives_up_sends_the_foot_round_again_up_to_the_attempts() -> None:
    """A foot lying apart cannot ask again (no link to send RCT through): a trip out of budget
    sets it off again from where it is, BRING_ATTEMPTS times in all, then leaves it."""
    run = PhysicsRun(Robot(STILL, DRAGON, seed=0))
    foot, tail = DRAGON.names.index("left_leg1"), DRAGON.names.index("tail4")
    try:
        for _ in range(10):
            run.cycle()
        run.release(foot, FRONT)
        assert run.docking.bring(foot, (tail, BACK), (FRONT, FRONT))
        set_off = 0
        for _ in range(BRING_ATTEMPTS * 40 + 10):
            for trip in [b.trip for b in run.docking.trips]:
                if trip.cycles == 0:
                    trip.budget = 30  # too short to arrive: it gives up
                    set_off += 1
            run.cycle()
        assert set_off == BRING_ATTEMPTS and not run.docking.trips and not run.docking.motions
        assert len(run.docking.trips_done) == BRING_ATTEMPTS and not any(t.arrived for t in run.docking.trips_done)
        log = "\n".join(run.robot.log)
        assert log.count("the trip gave up after 31 cycles") == BRING_ATTEMPTS, log
        assert [n for n in range(2, BRING_ATTEMPTS + 1) if f"the foot tries again ({n})" in log] == list(
            range(2, BRING_ATTEMPTS + 1)
        )
        assert run.robot.peer_of((tail, BACK)) is None
    finally:
        run.close()
