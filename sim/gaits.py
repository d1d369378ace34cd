"""Scripted joint schedules that stand in for DH2 programs in physics tests.

:func:`run_caterpillar` drives a world through a schedule, by default the paper's caterpillar
(Table I) as the firmware's motions run it (:func:`firmware.motion.gaits.caterpillar_schedule`,
whose docs say how it reads Table I; :func:`firmware.motion.gaits.delay_wave_schedule` is the
other reading, kept to compare).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

from dh2rt.errors import GaitError
from firmware.motion.gaits import caterpillar_schedule

if TYPE_CHECKING:
    pass


class GaitWorld(Protocol):
    """What :func:`run_caterpillar` needs of a world (``sim.world.World`` has it)."""

    @property
    def time(self) -> float: ...
    @property
    def size(self) -> int: ...
    def set_targets(self, module: int, dof1_deg: float, dof2_deg: float) -> None: ...
    def joint_angles(self, module: int) -> tuple[float, float]: ...
    def centroid(self) -> tuple[float, float, float]: ...
    def step(self, n: int = 1) -> None: ...


#: Control-cycle length and ClockCycle the physics tests and benchmark use (at 240 Hz:
#: 0.05 s per cycle, a 1.6 s gait period).
STEPS_PER_CYCLE = 12
CLOCK_CYCLE = 32

Sample = tuple[float, list[tuple[float, float]], tuple[float, float, float]]


def run_caterpillar(
    world: GaitWorld,
    cycles: int,
    *,
    steps_per_cycle: int = STEPS_PER_CYCLE,
    clock_cycle: int = CLOCK_CYCLE,
    first_cycle: int = 0,
    schedule: Callable[[int, int, int], list[float]] = caterpillar_schedule,
    sample: bool = False,
    on_step: Callable[[int], None] | None = None,
) -> list[Sample]:
    """Drive ``world`` through ``cycles`` control cycles of ``schedule`` (DOF2 held at 0).

    With ``sample`` one sample per cycle is returned: (time, angles, centroid), the data
    :func:`sim.record.plot_run` draws. ``on_step(cycle)`` runs after each cycle's steps
    (e.g. to capture a frame).
    """
    if steps_per_cycle < 1:
        raise GaitError(f"steps_per_cycle must be >= 1, got {steps_per_cycle}")
    samples: list[Sample] = []
    n = world.size
    for cycle in range(first_cycle, first_cycle + cycles):
        for m, dof1 in enumerate(schedule(n, cycle, clock_cycle)):
            world.set_targets(m, dof1, 0.0)
        world.step(steps_per_cycle)
        if on_step is not None:
            on_step(cycle)
        if sample:
            samples.append((world.time, [world.joint_angles(m) for m in range(n)], world.centroid()))
    return samples
