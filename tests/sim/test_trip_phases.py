"""firmware.motion.crawl.Trip's choices of where to go, on a floor held still (no physics).

The tail lies along +x with its back face at the origin (normal -x); the foot's front is put
where each test says, its heading along +x unless said. Trip reads only the tracker's poses, so a
table of poses is its whole world here; what the gaits then do on the floor is measured in
tests/sim/test_foot_to_tail_physics.py and tests/sim/test_legs_to_snake_physics.py.
"""

from __future__ import annotations

import math

import pytest

from firmware.motion.body import DEFAULT_MODEL
from firmware.motion.crawl import (
    ACROSS_BEHIND_M,
    ALONGSIDE_M,
    DIAGONAL_LEAN_DEG,
    DIAGONAL_M,
    OBSTACLE_CLEAR_M,
    Trip,
)
from firmware.motion.gaits import back_off, turn
from firmware.motion.readings import FloorPoses, ModulePose, PartPose

FOOT, TAIL, LEG = 0, 1, 2
#: Centres of the tail's modules up the robot from the face (m).
BODY = {TAIL: (0.05, 0.0), 3: (0.155, 0.0), 4: (0.26, 0.0), 5: (0.365, 0.0)}


class StillWorld:
    """What the overhead tracker would report, set by hand: the foot's front face and heading,
    the tail's back face at the origin (normal -x), the body's and the leg's centres."""

    def __init__(self, front: tuple[float, float], heading_deg: float = 0.0) -> None:
        self.front = front
        self.heading = math.radians(heading_deg)
        self.leg = (0.30, 0.065)

    def floor(self) -> FloorPoses:
        h = self.heading
        fx = DEFAULT_MODEL.front.half[0]
        front = PartPose(self.front[0] - fx * math.cos(h), self.front[1] - fx * math.sin(h), h)
        modules = {FOOT: ModulePose(PartPose(front.x, front.y, h), front, PartPose(front.x, front.y, h))}
        for m, (x, y) in {**BODY, LEG: self.leg}.items():
            centre = PartPose(x, y, 0.0)
            modules[m] = ModulePose(centre, centre, centre)
        # the tail's back face at the origin, facing -x: its back part's centre half a box behind
        back = PartPose(DEFAULT_MODEL.back.half[0], 0.0, 0.0)
        modules[TAIL] = ModulePose(modules[TAIL].centre, modules[TAIL].front, back)
        return FloorPoses(modules)


def trip(world: StillWorld, *, leg: bool = False) -> Trip:
    t = Trip(
        world.floor(),
        FOOT,
        (TAIL, 2),  # its back
        body=lambda: [TAIL, 3, 4, 5],
        others=(lambda: [LEG]) if leg else (lambda: []),
    )
    t.phase = "along"  # past the back-off
    return t


AIM = -0.03 - 0.03  # park [0] less the margin: where the line along used to end


def early(lat: float) -> float:
    """How far before the line's end (m) a foot ``lat`` beside the axis starts across."""
    return min(DIAGONAL_M, (lat - 0.005) / math.tan(math.radians(DIAGONAL_LEAN_DEG)))


@pytest.mark.parametrize("lat", [0.10, 0.05])
@pytest.mark.parametrize("before", [0.005, 0.05, 0.5])
def test_the_foot_starts_across_before_the_line_ends(lat: float, before: float) -> None:
    """On its line (10 cm out) it starts across about 20 cm before the line's end, leaning
    in about 25 degrees; closer to the robot, later, so that it leans no more."""
    assert 0.18 < early(0.10) <= DIAGONAL_M and early(0.05) < 0.10
    s = AIM + before * early(lat)
    world = StillWorld((s, lat))
    t = trip(world)
    targets = t.step(world.floor())
    assert t.phase == "aside"
    want = math.degrees(math.atan2(lat - t.park[1], s - AIM))
    assert DIAGONAL_LEAN_DEG - 1 < want < 90
    assert targets == turn(t.cycles, +1), "8 degrees off or more: it turns towards its lean"


@pytest.mark.parametrize("lat", [0.10, 0.05])
def test_before_that_it_keeps_backing_along(lat: float) -> None:
    world = StillWorld((AIM + early(lat) + 0.01, lat))
    t = trip(world)
    t.step(world.floor())
    assert t.phase == "along"


def test_beside_the_target_module_and_close_to_it_it_backs_straight_along() -> None:
    """Its front still beside the tail and within ALONGSIDE_M of the axis, it does not lean
    in (its back would catch on the tail's end): heading straight, it backs off."""
    world = StillWorld((0.03, ALONGSIDE_M - 0.01))
    t = trip(world)
    t.phase = "aside"
    assert t.step(world.floor()) == back_off(t.cycles)
    world.front = (-0.01, ALONGSIDE_M - 0.01)  # past the face: in towards the spot
    assert t.step(world.floor()) == turn(t.cycles, +1)


def test_with_a_leg_on_the_body_near_it_goes_along_to_the_end() -> None:
    """The diagonal would cut the leg's corner: the line's end stays where it was."""
    world = StillWorld((AIM + 0.10, 0.10))
    world.leg = (AIM + 0.10 + 0.05, 0.065)
    t = trip(world, leg=True)
    t.step(world.floor())
    assert t.phase == "along"
    world.front = (AIM - 0.001, 0.17)
    t.step(world.floor())
    assert t.phase == "aside"


@pytest.mark.parametrize(
    ("hung", "where", "in_the_way"),
    [
        (0.66, (0.60, 0.145), True),
        (0.66, (0.72, 0.12), True),
        (0.66, (0.60, 0.10 + OBSTACLE_CLEAR_M), False),
        (0.20, (-0.05, 0.03), False),
        (0.20, (0.05, 0.13), True),
    ],
)
def test_a_module_lying_beside_the_robot_is_steered_round_like_a_leg(
    hung: float, where: tuple[float, float], in_the_way: bool
) -> None:
    """A foot that died on its way lies beside the robot where the next foot hangs (seed 11,
    the trip kill: the next foot turned in place between it and the body for 2,000 cycles).
    The next foot backs off on out past it, its front OBSTACLE_CLEAR_M beyond its centre,
    before it sets off along, as past a leg on the body. Further out than that from the foot's
    line, or beyond the face (a foot killed as it docked: the robot crawls clear of it
    first), it is not in the way."""
    world = StillWorld((hung, 0.03), heading_deg=-90.0)  # hanging, its front on the body
    world.leg = where  # the module lying apart, in the LEG slot of others
    t = Trip(world.floor(), FOOT, (TAIL, 2), body=lambda: [TAIL, 3, 4, 5], others=lambda: [LEG])
    world.front = (hung, 0.03 + t.backoff_m + 0.005)  # backed off its 8 cm
    t.step(world.floor())
    assert t.phase == ("back off" if in_the_way else "along")
    if in_the_way:
        assert t.step(world.floor()) == back_off(t.cycles)  # on out, away from the body
        world.front = (hung, where[1] + OBSTACLE_CLEAR_M)  # out past it
        t.step(world.floor())
        assert t.phase == "along"


@pytest.mark.parametrize(("behind", "turns_about"), [(0.02, False), (ACROSS_BEHIND_M - 0.005, False), (0.09, True)])
def test_a_little_too_far_back_it_moves_across_not_about(behind: float, turns_about: bool) -> None:
    """Straight across (its front to the outside, so that it backs in) unless it is more
    than ACROSS_BEHIND_M too far back: then it turns about to back towards the face."""
    world = StillWorld((AIM - behind, 0.06), heading_deg=90.0)
    t = trip(world)
    t.phase = "aside"
    targets = t.step(world.floor())
    assert t.phase == "aside"
    if turns_about:
        assert targets == turn(t.cycles, +1), "the spot is behind its back's side: it turns"
    else:
        assert targets == (45.0 + 40.0 * math.sin(2 * math.pi * t.cycles / 8), 0.0), "it backs across"


@pytest.mark.parametrize(("s", "lat", "square"), [(-0.05, 0.01, True), (-0.075, -0.012, True), (-0.05, 0.03, False)])
def test_it_squares_anywhere_in_the_box_behind_the_face(s: float, lat: float, square: bool) -> None:
    """Within 2 cm of the axis and 2 cm to 8 cm behind the face it stops moving across and
    squares; squared there it has arrived."""
    world = StillWorld((s, lat))
    t = trip(world)
    t.phase = "aside"
    t.step(world.floor())
    assert (t.phase == "square") is square
    assert t.arrived is square, "square already: arrived in the same cycle"
