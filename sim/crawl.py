"""A lone module's own motion: how a released foot moves, turns, and closes a dock itself.

A module on its own has two joints and three boxes. Measured in this world (docs/physics.md,
*Legs to snake, geometry*), seeds 0 to 5 (every seed but 0 turns the world's axes, against
which the floor's pyramid friction differs):

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

:class:`Trip` takes a released foot to just behind a free face; :class:`Creep` is the
foot's half of the dock that follows, whose target lies beyond a straight chain's reach (a
chain lying straight cannot lengthen by bending): while the other side's docking motion
(:class:`sim.reach.Reach`) squares its face to the foot, the foot creeps front first; it
holds still, its front square, once its front's infrared pair reads the face within
:data:`HOLD_MM`, and creeps again if the reading grows past :data:`RESUME_MM` or the face
drops out of view for :data:`LOST_CYCLES` cycles.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, Protocol

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
    return 45.0 * math.sin(2.0 * math.pi * cycle / PERIOD), 0.0


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


#: The turning gait's period (control cycles); see the module docs.
TURN_PERIOD = 12


def turn(cycle: int, direction: int) -> tuple[float, float]:
    """The lone module's joint targets to turn in place: ``direction`` +1 to its left
    (counter-clockwise from above), -1 to its right."""
    x = 2.0 * math.pi * cycle / TURN_PERIOD
    return 30.0 + 40.0 * math.sin(x), direction * 40.0 * math.sin(x + math.pi / 2.0)


class Poses(Protocol):
    """What :class:`Trip` reads of the world (a :class:`sim.world.World`)."""

    def connector_pose(
        self, module: int, connector: int | str
    ) -> tuple[tuple[float, float, float], tuple[float, float, float]]: ...

    def part_transform(self, module: int, link: int) -> Any: ...


class Trip:
    """A released foot's trip to a spot just behind a free face (the tail's back), facing it.

    The foot's front is the face that will dock, so the foot ends facing along the target's
    module (its heading that module's, reversed from the face's normal). In the target
    face's frame (``s`` along the module's heading from the face, ``lat`` across it, positive
    on the foot's side) the trip is: :func:`back_off` :attr:`backoff_m` away from where it
    hung (its side of the target module is the one it is on then); then, turning in place
    (:func:`turn`) whenever its heading is more than 8 degrees off the one it wants, else
    backing off: along a line :attr:`clear_m` beside the target module's axis (the heading
    it wants leans into the line by 5 degrees per cm off it, at most 29) until its front is
    :attr:`park` [0] behind the face; then sideways (heading 80 degrees off) until it is
    within 1.5 cm of :attr:`park` [1] aside; then square (within 6 degrees) and still; if it
    ended more than 2 cm further back than the spot, it creeps forward to it. The line is
    straight: it follows the tail only while the tail lies straight.

    Where the face is relative to the foot is read from the world (the foot's estimate of it
    from the chain's joint angles at release and its own odometry is not modelled); the
    last centimetres are the dock's (:class:`Creep`, the foot's infrared).
    """

    def __init__(
        self,
        world: Poses,
        module: int,
        target: tuple[int, int],
        *,
        backoff_m: float = 0.08,
        clear_m: float = 0.04,
        park: tuple[float, float] = (-0.03, 0.005),
        budget: int = 2500,
    ) -> None:
        self.world = world
        self.module = module
        self.target = target
        self.backoff_m = backoff_m
        self.clear_m = clear_m
        self.park = park
        self.budget = budget
        #: +1 if the foot travels on the target module's left, -1 on its right (decided when
        #: it has backed off).
        self.side = 1
        (fx, fy, _), _ = world.connector_pose(module, "front")
        self._start = (fx, fy)
        self.phase = "back off"
        self.cycles = 0
        self._turning = 0
        self.done = False
        #: Whether the foot got to the spot (False: the budget ran out).
        self.arrived = False

    def _frame(self) -> tuple[float, float, float]:
        """The foot's front in the target face's frame (s, lat unmirrored) and its heading off
        the target module's (radians, unmirrored)."""
        (fx, fy, _), _ = self.world.connector_pose(self.module, "front")
        t = self.world.part_transform(self.module, -1)
        (px, py, _), (nx, ny, _) = self.world.connector_pose(*self.target)
        norm = math.hypot(nx, ny) or 1.0
        ux, uy = -nx / norm, -ny / norm
        rx, ry = fx - px, fy - py
        heading = math.atan2(float(t[1, 0]), float(t[0, 0])) - math.atan2(uy, ux)
        return rx * ux + ry * uy, -rx * uy + ry * ux, (heading + math.pi) % (2 * math.pi) - math.pi

    def state(self) -> tuple[float, float, float]:
        """(s, lat, heading) with lat and heading mirrored to the foot's side."""
        s, lat, heading = self._frame()
        return s, lat * self.side, heading * self.side

    def step(self) -> tuple[float, float]:
        """Advance by one control cycle; the foot's joint targets (DOF1, DOF2 degrees)."""
        self.cycles += 1
        c = self.cycles
        if self.cycles > self.budget:
            self.done = True
            return 0.0, 0.0
        s, lat, heading = self.state()
        if self.phase == "back off":
            (fx, fy, _), _ = self.world.connector_pose(self.module, "front")
            if math.dist((fx, fy), self._start) > self.backoff_m:
                self.phase = "along"
                self.side = 1 if self._frame()[1] >= 0 else -1
                s, lat, heading = self.state()
        if self.phase == "along" and s <= self.park[0]:
            self.phase = "aside"
        if self.phase == "back off":
            return back_off(c)
        crawl: Callable[[int], tuple[float, float]] | None = back_off
        if self.phase == "along":
            want = max(-0.5, min(0.5, 5.0 * (lat - self.clear_m)))
        elif self.phase == "aside":
            off = lat - self.park[1]
            if abs(off) > 0.015:
                want = math.radians(80) * (1 if off > 0 else -1)
            else:
                self.phase, want, crawl = "square", 0.0, None
        else:
            want, crawl = 0.0, None
            if self.phase == "forward":
                crawl = creep
                if s >= self.park[0] - 0.01:
                    self.done = self.arrived = True
                    return 0.0, 0.0
                if abs(lat - self.park[1]) > 0.03:
                    self.phase = "aside"
        err = want - heading
        if self._turning and (abs(err) < math.radians(4) or self._turning * err < 0):
            self._turning = 0
        if not self._turning and abs(err) > math.radians(6 if crawl is None else 8):
            self._turning = 1 if err > 0 else -1
        if self._turning:
            return turn(c, self._turning * self.side)
        if self.phase == "square":
            if s < self.park[0] - 0.02:
                self.phase = "forward"
            else:
                self.done = self.arrived = True
            return 0.0, 0.0
        return crawl(c) if crawl is not None else (0.0, 0.0)
