"""A ``reach_and_dock`` carried out by the asking module (firmware.motion.assimilating), on
plain numbers: links in a table, ideal servos, frames carried at once, the tracker's report
and the face's infrared pair set by the test, the latch scripted.

The robot: a snake 0-1-2-3 (k's back on k+1's front; 3 is the tail, its back the face) and a
leg 4 hanging by its front on 1's left. The tail learns the route to the foot and the body up
its front links, hands the foot its SET_OFF until the foot lets go, sends nothing while the
foot is on its way, squares its face when the tracker shows the foot parked behind it, and
latches; a squaring that does not latch waits for the foot to leave the spot and come back."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import pytest

from dh2rt.profile import CONRO
from dh2rt.wire import motion as mw
from firmware.motion.asker import Asker
from firmware.motion.assimilating import (
    DARK_CYCLES,
    PARKED_CYCLES,
    PARKED_HEADING_DEG,
    PARKED_STEADY_DEG,
    STILL_CYCLES,
    SelfAssimilate,
)
from firmware.motion.body import DEFAULT_MODEL
from firmware.motion.crawl import parked
from firmware.motion.readings import FloorPoses, ModulePose, PartPose
from tests.firmware.test_self_reach import NOTHING, Robot

C = CONRO.connector_index
FRONT, BACK, LEFT = C("front"), C("back"), C("left")
ROUTE = (FRONT, FRONT, LEFT)
#: centre to centre of two modules docked front to back, lying straight
PITCH = DEFAULT_MODEL.length + DEFAULT_MODEL.front.half[0] + DEFAULT_MODEL.back.half[0]


def lying(x: float, y: float = 0.0) -> ModulePose:
    """A module lying straight along the arena's x axis, its front towards +x."""
    half = DEFAULT_MODEL.length / 2 + DEFAULT_MODEL.front.half[0]
    return ModulePose(PartPose(x, y, 0.0), PartPose(x + half, y, 0.0), PartPose(x - half, y, 0.0))


@dataclass
class Legged(Robot):
    """The robot of the module docs, the tracker's report set by the test."""

    report: dict[int, ModulePose] = field(default_factory=dict)
    #: the foot's infrared emitter is on: the face's pair sees it within 85 mm (foot_at)
    foot_lit: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        del self.links[(3, BACK)], self.links[(4, FRONT)]  # 4 is the leg, not the snake's fifth
        self.links[(1, LEFT)], self.links[(4, FRONT)] = (4, FRONT), (1, LEFT)
        self.report = {m: lying(-m * PITCH) for m in range(4)} | {4: lying(-PITCH, 0.3)}

    def floor(self) -> FloorPoses:
        return FloorPoses(dict(self.report))

    def foot_at(self, behind_m: float) -> None:
        """The foot lying straight behind the tail, its front ``behind_m`` from the face."""
        floor = self.floor()
        fx, _, _, _ = floor.face(DEFAULT_MODEL, 3, "back")
        probe = FloorPoses({4: lying(0.0)})
        front_x, _, _, _ = probe.face(DEFAULT_MODEL, 4, "front")
        self.report[4] = lying(fx - behind_m - front_x)
        self.ir = (behind_m * 1000, 3.0) if self.foot_lit and behind_m <= 0.085 else NOTHING

    def cut(self, a: int, connector: int) -> None:
        peer = self.links.pop((a, connector))
        del self.links[peer]

    def run(self, reach: SelfAssimilate, cycle: int) -> int:
        """One cycle as the asking module's host runs it; the frames it sent."""
        outs = reach.step(cycle)
        self.deliver(self.asking, outs, cycle)
        me = self.members[self.asking]
        for report in me.reports:
            reach.received(report, cycle)
        me.reports.clear()
        for m, member in enumerate(self.members):
            member.cycle(cycle)
            held = reach.own_targets if m == self.asking else member.held
            pos = list(self.joints.get(m, (0.0, 0.0)))
            for dof, v in held.items():
                pos[dof] = v
            self.joints[m] = (pos[0], pos[1])
        return len(outs)


def assimilate(robot: Legged, route: tuple[int, ...] = ROUTE) -> SelfAssimilate:
    motions = iter(range(20, 40))
    to_foot = Asker(10, 3, robot.status(3), route, 0, log=robot.log.append)
    body = Asker(11, 3, robot.status(3), (FRONT,) * 16, 0, log=robot.log.append)
    return SelfAssimilate(
        to_foot,
        body,
        BACK,
        robot,
        robot,
        DEFAULT_MODEL,
        CONRO,
        robot.log.append,
        own_links=lambda: robot.status(3),
        next_motion=lambda: next(motions),
    )


def handed_over(robot: Legged, reach: SelfAssimilate) -> int:
    """Run the reach until the foot let go (its link cut when the SET_OFF reaches it) and the
    tail waits: the next cycle."""
    cycle = 0
    while reach.phase != "hand over":
        robot.run(reach, cycle)
        cycle += 1
    robot.cut(4, FRONT)
    while reach.phase != "waiting":
        robot.run(reach, cycle)
        cycle += 1
    return cycle


def squared_in_vain(robot: Legged, reach: SelfAssimilate) -> int:
    """Hand the foot over, park it 4 cm behind the face, and let the squaring that follows give
    up unlatched; the cycle after, the tail waiting for the foot to come round again."""
    cycle = handed_over(robot, reach)
    robot.foot_at(0.04)
    for _ in range(PARKED_CYCLES):
        robot.run(reach, cycle)
        cycle += 1
    assert reach.phase == "squaring" and reach.docking is None
    while reach.docking is None:
        cycle += 1
        robot.run(reach, cycle)
    reach.docking.motions[0].reach.timeout = reach.docking.motions[0].reach.cycles + 1  # it gives up now
    for _ in range(3):
        cycle += 1
        robot.run(reach, cycle)
    assert reach.phase == "waiting" and reach.squarings == 1 and not robot.latches, robot.log
    return cycle


def test_parked_is_where_a_trip_ends() -> None:
    robot = Legged(5, asking=3)
    robot.foot_at(0.04)
    assert parked(robot.floor(), DEFAULT_MODEL, 4, (3, BACK))
    robot.foot_at(0.30)  # still on its way
    assert not parked(robot.floor(), DEFAULT_MODEL, 4, (3, BACK))
    robot.foot_at(0.04)
    foot = robot.report[4]
    centre, front, back = (PartPose(p.x, p.y, 0.5) for p in (foot.centre, foot.front, foot.back))
    robot.report[4] = ModulePose(centre, front, back)
    assert not parked(robot.floor(), DEFAULT_MODEL, 4, (3, BACK))  # not squared


def test_the_tail_hands_the_foot_over_waits_squares_and_latches() -> None:
    robot = Legged(5, asking=3)
    reach = assimilate(robot)
    cycle = 0
    while reach.phase == "learn":
        robot.run(reach, cycle)
        cycle += 1
        assert cycle < 10 and not reach.done, robot.log
    assert reach.foot == 4 and reach.body == [3, 2, 1, 0]
    assert reach.phase == "hand over"

    robot.run(reach, cycle)  # the SET_OFF reaches the foot: come to the tail's back
    set_off = robot.members[4].set_off
    assert isinstance(set_off, mw.SetOff)
    assert (set_off.target, set_off.connector, set_off.body, set_off.others) == (3, BACK, (3, 2, 1, 0), ())
    robot.members[4].set_off = None
    cycle += 1
    robot.run(reach, cycle)
    assert robot.members[4].set_off is not None  # sent again until the foot lets go
    robot.cut(4, FRONT)  # it lets go
    for _ in range(3):
        cycle += 1
        robot.run(reach, cycle)
    assert reach.phase == "waiting", robot.log

    robot.foot_at(0.40)  # on its way: nothing goes on the links
    assert [robot.run(reach, cycle + k) for k in range(1, 6)] == [0] * 5
    cycle += 6
    robot.foot_at(0.04)  # parked behind the face: after PARKED_CYCLES in a row, the square-up
    for _ in range(PARKED_CYCLES - 1):
        robot.run(reach, cycle)
        cycle += 1
    assert reach.phase == "waiting"
    robot.run(reach, cycle)
    assert reach.phase == "squaring" and reach.squaring is not None
    while reach.docking is None:
        cycle += 1
        robot.run(reach, cycle)
        assert cycle < 60, robot.log
    assert reach.squaring.route == (FRONT, FRONT)  # the last two modules up the robot
    cycle += 1
    robot.run(reach, cycle)
    assert robot.members[2].held and reach.own_targets  # squaring: the tail's joints and m2's, by TARGETS
    robot.ir = (12.0, 5.0)  # the foot's front in view, within the tolerance
    for _ in range(3):
        cycle += 1
        robot.run(reach, cycle)
    assert robot.latches == [(3, BACK, 4, FRONT)] and reach.verdict == "linked", robot.log
    assert all(member.held == {} for member in robot.members)  # END to every member
    assert any("reach_dock m3.back -> m4.front: latched" in line for line in robot.log), robot.log


def turned(pose: ModulePose, degrees: float) -> ModulePose:
    """``pose`` turned in place about its centre by ``degrees``."""
    h = math.radians(degrees)
    c = pose.centre

    def part(p: PartPose) -> PartPose:
        dx, dy = p.x - c.x, p.y - c.y
        return PartPose(
            c.x + dx * math.cos(h) - dy * math.sin(h), c.y + dx * math.sin(h) + dy * math.cos(h), p.heading + h
        )

    return ModulePose(part(c), part(pose.front), part(pose.back))


@pytest.mark.parametrize("rock", [PARKED_STEADY_DEG + 1.0, 2 * PARKED_STEADY_DEG, PARKED_HEADING_DEG - 1.0])
def test_a_foot_turning_in_place_in_the_parking_window_is_not_parked_until_it_stands_square(rock: float) -> None:
    """A foot in the parking window still turning to square itself (its heading rocking
    within the window's 15 degrees) has not arrived: the face squaring at it moves the spot it
    steers for (legs to snake in physics, seeds 3 and 9). Its heading steady for
    PARKED_CYCLES, it has."""
    robot = Legged(5, asking=3)
    reach = assimilate(robot)
    cycle = handed_over(robot, reach)
    robot.foot_at(0.04)
    square = robot.report[4]
    robot.ir = NOTHING  # the tracker's report alone: the pair reads its alignment only when it sees
    for k in range(4 * PARKED_CYCLES):  # rocking: the heading runs up and down `rock` apart
        robot.report[4] = turned(square, -rock / 2 + rock * (k % 4) / 3)
        assert parked(robot.floor(), DEFAULT_MODEL, 4, (3, BACK), heading_deg=PARKED_HEADING_DEG)
        robot.run(reach, cycle)
        cycle += 1
        assert reach.phase == "waiting", (k, robot.log)
    for k in range(PARKED_CYCLES):  # it stands square, to within the tracker's wobble
        robot.report[4] = turned(square, 1.5 * (-1) ** k)  # a tracker's noise of a degree or so
        robot.run(reach, cycle)
        cycle += 1
    assert reach.phase == "squaring", robot.log


def test_a_squaring_that_does_not_latch_waits_for_the_foot_to_come_round_again() -> None:
    robot = Legged(5, asking=3)
    reach = assimilate(robot)
    cycle = squared_in_vain(robot, reach)
    cycle += 1
    robot.run(reach, cycle)
    assert reach.phase == "waiting"  # the foot still lies there: its creep runs out first
    robot.foot_at(0.10)  # off the window for a moment: not gone round yet
    cycle += 1
    robot.run(reach, cycle)
    robot.foot_at(0.04)
    for _ in range(PARKED_CYCLES + 2):
        cycle += 1
        robot.run(reach, cycle)
    assert reach.phase == "waiting"
    robot.foot_at(0.12)  # it went round again: off the window for PARKED_CYCLES in a row
    for _ in range(PARKED_CYCLES):
        cycle += 1
        robot.run(reach, cycle)
    robot.foot_at(0.04)  # and is back
    for _ in range(PARKED_CYCLES):
        cycle += 1
        robot.run(reach, cycle)
    assert reach.phase == "squaring"


def test_a_foot_that_does_not_hang_by_its_front_is_refused() -> None:
    robot = Legged(5, asking=3)
    robot.cut(1, LEFT)
    robot.links[(1, LEFT)], robot.links[(4, BACK)] = (4, BACK), (1, LEFT)
    reach = assimilate(robot)
    for cycle in range(8):
        robot.run(reach, cycle)
    assert reach.verdict == "the foot does not hang by its front"
    assert robot.members[4].set_off is None


def test_a_foot_that_lies_still_on_its_way_ends_the_dock() -> None:
    """A foot on its trip always crawls or turns: one the tracker shows still for STILL_CYCLES
    (it died, or is stuck) ends the wait, not linked, and the tail can ask for the next."""
    robot = Legged(5, asking=3)
    reach = assimilate(robot)
    cycle = handed_over(robot, reach)
    for k in range(2 * STILL_CYCLES):  # crawling on its way: 8 cm a 100 cycles
        robot.foot_at(0.30 + 0.0008 * k)
        robot.run(reach, cycle)
        cycle += 1
    assert not reach.done
    for _ in range(2 * STILL_CYCLES + 2):  # then lying still
        robot.run(reach, cycle)
        cycle += 1
    assert reach.verdict == f"not linked: module 4 hardly moved in {STILL_CYCLES} cycles (dead or stuck)"


def test_a_foot_that_backs_off_and_comes_back_within_the_window_has_moved() -> None:
    """Still is judged by how far the foot went in the window, not where it ends: a foot that
    backed off 8 cm and came back to where it was (seed 2 in physics, its second round) is
    alive and is not given up."""
    robot = Legged(5, asking=3)
    reach = assimilate(robot)
    cycle = handed_over(robot, reach)
    robot.foot_at(0.30)
    for k in range(3 * STILL_CYCLES):  # out 8 cm and back again, each STILL_CYCLES
        robot.foot_at(0.30 + 0.08 * (1 - abs((k % STILL_CYCLES) / (STILL_CYCLES / 2) - 1)))
        robot.run(reach, cycle)
        cycle += 1
    assert not reach.done, robot.log


def test_after_a_squaring_that_did_not_latch_a_foot_that_backed_off_inside_the_window_has_gone_round() -> None:
    """The foot's trip backs it off 8 cm and brings it back; when it is off the parking window
    for fewer than PARKED_CYCLES on the way (seed 2 in physics: back in 79 cycles, never
    off it), the tracker showing its front BACKED_OFF_M from where it lay tells the tail it
    went round again, and it squares again."""
    robot = Legged(5, asking=3)
    reach = assimilate(robot)
    cycle = squared_in_vain(robot, reach)
    off = 0
    for behind in (0.06, 0.08, 0.10, 0.115, 0.08, 0.06):  # off the window for fewer than PARKED_CYCLES
        robot.foot_at(behind)
        off += 3 * (not parked(robot.floor(), DEFAULT_MODEL, 4, (3, BACK), heading_deg=180.0))
        for _ in range(3):
            cycle += 1
            robot.run(reach, cycle)
    assert 0 < off < PARKED_CYCLES
    robot.foot_at(0.04)
    for _ in range(PARKED_CYCLES):
        cycle += 1
        robot.run(reach, cycle)
    assert reach.phase == "squaring", robot.log


@pytest.mark.parametrize("dies", ["waiting", "squaring"])
def test_a_foot_in_sight_whose_pair_is_dark_ends_the_dock(dies: str) -> None:
    """The infrared pairs are active: a foot the tracker shows right behind the face that the
    face's pair does not see has no power. DARK_CYCLES in a row end the dock, not linked, as
    it waits or as it squares; a lit foot there does not, nor an unseen one that moves (a live
    foot creeping lifts its front out of the pair's cone)."""
    robot = Legged(5, asking=3)
    reach = assimilate(robot)
    cycle = handed_over(robot, reach)
    robot.foot_at(0.04)  # lit: the face's pair sees it
    while reach.phase == "waiting":
        robot.run(reach, cycle)
        cycle += 1
        assert cycle < 100, robot.log
    if dies == "waiting":  # a squaring that does not latch: it waits again, the foot still there
        while reach.docking is None:
            cycle += 1
            robot.run(reach, cycle)
        reach.docking.motions[0].reach.timeout = reach.docking.motions[0].reach.cycles + 1
        while reach.phase == "squaring":
            cycle += 1
            robot.run(reach, cycle)
    for _ in range(3 * DARK_CYCLES):  # lit all along: nothing ends
        cycle += 1
        robot.run(reach, cycle)
    assert reach.phase == dies and not reach.done, robot.log
    for k in range(3 * DARK_CYCLES):  # unseen but creeping (its front lifted out of the cone)
        robot.foot_at(0.04 + (0.005 if k % 2 else 0.0))
        robot.ir = NOTHING
        cycle += 1
        robot.run(reach, cycle)
    assert reach.phase == dies and not reach.done, robot.log
    robot.foot_at(0.04)  # seen again
    cycle += 1
    robot.run(reach, cycle)
    robot.foot_lit, robot.ir = False, NOTHING  # its emitter goes dark, and it lies still
    for _ in range(DARK_CYCLES - 1):
        cycle += 1
        robot.run(reach, cycle)
    assert not reach.done
    cycle += 1
    robot.run(reach, cycle)
    assert reach.verdict == "not linked: module 4 lies in the face's sight and its infrared is dark (no power)"
    assert all(member.held == {} for member in robot.members)  # END to every member
