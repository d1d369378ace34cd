"""A released foot's own part of reach_and_dock (firmware.motion.foot), on plain numbers: it
sets off from a SET_OFF by the tracker's poses, creeps on its front infrared once arrived, is
docked when its front links, and goes round again (trip or creep out of budget, the tracker
missing a module) up to its attempts, then gives up."""

from __future__ import annotations

from dh2rt.docking import body_up, off_path
from dh2rt.profile import CONRO
from dh2rt.wire import motion as mw
from dh2rt.wire.motion import SetOff
from firmware.motion.body import DEFAULT_MODEL
from firmware.motion.crawl import Trip
from firmware.motion.docking import BRING_ATTEMPTS
from firmware.motion.foot import ATTEMPTS, Foot, hand_over
from firmware.motion.readings import FloorPoses, ModulePose, PartPose

BACK = 2
#: The robot: tail 20 (its back the face), then 21, 22 up the body; the foot 30 lies 50 cm
#: behind the tail, facing it; 40 a leg off the path.
SET_OFF = SetOff(9, 1, ((BACK, 1),), 20, BACK, (20, 21, 22), (40,))


def lying(x: float, y: float = 0.0, facing_x: bool = True) -> ModulePose:
    half = DEFAULT_MODEL.length / 2 + DEFAULT_MODEL.front.half[0]
    h, d = (0.0, half) if facing_x else (3.14159, -half)
    return ModulePose(PartPose(x, y, h), PartPose(x + d, y, h), PartPose(x - d, y, h))


def floor(without: int | None = None) -> FloorPoses:
    poses = {20: lying(0.0), 21: lying(0.15), 22: lying(0.30), 40: lying(0.30, 0.2), 30: lying(-0.5)}
    return FloorPoses({m: p for m, p in poses.items() if m != without})


def arrives(trip: Trip) -> None:
    """The trip arrives at its next step (its walk is the trip's own tests', in physics)."""
    trip.done = trip.arrived = True
    trip.step = lambda floor: (0.0, 0.0)  # type: ignore[method-assign]


def test_one_rule_for_the_attempts_in_one_process_and_in_the_foot() -> None:
    assert BRING_ATTEMPTS == ATTEMPTS == 3


def test_the_foot_waits_for_the_tracker_then_walks_its_trip_by_it() -> None:
    foot = Foot(30, SET_OFF)
    assert foot.step(FloorPoses(), {}, False) == {0: 0.0, 1: 0.0} and foot.trip is None
    targets = foot.step(floor(), {}, False)
    assert foot.trip is not None and foot.phase == "trip" and foot.tries == 1
    assert foot.trip.target == (20, BACK) and foot.trip.body is not None and foot.trip.body() == [20, 21, 22]
    assert foot.trip.others is not None and foot.trip.others() == [40]
    assert set(targets) == {0, 1} and targets != {0: 0.0, 1: 0.0}  # it backs off: its joints move


def test_arrived_it_creeps_on_its_front_infrared_holds_close_and_is_docked_when_its_front_links() -> None:
    foot = Foot(30, SET_OFF)
    foot.step(floor(), {}, False)
    assert foot.trip is not None
    arrives(foot.trip)
    assert foot.step(floor(), {}, False) == {0: 0.0, 1: 0.0} and foot.phase == "creep"
    assert foot.events[-1][0] == "trip_arrived"
    creeping = foot.step(floor(), {"ir_front": 0.0}, False)
    assert creeping != {0: 0.0, 1: 0.0}
    assert foot.step(floor(), {"ir_front": 10.0}, False) == {0: 0.0, 1: 0.0}  # within HOLD_MM: square, still
    assert foot.step(floor(), {"ir_front": 10.0}, True) == {} and foot.done and foot.phase == "docked"
    assert foot.events[-1] == ("docked", "front linked after 2 cycles of creeping")


def test_a_creep_no_latch_ends_sends_it_round_again() -> None:
    foot = Foot(30, SET_OFF, creep_budget=5)
    foot.step(floor(), {}, False)
    assert foot.trip is not None
    arrives(foot.trip)
    foot.step(floor(), {}, False)
    for _ in range(5):
        foot.step(floor(), {"ir_front": 30.0}, False)
    assert foot.phase == "creep"
    assert foot.step(floor(), {"ir_front": 30.0}, False) == {} and foot.phase == "trip"
    assert foot.events[-1] == ("creep_gave_up", "front unlinked after 5 cycles")
    foot.step(floor(), {}, False)
    assert foot.tries == 2 and foot.trip is not None and not foot.trip.done


def test_trips_out_of_budget_or_a_module_the_tracker_lost_end_in_giving_up_after_the_attempts() -> None:
    foot = Foot(30, SET_OFF)
    foot.step(floor(), {}, False)
    assert foot.trip is not None
    foot.trip.budget = foot.trip.cycles  # its next step is past its budget
    assert foot.step(floor(), {}, False) == {} and foot.events[-1][0] == "trip_gave_up"
    foot.step(floor(without=30), {}, False)  # the tracker lost the foot: named, a try gone
    assert foot.events[-1][0] == "trip_gave_up" and "module 30" in foot.events[-1][1]
    assert foot.tries == 2 and not foot.done
    foot.step(floor(), {}, False)
    assert foot.trip is not None
    foot.trip.budget = foot.trip.cycles
    foot.step(floor(), {}, False)
    assert foot.done and foot.phase == "gave up" and foot.events[-1] == ("gave_up", "3 trips")
    assert foot.step(floor(), {}, False) == {}


def test_a_foot_still_hanging_on_the_body_waits_for_its_release() -> None:
    """Its front linked before it ever let go is the body it hangs on, not a dock."""
    foot = Foot(30, SET_OFF)
    assert foot.step(floor(), {}, True) == {} and not foot.done and foot.trip is None
    assert foot.step(floor(), {}, False) != {} and foot.loose


def test_the_hand_over_names_off_the_path_by_the_tracker_what_the_link_map_would() -> None:
    """A tail (0) up a spine (1, 2) with a leg (4) on 2 and the foot (3) on 1, a module lying
    apart (5): the SET_OFF's body is dh2rt.docking.body_up's and its others off_path's, read
    from the tracker's report instead of the world's link map."""
    front, back, left, right = (CONRO.connector_index(c) for c in ("front", "back", "left", "right"))
    links = {(0, front): (1, back), (1, front): (2, back), (4, front): (2, left), (3, front): (1, right)}
    links |= {b: a for a, b in links.items()}
    tracked = FloorPoses({m: lying(0.1 * m) for m in range(6)})
    body = body_up(links.get, CONRO, 0)
    set_off = hand_over(9, 1, ((left, front),), (0, back), body, tracked, 3)
    assert set_off.body == (0, 1, 2) and (set_off.target, set_off.connector) == (0, back)
    assert list(set_off.others) == off_path(links.get, CONRO, 0, 6, 3) == [4, 5]
    assert mw.decode(mw.encode(left, set_off)).message == set_off
