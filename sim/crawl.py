"""A lone module's own motion: how a released foot moves, and how it closes a dock itself.

A module on its own has two joints and three boxes. Measured in this world (docs/physics.md,
*Legs to snake, geometry*), 100 control cycles, seeds 0 to 2:

:func:`back_off`
    DOF1 = 45 + 40 sin(2 pi c / 8), DOF2 = 0: the front body paddles and the module slides
    away from its front, 7.9 to 9.8 cm (18.2 to 19.4 cm in 200 cycles; seeds 0 to 5); the
    robust gait.
:func:`creep`
    DOF1 a square wave between +60 and -30 degrees, period 8: the module moves front first,
    0.4 to 4.7 cm (2.5 to 9.3 cm in 200 cycles; seeds 0 to 5). Slow and uneven, but it is
    the only way a front (the female face) approaches something.

Turning is not offered. The paddle with the yaw swinging 60 degrees a quarter period behind
it, meant to turn the module to its left, turned it +297 degrees in 300 cycles at seed 0 but
-11 and -37 (the wrong way) at seeds 1 and 2; the yaw swinging in phase, +67, +18 and -2
(the robot's heading against the world's axes differs by seed, and the floor's pyramid
friction depends on it). So no route that needs a released foot to turn is reliable here.

:class:`Creep` is the foot's half of a dock whose target face lies beyond a straight
chain's reach (a chain lying straight cannot lengthen by bending): while the other side's
docking motion (:class:`sim.reach.Reach`) squares its face to the foot, the foot creeps
front first; it holds still, its front square, once its front's infrared pair reads the face
within :data:`HOLD_MM`, and creeps again if the reading grows past :data:`RESUME_MM` or the
face drops out of view for :data:`LOST_CYCLES` cycles.
"""

from __future__ import annotations

import math
from typing import Protocol

#: The gaits' period (control cycles).
PERIOD = 8
#: The foot holds still (front square) once its front infrared reads the target this close (mm).
HOLD_MM = 12.0
#: ... and creeps again once the reading is beyond this (mm).
RESUME_MM = 22.0
#: Cycles with nothing in view before a holding foot creeps again.
LOST_CYCLES = 16


def back_off(cycle: int) -> tuple[float, float]:
    """The lone module's joint targets (DOF1, DOF2 degrees) to slide away from its front."""
    return 45.0 + 40.0 * math.sin(2.0 * math.pi * cycle / PERIOD), 0.0


def creep(cycle: int) -> tuple[float, float]:
    """The lone module's joint targets (DOF1, DOF2 degrees) to move front first, slowly."""
    return (60.0 if (cycle // (PERIOD // 2)) % 2 == 0 else -30.0), 0.0


class Infrared(Protocol):
    """What :class:`Creep` reads: ``read([m])[m]`` maps ``ir_<c>`` to millimetres (0: nothing)."""

    def read(self, modules: list[int]) -> dict[int, dict[str, float]]: ...


class Creep:
    """A lone module creeping front first towards what its front infrared sees.

    Stepped once a control cycle by its owner; :meth:`step` returns the joint targets
    (degrees) the module holds this cycle.
    """

    def __init__(self, sensors: Infrared, module: int, connector_name: str = "front") -> None:
        self.sensors = sensors
        self.module = module
        self._ir = f"ir_{connector_name}"
        self.cycles = 0
        self.holding = False
        self._lost = 0
        #: Cycles spent creeping (not holding).
        self.crept = 0

    def reading_mm(self) -> float:
        return float(self.sensors.read([self.module])[self.module][self._ir])

    def step(self) -> tuple[float, float]:
        self.cycles += 1
        mm = self.reading_mm()
        if self.holding:
            self._lost = self._lost + 1 if mm == 0 else 0
            if mm > RESUME_MM or self._lost >= LOST_CYCLES:
                self.holding = False
        elif 0 < mm <= HOLD_MM:
            self.holding, self._lost = True, 0
        if self.holding:
            return 0.0, 0.0
        self.crept += 1
        return creep(self.crept)
