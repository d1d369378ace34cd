"""A released foot's own part of ``reach_and_dock`` (sans-IO): its trip, its creep, its retry.

Once it lets go, the foot has no link to the robot: nobody can send it targets. So it runs its
part itself, from what it senses (docs/hil.md, *`reach_and_dock` in the modules*):

- the **trip** (:class:`firmware.motion.crawl.Trip`) to just behind the face, steered by the
  overhead tracker's poses (its own, the target's, the robot's ``body`` and the ``others``
  off the path, all by tracker marker);
- then the **creep** (:class:`firmware.motion.crawl.Creep`) on its front infrared pair, while
  the asking robot squares its face (that half is the asker's: ``Docking.reach_other``);
- docked when its front's link comes up; a trip out of budget, or a creep that no latch ended
  within the reach's own budget (:data:`CREEP_BUDGET`: the asker gave up, and cannot say so),
  sends it round again from where it is, up to :data:`firmware.motion.docking.BRING_ATTEMPTS`
  trips in all.

What it was told before the release is a :class:`dh2rt.wire.motion.SetOff`. The same
:func:`trip_to` builds every trip, the physics runner's and the loop's
(:class:`firmware.motion.docking.Docking`) and the foot's own, so the trip is planned once.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from dh2rt.docking import End
from dh2rt.wire.fields import Path
from dh2rt.wire.motion import SetOff
from firmware.motion.body import DEFAULT_MODEL, ConroModel
from firmware.motion.crawl import DIAGONAL_M, Creep, Trip
from firmware.motion.reach import DEFAULT_TIMEOUT
from firmware.motion.readings import FloorPoses, Readings, TrackerMissing

#: Trips a foot makes in all before it gives up (``Docking``'s rule, the same number).
ATTEMPTS = 3
#: Cycles a foot creeps with its front unlinked before it takes the dock as given up: the
#: asker's square-up gives up after ``DEFAULT_TIMEOUT`` cycles of its reach, which began when
#: the foot arrived; past that, no latch will come.
CREEP_BUDGET = DEFAULT_TIMEOUT


def trip_to(
    floor: FloorPoses,
    foot: int,
    target: End,
    *,
    model: ConroModel,
    body: Callable[[], list[int]],
    others: Callable[[], list[int]],
    diagonal_m: float = DIAGONAL_M,
) -> Trip:
    """The trip of ``foot`` to ``target``'s face along ``body``, clear of ``others``."""
    return Trip(floor, foot, target, model=model, body=body, others=others, diagonal_m=diagonal_m)


def hand_over(
    motion: int, seq: int, route: Path, face: End, body: Sequence[int], floor: FloorPoses, foot: int
) -> SetOff:
    """The SET_OFF the asking module sends ``foot`` (at the end of ``route``) before it lets
    go: come to ``face`` along ``body`` (the markers up the asker's robot, the asker first:
    what it learnt by following front links, :func:`dh2rt.docking.body_up`) and clear of every
    other module the tracker reports (:func:`dh2rt.docking.off_path`, read from the tracker
    instead of the world's link map: the legs still on the robot and any module lying
    apart)."""
    others = tuple(sorted(set(floor.modules) - set(body) - {foot}))
    return SetOff(motion, seq, route, face[0], face[1], tuple(body), others)


@dataclass
class Foot:
    """One foot's trip and creep, run on its own joints (module docs). :meth:`step` once a
    control cycle; :attr:`events` collects what the host reports (``trip_arrived``,
    ``trip_gave_up``, ``creep_gave_up``, ``docked``, ``gave_up``)."""

    module: int
    set_off: SetOff
    model: ConroModel = DEFAULT_MODEL
    diagonal_m: float = DIAGONAL_M
    attempts: int = ATTEMPTS
    creep_budget: int = CREEP_BUDGET
    trip: Trip | None = None
    creep: Creep | None = None
    tries: int = 0
    crept: int = 0
    #: "trip", "creep", then "docked" or "gave up"
    phase: str = "trip"
    #: whether its front has been seen unlinked (let go): a link there after that is the dock
    loose: bool = False
    events: list[tuple[str, str]] = field(default_factory=list)

    @property
    def target(self) -> End:
        return self.set_off.target, self.set_off.connector

    @property
    def done(self) -> bool:
        return self.phase in ("docked", "gave up")

    def step(self, floor: FloorPoses, infrared: Mapping[str, float], front_linked: bool) -> dict[int, float]:
        """This cycle's joint targets (DOF index -> degrees; empty once done) from the
        tracker's ``floor``, the foot's own ``infrared`` pairs and whether its front is linked."""
        if self.done:
            return {}
        if not front_linked:
            self.loose = True
        elif not self.loose:  # still hanging on the body: the release comes first
            return {}
        else:
            self._end("docked", f"front linked after {self.crept} cycles of creeping")
            return {}
        if self.phase == "creep":
            return self._step_creep(infrared)
        if not floor.modules:  # no report yet (the tracker's latency): wait, still
            return {0: 0.0, 1: 0.0}
        try:
            return self._step_trip(floor)
        except TrackerMissing as exc:
            self._event("trip_gave_up", str(exc))
            return self._again()

    def _step_trip(self, floor: FloorPoses) -> dict[int, float]:
        if self.trip is None:
            self.tries += 1
            body, others = list(self.set_off.body), list(self.set_off.others)
            self.trip = trip_to(
                floor,
                self.module,
                self.target,
                model=self.model,
                body=lambda: body,
                others=lambda: others,
                diagonal_m=self.diagonal_m,
            )
        trip = self.trip
        d1, d2 = trip.step(floor)
        if not trip.done:
            return {0: d1, 1: d2}
        if not trip.arrived:
            self._event("trip_gave_up", f"after {trip.cycles} cycles ({trip.account()})")
            return self._again()
        s, lat, _ = trip.state()
        self._event("trip_arrived", f"after {trip.cycles} cycles ({s * 100:+.1f} cm along, {lat * 100:+.1f} cm aside)")
        self.phase, self.creep, self.crept = "creep", Creep(self.module), 0
        return {0: 0.0, 1: 0.0}

    def _step_creep(self, infrared: Mapping[str, float]) -> dict[int, float]:
        assert self.creep is not None
        self.crept += 1
        if self.crept > self.creep_budget:
            self._event("creep_gave_up", f"front unlinked after {self.creep_budget} cycles")
            return self._again()
        d1, d2 = self.creep.step(Readings(infrared={self.module: infrared}))
        return {0: d1, 1: d2}

    def _again(self) -> dict[int, float]:
        """Round again from where it is, or give up after the last try."""
        self.trip, self.creep, self.phase = None, None, "trip"
        if self.tries >= self.attempts:
            self._end("gave up", f"{self.tries} trips")
        return {}

    def _event(self, kind: str, detail: str) -> None:
        self.events.append((kind, detail))

    def _end(self, phase: str, detail: str) -> None:
        self.phase = phase
        self._event(phase.replace(" ", "_"), detail)
