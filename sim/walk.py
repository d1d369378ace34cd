"""Legged walking, measured: how far and how straight a DH2 program walks a robot in physics
(:func:`measure_walk`, used by ``tests/sim/test_legged_gaits.py`` and ``benchmarks/bench_legged.py``).

It runs the program through :class:`sim.runner.PhysicsRun`, so it lives apart from the scripted
schedules of :mod:`sim.gaits`, which the runner's own crawls use."""

from __future__ import annotations

import math
from dataclasses import dataclass

from dh2rt.errors import GaitError
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from sim.gaits import STEPS_PER_CYCLE
from sim.runner import PhysicsRun
from sim.world import World


@dataclass(frozen=True)
class Walk:
    """How a DH2 program moved a robot in physics (:func:`measure_walk`).

    ``cm_per_gait_cycle``: the centroid's travel along the direction module 0's front
    connector faced when the world was built (``World.forward``), per gait cycle (ClockCycle
    control cycles), over the measured gait cycles after ``settle``.
    ``heading_deg``: module 0's heading at the end of each gait cycle, settling ones
    included, in degrees from ``World.forward`` (the build-time heading), signed (left > 0):
    the horizontal direction of module 0's front connector normal. ``drift_deg`` is the
    largest of their magnitudes. ``joint_span_deg``: per module, the range (max - min) of
    its (DOF1, DOF2) angles sampled every control cycle.
    """

    topology: str
    seed: int
    gait_cycles: int
    cm_per_gait_cycle: float
    sideways_cm_per_gait_cycle: float
    heading_deg: tuple[float, ...]
    joint_span_deg: tuple[tuple[float, float], ...]

    @property
    def drift_deg(self) -> float:
        return max(abs(h) for h in self.heading_deg)


def heading_deg(world: World) -> float:
    """Module 0's heading in degrees from ``World.forward`` (left > 0), from its front normal."""
    nx, ny, _ = world.connector_pose(0, 1)[1]
    fx, fy, _ = world.forward
    return math.degrees(math.atan2(fx * ny - fy * nx, fx * nx + fy * ny))


def measure_walk(
    program: CompiledProgram,
    topology: str,
    seed: int,
    *,
    gait_cycles: int = 20,
    settle: int = 1,
    steps_per_cycle: int = STEPS_PER_CYCLE,
) -> Walk:
    """Run ``program`` on ``topology`` in PyBullet and measure its walk (see :class:`Walk`).

    ``settle`` gait cycles are run first and not counted for speed; heading is sampled at the
    end of each of the ``gait_cycles`` gait cycles that follow (and of the settle ones).
    """
    if gait_cycles < 1 or settle < 0:
        raise GaitError(f"gait_cycles must be >= 1 and settle >= 0, got {gait_cycles} and {settle}")

    run = PhysicsRun(Robot(program, parse_spec(topology), seed=seed), steps_per_cycle=steps_per_cycle)
    world, clock = run.world, program.clock_cycle
    low = [[math.inf, math.inf] for _ in range(world.size)]
    high = [[-math.inf, -math.inf] for _ in range(world.size)]

    def track(_cycle: int) -> None:
        for m in range(world.size):
            for j, a in enumerate(world.joint_angles(m)):
                low[m][j] = min(low[m][j], a)
                high[m][j] = max(high[m][j], a)

    try:
        headings = []
        for _ in range(settle):
            run.run(clock, on_cycle=track)
            headings.append(heading_deg(world))
        start = world.centroid()
        for _ in range(gait_cycles):
            run.run(clock, on_cycle=track)
            headings.append(heading_deg(world))
        end = world.centroid()
        fx, fy, _ = world.forward
        dx, dy = end[0] - start[0], end[1] - start[1]
        spans = tuple((h[0] - lo[0], h[1] - lo[1]) for lo, h in zip(low, high, strict=True))
        return Walk(
            topology,
            seed,
            gait_cycles,
            (dx * fx + dy * fy) * 100 / gait_cycles,
            (fx * dy - fy * dx) * 100 / gait_cycles,
            tuple(headings),
            spans,
        )
    finally:
        run.close()
