"""What is under way in a docking sequence (:class:`firmware.motion.docking.Docking`): each
motion with the cycles it was asked, planned and stepped at, and how each ended.

Plain records, no behaviour: the sequence steps the motions they hold; its owners read them
(the loop's summary, the benchmarks, the tests).
"""

from __future__ import annotations

from dataclasses import dataclass

from dh2rt.docking import End
from firmware.motion.clearing import Clearing
from firmware.motion.crawl import Creep, Trip
from firmware.motion.reach import Reach

#: module -> {DOF index: degrees}: the joint targets the moving modules hold this cycle.
Targets = dict[int, dict[int, float]]


@dataclass(frozen=True)
class Needs:
    """What the motions read this cycle: joint angles of ``joints``, infrared pairs of
    ``infrared``, the overhead tracker if ``floor``, the IMU of ``attitude``."""

    joints: frozenset[int] = frozenset()
    infrared: tuple[int, ...] = ()
    floor: bool = False
    attitude: tuple[int, ...] = ()


@dataclass
class Motion:
    """One reach under way (``reach_dock``, or the dock of a foot that came)."""

    reach: Reach
    #: ``asking -> target`` in words
    where: str
    #: the cycle it was asked at, and the one its plan was ready at
    asked: int
    planned: int
    #: seconds the plan took, by the owner's clock (:attr:`Docking.clock`)
    plan_s: float
    #: the cycle it was last stepped at, and the cycles since its plan was ready that went by
    #: without a step (an owner whose thread came too late for them)
    last: int = -1
    missed: int = 0
    #: the lone module (a foot that came) creeping towards the asking face meanwhile, if any
    creep: Creep | None = None

    @property
    def modules(self) -> set[int]:
        """The modules whose joints the motion holds (the creeping foot's included)."""
        return self.reach.modules | ({self.creep.module} if self.creep is not None else set())


@dataclass
class Bringing:
    """A released foot on its way, by its own gaits, to a free face."""

    trip: Trip
    #: the route up the target's robot whose joints square its face once the foot is there
    route: tuple[int, ...]
    #: the cycle it set off at, and the one it was last stepped at
    asked: int
    last: int
    missed: int = 0


@dataclass
class CrawlingClear:
    """A robot crawling clear of a module lying on the spot behind ``face`` before ``foot``
    (the foot's end that still hangs on the body) lets go."""

    clearing: Clearing
    face: End
    foot: End
    asked: int
    last: int
    missed: int = 0


@dataclass(frozen=True)
class Arrival:
    """A foot's trip that got to its spot: the foot, the face, cycles (set off, arrived), the
    trip's steps and the cycles it missed."""

    foot: int
    target: End
    asked: int
    arrived: int
    steps: int
    missed: int


@dataclass(frozen=True)
class Outcome:
    """How a reach ended: cycles (asked, plan ready, latched or given up), its steps, the
    cycles it missed, the plan's seconds, whether it linked."""

    asked: int
    planned: int
    ended: int
    steps: int
    missed: int
    plan_s: float
    latched: bool
