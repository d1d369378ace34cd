"""Joint schedules the motions run: the caterpillar's wave and a lone module's gaits.

:func:`caterpillar_schedule` is what the paper's caterpillar program (Table I, Fig. 4)
produces in a lockstep run where a hormone crosses one link per control cycle:

* the head (T1, module 0) sets DOF1 +45 at LocalTimer 0, -45 at ClockCycle/4, -45 at
  ClockCycle/2, +45 at 3*ClockCycle/4, emitting hormones A, B, C, D, and holds in between;
* a body or tail module (T16, T2) that receives A sets -45 and sends B, B -> -45 and C,
  C -> +45 and D, D -> +45 and A: it takes the angle *of the next letter*.

So module k, k cycles after the head's event e (0..3), sets ``HEAD[(e + k) % 4]``: a square
wave one quarter period ahead of its front neighbour and one cycle late. Modules hold 0
before the first hormone reaches them. The robot crawls clear by it
(:class:`firmware.motion.clearing.Clearing`). :func:`delay_wave_schedule` is the other
reading, where module k repeats at cycle c what module k-1 set at cycle c-1 (no
relabelling), kept to compare; it is *not* what Table I says.

A module on its own has two joints and three boxes. Measured in the PyBullet world
(docs/physics.md, *Legs to snake, geometry*), seeds 0 to 5 (every seed but 0 turns the
world's axes, against which the floor's pyramid friction differs):

:func:`back_off`
    DOF1 = 45 + 40 sin(2 pi c / 8), DOF2 = 0: the front body paddles and the module slides
    away from its front, 7.9 to 9.8 cm in 100 cycles (18.2 to 19.4 cm in 200).
:func:`creep`
    DOF1 = 45 sin(2 pi c / 8), DOF2 = 0 (the caterpillar's flap): the module moves front
    first, 4.5 to 6.1 cm in 200 cycles, turning at most 10 degrees. The only way a front
    (the female face) approaches something. A square wave between +60 and -30 degrees did
    2.5 to 9.3 cm, unevenly.
:func:`turn`
    DOF1 = 30 + 40 sin(2 pi c / 12), DOF2 = 40 sin(2 pi c / 12 + pi / 2), mirrored: +222 to
    +254 degrees in 200 cycles (-241 to -249 mirrored), moving 7 to 10 cm meanwhile. Found
    by a sweep (period, phase, amplitudes); the gaits tried before it turned either way
    depending on the seed.
"""

from __future__ import annotations

import math

from dh2rt.errors import GaitError

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


#: The gaits' period (control cycles).
PERIOD = 8
#: The turning gait's period (control cycles); see the module docs.
TURN_PERIOD = 12


def back_off(cycle: int) -> tuple[float, float]:
    """The lone module's joint targets (DOF1, DOF2 degrees) to slide away from its front."""
    return 45.0 + 40.0 * math.sin(2.0 * math.pi * cycle / PERIOD), 0.0


def creep(cycle: int) -> tuple[float, float]:
    """The lone module's joint targets (DOF1, DOF2 degrees) to move front first, slowly."""
    return 45.0 * math.sin(2.0 * math.pi * cycle / PERIOD), 0.0


def turn(cycle: int, direction: int) -> tuple[float, float]:
    """The lone module's joint targets to turn in place: ``direction`` +1 to its left
    (counter-clockwise from above), -1 to its right."""
    x = 2.0 * math.pi * cycle / TURN_PERIOD
    return 30.0 + 40.0 * math.sin(x), direction * 40.0 * math.sin(x + math.pi / 2.0)
