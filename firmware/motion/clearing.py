"""The robot crawls clear of a body lying on the spot a foot must come to.

In legs to snake a foot comes to the tail's back by its own gaits (:class:`firmware.motion.crawl.Trip`)
and parks just behind it. A foot killed while it docks there stays where it died, 7 to 8 cm
behind the tail's back: on the spot the next foot must reach. Turning the tail's face aside
instead (its yaw at 45 or 80 degrees, so that the spot moves off the dead foot) was tried
and not kept: the trips to a turned face gave up at two seeds of three (docs/physics.md).

So before the next foot lets go of the body, the robot crawls forward: its body (from the
head to the tail's end) runs the caterpillar's wave, Table I as the program runs it
(:func:`firmware.motion.gaits.caterpillar_schedule` at the program's ClockCycle of 40 cycles) one gait
cycle at a time; after each it lies straight for :data:`SETTLE_CYCLES` and looks whether
anything still lies on the spot (in the wave the tail's face swings through 45 degrees and
the spot with it). The legs still on the body hold their
joints and are carried along. Measured at seeds 0 to 2, the winning foot killed as its dock
began: four gait cycles moved the robot 17.4 to 18.2 cm and left the dead foot 31 to 33 cm
behind the tail's back (from 12 to 14 cm).

:class:`Clearing` is stepped once a control cycle by its owner (``sim.runner.PhysicsRun``,
or ``hil.reach_loop.LoopReaches`` once a world cycle in the loop), which says what lies
where (``taken``, usually :func:`spot_taken` of the overhead tracker's poses).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

from dh2rt import docking
from dh2rt.docking import End
from dh2rt.profile import Profile
from firmware.motion.body import ConroModel
from firmware.motion.gaits import caterpillar_schedule
from firmware.motion.readings import FloorPoses

#: The caterpillar program's ClockCycle (examples/caterpillar.dh2), control cycles.
CLOCK_CYCLE = 40
#: Gait cycles the robot crawls at most before the foot sets off anyway: enough to leave a
#: body lying against the face (its centre 8 cm out) beyond :data:`SPOT_DEPTH_M` (the body
#: fell behind 2.5 cm a gait cycle there: 9 gait cycles, seed 1).
MAX_GAIT_CYCLES = 12
#: Control cycles the body lies straight after the crawl, before the foot lets go.
SETTLE_CYCLES = 20
#: The spot behind a face a foot comes to: this far out along its normal, this far either
#: side (m). A module lying apart with its centre there makes the robot crawl clear first.
#: Wider than the spot itself: the next foot comes to it from the side, and a body lying
#: just aside (within 8 cm of the axis, 25 cm out before) turned the next feet in place
#: there until their trips gave up (legs to snake, the winner killed as it docked, seeds 1
#: and 6 with the motions in the modules: formed at 6,881 and 6,988 with these, not before).
SPOT_DEPTH_M = 0.30
SPOT_HALF_WIDTH_M = 0.20


def spot_taken(
    floor: FloorPoses,
    model: ConroModel,
    peer_of: Callable[[End], End | None],
    profile: Profile,
    size: int,
    face: End,
    foot: int,
) -> int | None:
    """A module lying apart (not ``foot``, not on ``face``'s robot; modules 0 to ``size`` - 1)
    whose centre is on the spot behind ``face`` (:data:`SPOT_DEPTH_M` out along its normal,
    :data:`SPOT_HALF_WIDTH_M` either side), or None. Read from the overhead tracker
    (``floor``), as :class:`firmware.motion.crawl.Trip` reads where the face is: the infrared
    sees faces, not bodies, and a foot that died pitched shows its face to none."""
    robot = docking.robot_of(peer_of, profile, face[0])
    px, py, nx, ny = floor.face(model, *face)
    norm = math.hypot(nx, ny) or 1.0  # the face's heading on the floor (it tilts as the robot crawls)
    nx, ny = nx / norm, ny / norm
    for m in range(size):
        if m == foot or m in robot:
            continue
        x, y = floor.centre(m)
        out, aside = (x - px) * nx + (y - py) * ny, -(x - px) * ny + (y - py) * nx
        if 0.0 < out <= SPOT_DEPTH_M and abs(aside) <= SPOT_HALF_WIDTH_M:
            return m
    return None


class Clearing:
    """A robot crawling forward until nothing lies on the spot behind a face.

    ``body`` is the robot's spine from its head to the module whose face it is (the wave
    starts at the head); ``taken`` says whether something still lies on the spot.
    """

    def __init__(
        self,
        body: Sequence[int],
        taken: Callable[[], bool],
        *,
        clock_cycle: int = CLOCK_CYCLE,
        max_gait_cycles: int = MAX_GAIT_CYCLES,
    ) -> None:
        if not body:
            raise ValueError("a clearing needs at least one module to crawl")
        self.body = list(body)
        self.taken = taken
        self.clock_cycle = clock_cycle
        self.max_gait_cycles = max_gait_cycles
        self.cycles = 0
        #: Gait cycles crawled so far.
        self.gait_cycles = 0
        self._settled: int | None = None
        self.done = False
        #: Whether the spot was clear when the crawl stopped (False: the budget ran out).
        self.cleared = False

    def step(self) -> dict[int, float]:
        """Advance by one control cycle; the DOF1 targets (degrees) of the body's modules."""
        if self.done:
            return {}
        if self._settled is not None:  # lying straight after a gait cycle
            self._settled += 1
            if self._settled <= SETTLE_CYCLES:
                return dict.fromkeys(self.body, 0.0)
            # the faces swing through 45 degrees in the wave: look only once it lies still
            self._settled = None
            self.cleared = not self.taken()
            if self.cleared or self.gait_cycles >= self.max_gait_cycles:
                self.done = True
                return {}
        angles = caterpillar_schedule(len(self.body), self.cycles, self.clock_cycle)
        self.cycles += 1
        if self.cycles % self.clock_cycle == 0:
            self.gait_cycles += 1
            self._settled = 0
        return dict(zip(self.body, angles, strict=True))
