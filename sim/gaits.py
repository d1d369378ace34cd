"""Scripted joint schedules that stand in for DH2 programs in physics tests.

:func:`caterpillar_schedule` is what the paper's caterpillar program (Table I, Fig. 4)
produces in a lockstep run where a hormone crosses one link per control cycle:

* the head (T1, module 0) sets DOF1 +45 at LocalTimer 0, -45 at ClockCycle/4, -45 at
  ClockCycle/2, +45 at 3*ClockCycle/4, emitting hormones A, B, C, D, and holds in between;
* a body or tail module (T16, T2) that receives A sets -45 and sends B, B -> -45 and C,
  C -> +45 and D, D -> +45 and A: it takes the angle *of the next letter*.

So module k, k cycles after the head's event e (0..3), sets ``HEAD[(e + k) % 4]``: a square
wave one quarter period ahead of its front neighbour and one cycle late. Modules hold 0
before the first hormone reaches them.

:func:`delay_wave_schedule` is the other reading, where module k repeats at cycle c what
module k-1 set at cycle c-1 (no relabelling). It is kept to compare; it is *not* what
Table I says.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

from dh2rt.errors import GaitError

if TYPE_CHECKING:
    pass

#: The head's DOF1 angle after each of its four events A, B, C, D (Table I).
HEAD_ANGLES: tuple[float, float, float, float] = (45.0, -45.0, -45.0, 45.0)


def _check(n_modules: int, cycle: int, clock_cycle: int) -> int:
    if n_modules < 1:
        raise GaitError(f"n_modules must be >= 1, got {n_modules}")
    if cycle < 0:
        raise GaitError(f"cycle must be >= 0, got {cycle}")
    if clock_cycle < 4 or clock_cycle % 4:
        raise GaitError(f"clock_cycle must be a positive multiple of 4, got {clock_cycle}")
    return clock_cycle // 4


def caterpillar_schedule(n_modules: int, cycle: int, clock_cycle: int) -> list[float]:
    """DOF1 targets (degrees) of modules 0..n-1 at control cycle ``cycle`` (Table I)."""
    quarter = _check(n_modules, cycle, clock_cycle)
    out = []
    for k in range(n_modules):
        since = cycle - k  # the head's cycle whose hormone module k is acting on now
        out.append(0.0 if since < 0 else HEAD_ANGLES[(since // quarter + k) % 4])
    return out


def delay_wave_schedule(n_modules: int, cycle: int, clock_cycle: int) -> list[float]:
    """DOF1 targets where module k copies module k-1 one cycle later (not Table I)."""
    quarter = _check(n_modules, cycle, clock_cycle)
    return [0.0 if cycle < k else HEAD_ANGLES[((cycle - k) // quarter) % 4] for k in range(n_modules)]


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
