"""A ``reach_dock`` carried out by the asking module (firmware.motion.asking.SelfReach) over
motion frames to its chain's members (firmware.motion.member.Member), on plain numbers: links
in a table, ideal servos, the asking face's infrared set by the test, the latch scripted.
The chain is learnt a hop at a time, each member holds the targets the same sequence gives
when it reads the world directly (firmware.motion.docking.Docking on the same readings), the
latch is asked and the members get their joints back; lost answers are counted and a member
that goes silent ends the motion."""

from __future__ import annotations

from dataclasses import dataclass, field

from dh2rt.docking import End
from dh2rt.profile import CONRO
from dh2rt.wire import motion as mw
from firmware.motion.asker import SILENT_CYCLES, Asker
from firmware.motion.asking import SelfReach
from firmware.motion.body import DEFAULT_MODEL
from firmware.motion.docking import Docking
from firmware.motion.member import Member
from firmware.motion.readings import FloorPoses, Readings
from firmware.motion.underway import Motion, Needs
from firmware.outbound import Out

C = CONRO.connector_index
FRONT, BACK = C("front"), C("back")
NOTHING = (0.0, 180.0)


@dataclass
class Robot:
    """Modules 0..n-1 in a snake (k's back on k+1's front), ideal servos, frames carried at
    once; module ``asking`` runs the reach."""

    n: int
    asking: int
    links: dict[End, End] = field(default_factory=dict)
    joints: dict[int, tuple[float, float]] = field(default_factory=dict)
    ir: tuple[float, float] = NOTHING
    latches: list[tuple[int, int, int, int]] = field(default_factory=list)
    log: list[str] = field(default_factory=list)
    #: modules whose frames are lost (a module that died, or a link that went)
    silent: set[int] = field(default_factory=set)
    #: frames and bytes each link carried, both ways: (lower module, higher) -> [frames, bytes]
    load: dict[tuple[int, int], list[int]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for k in range(self.n - 1):
            self.links[(k, BACK)], self.links[(k + 1, FRONT)] = (k + 1, FRONT), (k, BACK)
        self.members = [Member(m, ModuleBody(self, m), log=self.log.append) for m in range(self.n)]

    def status(self, m: int) -> tuple[int, ...]:
        return tuple(self.links.get((m, c), (0, 0))[1] for c in range(1, CONRO.connector_count + 1))

    def deliver(self, at: int, outs: list[Out], cycle: int) -> None:
        queue = [(at, o) for o in outs]
        while queue:
            at, out = queue.pop(0)
            if at in self.silent:
                continue
            peer = self.links.get((at, out.connector))
            if peer is None or peer[0] in self.silent:
                continue
            link = self.load.setdefault((min(at, peer[0]), max(at, peer[0])), [0, 0])
            link[0] += 1
            link[1] += len(out.frame)
            to, connector = peer
            queue.extend((to, o) for o in self.members[to].received(connector, out.frame, cycle))

    # the asking module's own senses (firmware.motion.asking.OwnSenses)
    def angles(self) -> tuple[float, ...]:
        return self.joints.get(self.asking, (0.0, 0.0))

    def infrared(self) -> dict[str, float]:
        out = {}
        for c in DEFAULT_MODEL.connectors:
            mm, deg = self.ir if c.name == "back" else NOTHING
            out.update({f"ir_{c.name}": mm, f"ir_{c.name}_align": deg})
        return out

    def floor(self) -> FloorPoses:
        return FloorPoses()

    def attitude(self) -> dict[int, tuple[float, float]]:
        return {}

    # the latch, asked of the world
    def aligned(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        return True

    def latch(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        self.latches.append((a, a_conn, b, b_conn))
        self.links[(a, a_conn)], self.links[(b, b_conn)] = (b, b_conn), (a, a_conn)
        return True

    def step(self, reach: SelfReach, cycle: int) -> None:
        """One cycle: the asker's frames and what they set off; the answers it got; every
        module's servos go where they are held (the asker's own, the members')."""
        self.deliver(self.asking, reach.step(cycle), cycle)
        me = self.members[self.asking]
        for report in me.reports:
            reach.asker.received(report, cycle)
        me.reports.clear()
        for m, member in enumerate(self.members):
            member.cycle(cycle)
            held = reach.own_targets if m == self.asking else member.held
            pos = list(self.joints.get(m, (0.0, 0.0)))
            for dof, v in held.items():
                pos[dof] = v
            self.joints[m] = (pos[0], pos[1])


@dataclass
class ModuleBody:
    robot: Robot
    module: int

    def angles(self) -> tuple[float, ...]:
        return self.robot.joints.get(self.module, (0.0, 0.0))

    def links(self) -> tuple[int, ...]:
        return self.robot.status(self.module)


def self_reach(robot: Robot, route: tuple[int, ...], connector: int, target_conn: int) -> SelfReach:
    asker = Asker(7, robot.asking, robot.status(robot.asking), route, 0, log=robot.log.append)
    return SelfReach(asker, connector, target_conn, robot, robot, DEFAULT_MODEL, CONRO, robot.log.append)


class Direct:
    """The same sequence with the world read directly (as the physics runner owns it)."""

    def __init__(self, robot: Robot) -> None:
        self.robot = robot
        self.cycle = 0

    @property
    def now(self) -> int:
        return self.cycle

    def sense(self, cycle: int, needs: Needs) -> Readings:
        joints = {m: self.robot.joints.get(m, (0.0, 0.0)) for m in needs.joints}
        return Readings(joints, {m: self.robot.infrared() for m in needs.infrared})

    def ended(self, motion: Motion, linked: bool, readings: Readings) -> None:
        pass


def test_the_asker_learns_its_chain_moves_it_by_frames_and_latches() -> None:
    robot = Robot(3, asking=2)
    reach = self_reach(robot, (FRONT, FRONT), BACK, FRONT)
    robot.step(reach, 0)  # m1 answers; its links lead on to m0
    assert [m.module for m in reach.asker.members] == [1, None]
    robot.step(reach, 1)  # m0 answers too: the chain is known
    assert reach.asker.known and reach.docking is None
    assert reach.asker.peer_of(2, FRONT) == (1, BACK) and reach.asker.peer_of(1, FRONT) == (0, BACK)
    assert reach.asker.peer_of(0, FRONT) is None  # the target face is free

    # the same sequence reading the world directly, from the same joints
    direct_owner = Direct(robot)
    direct_owner.cycle = 2
    direct = Docking(DirectWorld(robot), direct_owner, DEFAULT_MODEL, CONRO, ["m0", "m1", "m2"])
    assert direct.start_reach(2, BACK, (FRONT, FRONT), FRONT)
    expected = direct.step(2)

    robot.step(reach, 2)  # planned and stepped: every member holds its targets
    assert reach.docking is not None and reach.docking.busy
    for m in (0, 1):
        assert robot.members[m].held == {dof: round(v, 2) for dof, v in expected[m].items()}, m
    assert reach.own_targets == expected[2]
    for cycle in (3, 4):
        robot.step(reach, cycle)
    assert not robot.latches
    robot.ir = (12.0, 5.0)  # the face in view, within the tolerance
    robot.step(reach, 5)
    robot.step(reach, 6)
    assert robot.latches == [(2, BACK, 0, FRONT)] and reach.verdict == "linked"
    assert all(member.held == {} and member.holding is None for member in robot.members)  # END
    assert reach.own_targets == {}
    assert reach.asker.counts["unanswered"] == 0 and reach.asker.counts["stale"] == 0
    assert any("m2.back -> m0.front: latched" in line for line in robot.log)


@dataclass
class DirectWorld:
    robot: Robot

    def peer_of(self, end: End) -> End | None:
        return self.robot.links.get(end)

    def running(self, module: int) -> bool:
        return True

    def aligned(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        return True

    def latch(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        raise AssertionError("only stepped once")

    def cut(self, module: int, connector: int) -> None:
        raise AssertionError

    def dock(self, a: int, a_conn: int, b: int, b_conn: int) -> None:
        raise AssertionError

    def schedule(self, cycles_from_now: int, action: object) -> None:
        raise AssertionError

    def where(self, module: int, connector: int) -> str:
        return f"m{module}.{CONRO.connector_name(connector)}"

    def note(self, message: str) -> None:
        pass


def test_lost_answers_are_counted_and_a_silent_member_ends_the_motion() -> None:
    robot = Robot(3, asking=2)
    reach = self_reach(robot, (FRONT, FRONT), BACK, FRONT)
    for cycle in range(4):
        robot.step(reach, cycle)
    assert reach.docking is not None and reach.docking.busy and robot.members[0].holding == 7
    robot.silent.add(0)  # m0 dies: nothing of it, nothing to it
    cycle = 4
    while not reach.done:
        robot.step(reach, cycle)
        cycle += 1
        assert cycle < 4 + SILENT_CYCLES + 5
    assert reach.verdict == "abandoned: a member of the chain went silent"
    assert reach.asker.counts["unanswered"] >= SILENT_CYCLES - 20
    assert robot.members[1].held == {} and not robot.latches
    assert any("motion abandoned" in line for line in robot.log)


def test_a_route_through_a_connector_with_no_link_is_refused_at_once() -> None:
    robot = Robot(2, asking=1)
    try:
        self_reach(robot, (BACK,), FRONT, FRONT)
    except ValueError as exc:
        assert "connector 2, which has no link" in str(exc)
    else:
        raise AssertionError("a route through nothing was taken")


def test_the_link_load_of_a_reach() -> None:
    """Frames and bytes a cycle a reach puts on its busiest link, the asker's first: an ASK
    and a TARGETS for each member out, each member's ANGLES back."""
    robot = Robot(5, asking=4)  # four members
    reach = self_reach(robot, (FRONT,) * 4, BACK, FRONT)  # to m0's front
    for cycle in range(11):
        robot.step(reach, cycle)
    assert reach.docking is not None and reach.docking.busy, robot.log
    robot.load.clear()
    robot.step(reach, 11)
    frames, size = robot.load[(3, 4)]
    assert max(robot.load.values()) == [frames, size]
    assert reach.asker.sent[11][0] == 8  # it sent an ASK and a TARGETS to each of 4 members
    members = reach.asker.members
    expected: list[mw.MotionMessage] = [mw.Ask(0, 0, m.route, 1) for m in members]
    expected += [mw.Targets(0, 0, m.route, ((0, 0.0), (1, 0.0)), 1) for m in members]
    expected += [mw.Angles(0, 0, m.route, 0, (0.0, 0.0), robot.status(0), 0) for m in members]
    assert frames == 12 and size == sum(len(mw.encode(1, m)) for m in expected)
