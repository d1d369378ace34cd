"""The docking sequence (firmware.motion.docking.Docking) on plain numbers: no simulator.

A bench plays the world the sequence asks things of: links in a dict, ideal servos (a joint
reads what it was last told to hold), infrared pairs and the overhead tracker's poses set by
the test, and the latch's and the link's answers scripted. Each test drives one branch of the
sequence: a latch and its verdict, a refused latch that sends the foot round again up to the
attempt limit, a module that dies under way, a robot that crawls clear before the foot lets go.
"""

from __future__ import annotations

from collections.abc import Callable

import pytest

from dh2rt.docking import End
from dh2rt.profile import CONRO
from firmware.motion.body import DEFAULT_MODEL
from firmware.motion.docking import BRING_ATTEMPTS, Docking
from firmware.motion.readings import FloorPoses, ModulePose, PartPose, Readings
from firmware.motion.underway import Motion, Needs, Targets

C = CONRO.connector_index
FRONT, BACK, LEFT = C("front"), C("back"), C("left")
NAMES = [f"m{i}" for i in range(6)]
NOTHING = (0.0, 180.0)  # an infrared pair that sees nothing: 0 mm, 180 degrees off square


class Bench:
    """The world a :class:`Docking` runs in, on plain numbers."""

    def __init__(self, links: list[tuple[End, End]]) -> None:
        self.links: dict[End, End] = {}
        for a, b in links:
            self.links[a], self.links[b] = b, a
        self.cycle = 0
        self.dead: set[int] = set()
        self.log: list[str] = []
        #: module -> (pos1, pos2): ideal servos, each reads its last target
        self.joints: dict[int, tuple[float, float]] = {}
        #: (module, connector name) -> (mm, degrees off square)
        self.ir: dict[tuple[int, str], tuple[float, float]] = {}
        self.floor = FloorPoses()
        self.closes = True  # the latch closes when asked (physics has the faces aligned)
        self.links_agree = True  # the link is negotiated once the latch closed
        self.latches: list[tuple[int, int, int, int]] = []
        self.verdicts: list[tuple[End, End, bool]] = []

    # what the sequence asks of its owner
    @property
    def now(self) -> int:
        return self.cycle

    def peer_of(self, end: End) -> End | None:
        return self.links.get(end)

    def running(self, module: int) -> bool:
        return module not in self.dead

    def cut(self, module: int, connector: int) -> None:
        other = self.links.pop((module, connector))
        del self.links[other]

    def dock(self, a: int, a_conn: int, b: int, b_conn: int) -> None:
        self.links[(a, a_conn)], self.links[(b, b_conn)] = (b, b_conn), (a, a_conn)

    def aligned(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        return self.closes

    def schedule(self, cycles_from_now: int, action: Callable[[], None]) -> None:
        raise AssertionError("the sequence schedules nothing")

    def where(self, module: int, connector: int) -> str:
        return f"m{module}.{CONRO.connector_name(connector)}"

    def note(self, message: str) -> None:
        self.log.append(message)

    def sense(self, cycle: int, needs: Needs) -> Readings:
        assert cycle == self.cycle
        joints = {m: self.joints.get(m, (0.0, 0.0)) for m in needs.joints}
        ir: dict[int, dict[str, float]] = {}
        for m in needs.infrared:
            for c in DEFAULT_MODEL.connectors:
                mm, deg = self.ir.get((m, c.name), NOTHING)
                ir.setdefault(m, {}).update({f"ir_{c.name}": mm, f"ir_{c.name}_align": deg})
        return Readings(joints, ir, self.floor if needs.floor else FloorPoses())

    def latch(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        self.latches.append((a, a_conn, b, b_conn))
        if self.links_agree:
            self.dock(a, a_conn, b, b_conn)
        return self.links_agree

    def ended(self, motion: Motion, linked: bool, readings: Readings) -> None:
        self.verdicts.append((motion.reach.chain.asking, motion.reach.chain.target, linked))

    # driving it
    def step(self, docking: Docking) -> Targets:
        """One control cycle: the sequence's step, then the servos go where they were told."""
        held = docking.step(self.cycle)
        self.cycle += 1
        for m, dofs in held.items():
            pos = list(self.joints.get(m, (0.0, 0.0)))
            for dof, v in dofs.items():
                pos[dof] = v
            self.joints[m] = (pos[0], pos[1])
        return held


def snake(n: int) -> list[tuple[End, End]]:
    """Module k's back docked to module k+1's front."""
    return [((k, BACK), (k + 1, FRONT)) for k in range(n - 1)]


def lying_along_x(modules: dict[int, float]) -> FloorPoses:
    """Each module flat on the floor facing +x, its centre at x (m)."""
    half = DEFAULT_MODEL.length / 2 + DEFAULT_MODEL.front.half[0]
    poses = {}
    for m, x in modules.items():
        poses[m] = ModulePose(PartPose(x, 0.0, 0.0), PartPose(x + half, 0.0, 0.0), PartPose(x - half, 0.0, 0.0))
    return FloorPoses(poses)


def test_a_reach_dock_bends_asks_the_latch_and_links() -> None:
    """``reach_dock`` along a snake of three: the chain's modules hold the motion's targets
    each cycle; once the asking face's infrared sees the face the latch is asked, closes,
    the link is negotiated and the verdict is linked."""
    bench = Bench(snake(3))
    docking = Docking(bench, bench, DEFAULT_MODEL, CONRO, NAMES[:3])
    assert docking.start_reach(2, BACK, (FRONT, FRONT), FRONT)
    assert docking.docking_modules() == {2} and docking.busy
    for _ in range(3):
        held = bench.step(docking)
        assert set(held) == {0, 1, 2} and not bench.latches
    bench.ir[(2, "back")] = (12.0, 5.0)  # the face is in view, within the tolerance
    bench.step(docking)
    assert bench.latches == [(2, BACK, 0, FRONT)]
    assert bench.verdicts == [((2, BACK), (0, FRONT), True)]
    assert bench.peer_of((2, BACK)) == (0, FRONT)
    (outcome,) = docking.outcomes
    assert outcome.latched and outcome.steps == 4 and outcome.missed == 0
    assert not docking.busy and not docking.docking_modules() and bench.step(docking) == {}


def test_a_reach_dock_the_rules_refuse_moves_nothing() -> None:
    bench = Bench(snake(3))
    docking = Docking(bench, bench, DEFAULT_MODEL, CONRO, NAMES[:3])
    assert not docking.start_reach(2, BACK, (FRONT, FRONT), LEFT)  # male to male
    assert "both connectors are" in bench.log[-1]
    assert docking.start_reach(2, BACK, (FRONT, FRONT), FRONT)
    assert not docking.start_reach(1, LEFT, (FRONT,), FRONT)  # its joints are the first one's
    assert "owns part of the chain" in bench.log[-1] and len(docking.motions) == 1


def creep_dock(bench: Bench) -> Docking:
    """A snake of three (m0-m2) and a lone foot m3 just behind m2's back, which has come
    (its first attempt); m2's back bends to the foot's front while the foot creeps."""
    bench.floor = lying_along_x({0: 0.0, 1: -0.12, 2: -0.24, 3: -0.38})
    docking = Docking(bench, bench, DEFAULT_MODEL, CONRO, NAMES[:4])
    docking.attempts[3] = 1  # as bring() sets it when the foot sets off
    assert docking.reach_other(2, BACK, (FRONT, FRONT), (3, FRONT), creep=True)
    return docking


def test_a_refused_latch_sends_the_foot_round_again_until_the_attempts_run_out() -> None:
    """The latch closes but the link is refused: no link, the verdict says so, and the foot
    sets off again; each trip that gives up sends it again, up to BRING_ATTEMPTS in all,
    then the sequence leaves it (nothing under way, the last verdict in the log)."""
    bench = Bench(snake(3))
    docking = creep_dock(bench)
    bench.links_agree = False
    held = bench.step(docking)
    assert 3 in held  # the foot crept while the chain bent
    bench.ir[(2, "back")] = (10.0, 3.0)
    bench.step(docking)
    assert bench.latches == [(2, BACK, 3, FRONT)] and bench.peer_of((2, BACK)) is None
    assert bench.verdicts == [((2, BACK), (3, FRONT), False)]
    assert not docking.outcomes[-1].latched
    assert "the foot tries again (2)" in bench.log[-1]
    for attempt in range(2, BRING_ATTEMPTS + 1):
        (bringing,) = docking.trips
        assert docking.attempts[3] == attempt and docking.docking_modules() == {2}
        bringing.trip.budget = bringing.trip.cycles  # its next step is past its budget: it gives up
        bench.step(docking)
    assert not docking.busy and docking.attempts[3] == BRING_ATTEMPTS
    assert len(docking.trips_done) == BRING_ATTEMPTS - 1 and not any(t.arrived for t in docking.trips_done)
    assert sum("the trip gave up" in line for line in bench.log) == BRING_ATTEMPTS - 1
    assert f"tries again ({BRING_ATTEMPTS + 1})" not in "\n".join(bench.log)


def test_a_foot_that_dies_on_its_trip_is_abandoned_not_sent_again() -> None:
    bench = Bench(snake(3))
    bench.floor = lying_along_x({0: 0.0, 1: -0.12, 2: -0.24, 3: 0.20})
    docking = Docking(bench, bench, DEFAULT_MODEL, CONRO, NAMES[:4])
    assert docking.bring(3, (2, BACK), (FRONT, FRONT))
    for _ in range(3):
        held = bench.step(docking)
        assert set(held) == {3} and set(held[3]) == {0, 1}  # the foot's own gait
    bench.dead.add(3)
    assert bench.step(docking) == {}
    assert "trip abandoned" in bench.log[-1] and not docking.busy and docking.attempts[3] == 1
    assert not docking.docking_modules()


def test_a_module_of_the_chain_that_dies_abandons_the_reach_without_a_verdict() -> None:
    bench = Bench(snake(3))
    docking = Docking(bench, bench, DEFAULT_MODEL, CONRO, NAMES[:3])
    assert docking.start_reach(2, BACK, (FRONT, FRONT), FRONT)
    bench.step(docking)
    bench.dead.add(1)
    bench.step(docking)
    assert "motion abandoned" in bench.log[-1] and not docking.busy
    assert not bench.verdicts and not docking.outcomes and not bench.latches


def test_the_robot_crawls_clear_of_a_module_on_the_spot_before_the_foot_lets_go() -> None:
    """``reach_and_dock`` with a module lying on the spot behind the face: the robot crawls
    (its modules' pitch joints), the foot still on the body; once the tracker says the spot
    is clear, the foot lets go and sets off."""
    bench = Bench([*snake(3), ((0, LEFT), (3, FRONT))])  # foot m3 hangs on m0's left by its front
    bench.floor = lying_along_x({0: 0.0, 1: -0.12, 2: -0.24, 3: 0.0, 4: -0.40})
    docking = Docking(bench, bench, DEFAULT_MODEL, CONRO, NAMES[:5])
    assert docking.spot_taken((2, BACK), 3) == 4
    assert docking.assimilate(2, BACK, (FRONT, FRONT, LEFT))
    assert "m4 lies behind m2.back" in bench.log[-1] and docking.docking_modules() == {2}
    held = bench.step(docking)
    assert set(held) == {0, 1, 2} and all(set(d) == {0} for d in held.values())
    bench.floor = lying_along_x({0: 0.0, 1: -0.12, 2: -0.24, 3: 0.0, 4: -1.0})  # it rolled away
    for _ in range(200):
        bench.step(docking)
        if docking.trips:
            break
    assert docking.trips and not docking.clearings
    assert any("crawled 1 gait cycles" in line and "the spot clear" in line for line in bench.log)
    assert bench.peer_of((3, FRONT)) is None and "m3.front released" in bench.log
    assert docking.attempts[3] == 1 and docking.docking_modules() == {2}


def test_a_second_foot_for_the_same_face_is_refused() -> None:
    bench = Bench([*snake(3), ((0, LEFT), (3, FRONT))])
    bench.floor = lying_along_x({0: 0.0, 1: -0.12, 2: -0.24, 3: 0.0})
    docking = Docking(bench, bench, DEFAULT_MODEL, CONRO, NAMES[:4])
    assert docking.assimilate(2, BACK, (FRONT, FRONT, LEFT))
    assert "m3.front released" in bench.log and docking.trips
    bench.dock(0, LEFT, 3, FRONT)  # (as if another foot hung there)
    assert not docking.assimilate(2, BACK, (FRONT, FRONT, LEFT))
    assert "already on its way" in bench.log[-1]


@pytest.mark.parametrize("due", [True, False])
def test_a_late_owner_steps_a_missed_cycle_once_and_counts_it(due: bool) -> None:
    """An owner stepping cycle 2 after cycle 0 (its thread came late): each motion makes one
    step, and the cycle it missed is counted; one not due does not step twice a cycle."""
    bench = Bench(snake(3))
    docking = Docking(bench, bench, DEFAULT_MODEL, CONRO, NAMES[:3])
    assert docking.start_reach(2, BACK, (FRONT, FRONT), FRONT)
    assert docking.step(0)  # asked at cycle 0: its first step is cycle 0's
    (motion,) = docking.motions
    steps = motion.reach.cycles
    assert docking.step(0) == {} and motion.reach.cycles == steps  # stepped already
    bench.cycle = 2
    docking.step(2, due)
    assert motion.reach.cycles == steps + 1 and motion.missed == 1 and docking.stepped_in(2)
