"""Legs to snake in physics, driven by examples/legs_to_snake.dh2 (issue 13, item 3).

The program's protocol is the paper's (LTS, RCT, TAR, ALT: one foot per round); in physics
its ``dock_tail_to_foot`` is carried out by motion (PhysicsRun.assimilate): the winning foot
lets go of the body, comes to the tail's back by its own gaits (firmware.motion.crawl.Trip, along the
robot as it lies and round the legs still on it), and the two dock while the tail's last
modules square their face and the foot creeps (firmware.motion.reach, firmware.motion.crawl.Creep). The tail's
countdown to re-arm pauses while that motion is under way (``S.docking``); the head holds
still while feet are left and starts the wave at SNK. Every latch must have closed with the
faces within tolerance at that moment (PhysicsRun.contacts, the trace's ``dock`` record).

A reconfiguration takes 4,266 to 6,208 cycles here (seeds 0 to 2, with and without a kill,
and 11 with the trip kill; a trip is 55 to 85 cm at 8 to 10 cm per 100 cycles, plus the
turns), not the 1500 of the issue's command: docs/physics.md, *Legs to snake*.
``python -m benchmarks.bench_legs_to_snake`` runs the same at more seeds.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest

from dh2rt.compiler import compile_file
from sim import legs_to_snake
from sim.legs_to_snake import BACK, DRAGON, FRONT, KillWinner, snake_of
from sim.runner import DOCK_TOLERANCE_DEG, DOCK_TOLERANCE_M, PhysicsRun
from tests.conftest import EXAMPLES
from tests.marks import sweep

PROGRAM = compile_file(str(EXAMPLES / "legs_to_snake.dh2"))
FEET = {DRAGON.names.index(n) for n in DRAGON.names if "leg" in n}


def reconfigure(seed: int, on_cycle: Callable[[PhysicsRun], None] | None = None) -> tuple[PhysicsRun, int | None]:
    """Run LTS on the dragon until it is one snake (or the budget runs out): the run and the
    cycle the snake formed (sim.legs_to_snake.reconfigure with the shipped program)."""
    return legs_to_snake.reconfigure(PROGRAM, seed, on_cycle)


def check_latches(run: PhysicsRun, count: int) -> None:
    assert len(run.contacts) == count, run.robot.log[-6:]
    for contact in run.contacts:
        assert contact.asking[1] == BACK and contact.target[1] == FRONT and contact.target[0] in FEET
        assert contact.distance_m <= DOCK_TOLERANCE_M and contact.attitude_deg <= DOCK_TOLERANCE_DEG
        assert 0 < contact.ir_mm <= DOCK_TOLERANCE_M * 1000


@pytest.mark.slow
@pytest.mark.parametrize("seed", sweep([0, 1, 2]))
def test_the_dragon_assimilates_its_legs_and_crawls_away_as_an_11_module_snake(seed: int) -> None:
    pitches: list[float] = []  # the docking chain's pitch joints as each dock begins (degrees)

    def at_each_dock(run: PhysicsRun) -> None:
        for reach in [m.reach for m in run.docking.motions]:
            if reach.cycles == 1:
                angles = [run.world.joint_angles(m)[dof] for m, dof in reach.chain.joints]
                pitches.extend(abs(v) for (_m, dof), v in zip(reach.chain.joints, angles, strict=True) if dof == 0)

    run, formed = reconfigure(seed, at_each_dock)
    robot = run.robot
    try:
        assert formed is not None, robot.log[-6:]
        chain = snake_of(robot)
        assert chain is not None and len(chain) == 11
        assert chain[0] == DRAGON.names.index("spine0")
        # the feet, in the order they won, make the new end of the tail
        check_latches(run, 4)
        assert chain[-4:] == [c.target[0] for c in run.contacts]
        assert sum("trip gave up" in line for line in robot.log) == 0
        # the tail's end lies flat when a dock begins: the feet that docked before do not
        # carry a head wave's pitch (+45 or -45) into the tail (foot_wins sends their head
        # receptors to sleep)
        assert len(pitches) >= 8 and max(pitches) < 10.0, pitches
        # the head held still until the last foot docked, and the snake crawls away
        start = run.world.centroid()
        run.run(800)
        assert math.dist(start[:2], run.world.centroid()[:2]) > 0.10
    finally:
        run.close()


#: The world's sequence at seed 11, the winner killed on its trip, since its square-up reads the
#: foot from the asking module's own centre and takes the foot flat (the fourteenth session,
#: docs/physics.md): the second foot's dock gives up 58.9 mm, 17 degrees apart. The modules'
#: own motions form the same case (7,276 cycles). Strict: the run is deterministic in cycles.
WORLD_TRIP_11 = pytest.mark.xfail(
    reason="the world's sequence, trip kill at seed 11: a dock gives up (docs/physics.md)", strict=True
)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("when", "seed"),
    sweep(
        [("trip", 0), pytest.param("trip", 11, marks=WORLD_TRIP_11), ("dock", 0), ("dock", 1), ("dock", 2)],
        keep=(2,),
    ),
)
def test_the_winning_foot_killed_mid_dock_the_next_round_completes(when: str, seed: int) -> None:
    """The first winner dies on its way (400 cycles into its trip) or as the tail and it
    begin to close the dock: the motion ends, the tail's countdown runs out, it accepts again,
    and the three other feet are assimilated: a 10-module snake, the dead foot left lying
    apart. A foot that died on its way lies beside the robot: the next feet's trips steer
    round it and none gives up (at seed 11 the next foot, hanging beside it, turned in place
    between it and the body until its trip gave up, twice, before they did). A foot that
    died docking lies on the spot behind the tail's back, where the next foot must park: the
    robot crawls clear of it first (firmware.motion.clearing)."""
    kill_the_winner = KillWinner(when)
    killed = kill_the_winner.killed
    run, formed = reconfigure(seed, kill_the_winner)
    robot = run.robot
    try:
        assert len(killed) == 1 and killed[0] in FEET
        assert formed is not None, robot.log[-6:]
        chain = snake_of(robot)
        assert chain is not None and len(chain) == 10 and killed[0] not in chain
        check_latches(run, 3)
        assert killed[0] not in [c.target[0] for c in run.contacts]
        gone = "trip abandoned" if when == "trip" else "motion abandoned"
        assert sum(gone in line for line in robot.log) == 1, robot.log
        if when == "dock":
            assert any("the robot crawls clear first" in line for line in robot.log), robot.log
        else:
            assert sum("trip gave up" in line for line in robot.log) == 0, robot.log
    finally:
        run.close()


def test_an_unknown_interruption_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match="unknown kill 'late': one of none, trip, dock"):
        KillWinner("late")
