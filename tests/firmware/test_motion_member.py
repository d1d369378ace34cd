"""A chain member's side of a docking motion (firmware.motion.member), sans-IO, on a chain of
members a test network carries frames between: angles asked and answered along the route,
targets held, stale and off-route frames dropped, the joints given back on END and when the
motion goes silent."""

from __future__ import annotations

from dataclasses import dataclass

from dh2rt.wire import motion as mw
from firmware.motion.member import IDLE_CYCLES, Member

FRONT, BACK = 1, 2
#: The asker m0's back on m1's front, m1's back on m2's front.
ROUTE_1 = ((BACK, FRONT),)
ROUTE_2 = ((BACK, FRONT), (BACK, FRONT))


@dataclass
class Body:
    joints: tuple[float, ...]
    status: tuple[int, ...]

    def angles(self) -> tuple[float, ...]:
        return self.joints

    def links(self) -> tuple[int, ...]:
        return self.status


class Chain:
    """Members m1, m2 (m0 is the asker, also a Member for the reports it gets); a frame sent
    through ``back`` reaches the next one's ``front`` and the other way round."""

    def __init__(self) -> None:
        self.logs: list[str] = []
        self.bodies = [
            Body((0.0, 0.0), (0, 1, 0, 0)),
            Body((10.0, -20.0), (2, 1, 0, 0)),
            Body((33.33, 44.5), (2, 0, 0, 0)),
        ]
        self.modules = [Member(10 + i, self.bodies[i], log=self.logs.append) for i in range(3)]
        self.cycle = 0
        self.sent = 0

    def send(self, at: int, connector: int, frame: bytes) -> None:
        """``frame`` sent by module ``at`` through ``connector``, and what it sets off."""
        queue = [(at, connector, frame)]
        while queue:
            at, connector, frame = queue.pop(0)
            self.sent += 1
            to, arrives = (at + 1, FRONT) if connector == BACK else (at - 1, BACK)
            if not 0 <= to < len(self.modules):
                continue
            member = self.modules[to]
            outs = member.received(arrives, frame, self.cycle)
            queue.extend((to, out.connector, out.frame) for out in outs)

    def ask(self, message: mw.Outward) -> None:
        self.send(0, message.route[0][0], mw.encode(message.route[0][0], mw.onward(message)))


def test_angles_are_asked_and_answered_along_the_route() -> None:
    chain = Chain()
    chain.ask(mw.Ask(5, 1, ROUTE_2))
    assert chain.modules[0].reports == [mw.Angles(5, 1, ROUTE_2, 12, (33.33, 44.5), (2, 0, 0, 0), 0)]
    assert chain.modules[1].counts["relayed"] == 2  # the ASK out, the ANGLES back
    assert chain.modules[2].counts["ask"] == 1
    assert chain.sent == 4


def test_targets_are_held_and_a_stale_frame_changes_nothing() -> None:
    chain = Chain()
    m2 = chain.modules[2]
    chain.ask(mw.Targets(5, 3, ROUTE_2, ((0, 30.0), (1, -15.0))))
    assert m2.held == {0: 30.0, 1: -15.0} and m2.holding == 5
    assert chain.modules[1].held == {}  # it only passed them on
    chain.ask(mw.Targets(5, 2, ROUTE_2, ((0, 0.0),)))  # late: sent before the one above
    chain.ask(mw.Targets(5, 3, ROUTE_2, ((0, 0.0),)))  # a duplicate
    assert m2.held == {0: 30.0, 1: -15.0} and m2.counts["stale"] == 2
    chain.ask(mw.End(5, 4, ROUTE_2))
    assert m2.held == {} and m2.holding is None
    chain.ask(mw.Targets(5, 3, ROUTE_2, ((0, 10.0),)))  # a late one of the motion that ended
    assert m2.held == {}
    assert "motion: joints back to the program (motion 5 ended)" in chain.logs


def test_seq_wraps_and_each_motion_has_its_own() -> None:
    chain = Chain()
    m1 = chain.modules[1]
    chain.ask(mw.Targets(1, 0xFFFF, ROUTE_1, ((0, 1.0),)))
    chain.ask(mw.Targets(1, 0, ROUTE_1, ((0, 2.0),)))
    assert m1.held == {0: 2.0}
    chain.ask(mw.Targets(2, 0, ROUTE_1, ((0, 3.0),)))  # another asker's motion takes over
    assert m1.held == {0: 3.0} and m1.holding == 2
    chain.ask(mw.End(1, 1, ROUTE_1))  # the first motion's end gives back nothing of the second
    assert m1.held == {0: 3.0} and m1.holding == 2


def test_a_silent_motion_gives_the_joints_back_after_idle_cycles() -> None:
    chain = Chain()
    m1 = chain.modules[1]
    chain.cycle = 100
    chain.ask(mw.Targets(1, 0, ROUTE_1, ((0, 1.0),)))
    for cycle in range(101, 101 + IDLE_CYCLES):
        m1.cycle(cycle)
        assert m1.held == {0: 1.0}, cycle
    chain.cycle = 105
    chain.ask(mw.Ask(1, 1, ROUTE_1))  # any frame of the motion keeps it
    m1.cycle(105 + IDLE_CYCLES)
    assert m1.holding == 1
    m1.cycle(106 + IDLE_CYCLES)
    assert m1.held == {} and m1.holding is None and m1.counts["timed_out"] == 1
    assert f"no frame of motion 1 for {IDLE_CYCLES + 1} cycles" in chain.logs[-1]


def test_off_route_and_malformed_frames_are_dropped_and_counted() -> None:
    chain = Chain()
    m1 = chain.modules[1]
    # says it came in at m1's back, but it arrives at its front
    wrong = mw.encode(BACK, mw.Targets(1, 0, ((FRONT, BACK),), ((0, 1.0),), 1))
    assert m1.received(FRONT, wrong, 0) == []
    # a report whose hop back does not match where it came in
    report = mw.encode(BACK, mw.Angles(1, 0, ROUTE_2, 12, (1.0, 2.0), (), 1))
    assert m1.received(FRONT, report, 0) == []
    assert m1.received(FRONT, bytes((0x22, 0x42, 0)), 0) == []
    assert m1.counts == {"off_route": 2, "malformed": 1}
    assert m1.held == {}


def test_a_set_off_is_passed_on_and_kept_by_the_foot_at_the_route_s_end() -> None:
    """The foot (m2, two hops out) keeps its hand-over and answers nothing; the module it
    passed through keeps none; a stale copy is not taken again."""
    chain = Chain()
    set_off = mw.SetOff(5, 1, ROUTE_2, 10, BACK, (10, 11), (12,))
    chain.ask(set_off)
    foot, middle = chain.modules[2], chain.modules[1]
    assert foot.set_off == mw.onward(mw.onward(set_off))
    assert foot.set_off is not None and (foot.set_off.target, foot.set_off.body) == (10, (10, 11))
    assert middle.set_off is None and middle.counts["relayed"] == 1
    assert chain.sent == 2 and not chain.modules[0].reports  # no ANGLES back
    foot.set_off = None
    chain.ask(set_off)
    assert foot.set_off is None and foot.counts["stale"] == 1
