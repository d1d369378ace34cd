"""A module's firmware (firmware.main_loop.ModuleHost) as a member of a docking chain: motion
frames sent from the outside, as the asking neighbour would, over the in-process bus; the
module answers with its servos' angles, passes frames on, writes the targets it is sent to
its own servos (the recording stand-in) and gives its joints back to its program when the
motion goes silent. The operator's frames still reach the operator channel."""

from __future__ import annotations

import queue
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from dh2rt.compiler import compile_file
from dh2rt.hormone import Hormone
from dh2rt.transport.base import BusEnd, FrameFamily, Inbound
from dh2rt.transport.inproc import InprocTransport
from dh2rt.wire import motion as mw
from dh2rt.wire import operator as op
from dh2rt.wire.frame import FrameCodec
from drivers.latch import Position
from drivers.recording import RecordingDriver, RecordingLatch
from firmware.config import ModuleConfig
from firmware.control import Command, Detach, Effect, Floor, LatchAnswer, Readings, Report
from firmware.main_loop import ModuleHost, _ModuleLatch
from firmware.motion.asking import SelfReach
from firmware.motion.body import DEFAULT_MODEL
from firmware.motion.member import IDLE_CYCLES

ROOT = Path(__file__).resolve().parents[2]
FRONT, BACK, RIGHT = 1, 2, 4
ROUTE_2 = ((BACK, FRONT), (BACK, FRONT))


class Robot:
    """The asker's transport, its back on m1's front; m1's back on m2's front. Modules are
    stepped by hand, frames carried between them at once."""

    def __init__(self) -> None:
        program = compile_file(str(ROOT / "examples" / "caterpillar.dh2"))
        channel = f"motion-{uuid.uuid4().hex}"
        self.hosts: list[ModuleHost] = []
        self.commands: list[queue.Queue[Command]] = [queue.Queue(), queue.Queue()]
        self.reports: list[list[Report]] = [[], []]
        for i, module in enumerate((1, 2)):
            config = {"module": module, "image": program.image.hex(), "transport": f"inproc:{channel}"}
            self.hosts.append(ModuleHost(ModuleConfig.from_json(config), self.commands[i], self.reports[i].append))
        codec = FrameCodec(program.vocabulary, program.profile.connector_count)
        self.asker = InprocTransport(codec, channel=channel)
        self.asker.attach(BACK, BusEnd(0, 0))
        self.hosts[0].runtime.attach(FRONT, BusEnd(0, 1))
        self.hosts[0].runtime.attach(BACK, BusEnd(1, 0))
        self.hosts[1].runtime.attach(FRONT, BusEnd(1, 1))
        self.got: list[bytes] = []
        self.asker.listen(FrameFamily.CONTROL, self._got)

    def _got(self, frame: Inbound) -> None:
        self.got.append(frame.payload)

    def send(self, message: mw.Outward) -> None:
        assert self.asker.send_raw(BACK, mw.encode(BACK, mw.onward(message)))

    def cycles(self, n: int = 1) -> None:
        for _ in range(n):
            for host in self.hosts:
                host._take_commands(host.runtime)
                host.runtime.step()
            for _ in range(3):  # a control frame passes a hop a poll
                for host in self.hosts:
                    host.runtime.take_in()
            self.asker.poll()

    def driver(self, i: int) -> RecordingDriver:
        driver = self.hosts[i].driver
        assert isinstance(driver, RecordingDriver)
        return driver

    def close(self) -> None:
        for host in self.hosts:
            host.runtime.close()
        self.asker.close()


@pytest.fixture
def robot() -> Iterator[Robot]:
    r = Robot()
    try:
        yield r
    finally:
        r.close()


def test_the_member_answers_holds_and_gives_back(robot: Robot) -> None:
    robot.cycles(3)
    m2 = robot.hosts[1].runtime
    robot.send(mw.Ask(9, 0, ROUTE_2))
    robot.cycles()
    (report,) = [mw.decode(f).message for f in robot.got]
    angles = tuple(round(a, 2) for a in robot.driver(1).targets)
    assert report == mw.Angles(9, 0, ROUTE_2, 2, angles, tuple(m2.engine.status), 0)
    assert report.links[FRONT - 1] == BACK  # m1's back is linked at m2's front

    robot.send(mw.Targets(9, 1, ROUTE_2, ((0, 40.0), (1, -25.0))))
    robot.cycles()
    assert robot.driver(1).targets == (40.0, -25.0)
    assert robot.driver(0).targets == tuple(robot.hosts[0].runtime.engine.dof[:2])  # m1 passed them on
    assert robot.hosts[1].member.holding == 9
    status = robot.hosts[1]._status(m2)
    assert status["motion"] == {"ask": 1, "targets": 1}

    robot.cycles(IDLE_CYCLES)  # nothing more from the asker: it died, or a link went
    assert robot.driver(1).targets == (40.0, -25.0)
    robot.cycles()
    assert robot.hosts[1].member.holding is None
    assert robot.driver(1).targets == tuple(m2.engine.dof[:2])
    assert any(f"no frame of motion 9 for {IDLE_CYCLES + 1} cycles" in line for line in m2.log)


def test_end_gives_the_joints_back_at_once(robot: Robot) -> None:
    robot.cycles(2)
    robot.send(mw.Targets(3, 0, ROUTE_2[:1], ((1, 12.5),)))
    robot.cycles()
    m1 = robot.hosts[0].runtime
    assert robot.driver(0).targets == (m1.engine.dof[0], 12.5)
    robot.send(mw.End(3, 1, ROUTE_2[:1]))
    robot.cycles()
    assert robot.driver(0).targets == tuple(m1.engine.dof[:2])


def test_operator_frames_still_reach_the_operator_channel(robot: Robot) -> None:
    robot.cycles(2)
    pause = op.Signed(op.Pause(), 1, bytes(8), bytes(64))
    assert robot.asker.send_raw(BACK, op.encode(BACK, pause))
    robot.cycles()
    answers = [op.decode(f).message for f in robot.got]
    assert answers == [op.Refused(1, 0, (), op.RefusalReason.NO_CONTROL)]


#: The head, called by the tail, asks for its front to be docked to the tail's right.
REACHING = """program reaching
const ClockCycle = 10
hormone GO
hormone CALL
native reach_dock(path, mine, theirs)
receptor called when T == T1 and H == CALL as p { reach_dock(p, 1, 4) }
receptor go when T == T2 and H == GO { emit CALL via front }
"""


@pytest.mark.parametrize("latch", ["world", "recording"])
def test_a_module_carries_out_the_reach_dock_its_program_asks_for(tmp_path: Path, latch: str) -> None:
    """snake:2 of module firmware on the recording stand-in: the tail's CALL reaches the
    head, whose program asks reach_dock(p, Front, Right). The head runs the motion itself:
    it learns its chain (the tail) from the tail's ANGLES, moves the tail's joints by
    TARGETS and its own by its servos, and once its front's infrared sees the face (pushed
    as the world pushes readings) closes the latch: without a ``[latch]`` it asks its world
    and ends on the world's answer; with the recording stand-in's latch on its front
    (``latch = "recording"``) it closes its own, asks the world nothing, and ends once the
    latch says closed and a Hello is heard on the front (the test links the two faces, as the
    pins would). Then the tail's joints are its program's again. The test plays the world:
    readings in, the latch's answer or the new link."""
    source = tmp_path / "reaching.dh2"
    source.write_text(REACHING)
    program = compile_file(str(source))
    channel = f"reach-{uuid.uuid4().hex}"
    reports: list[list[object]] = [[], []]
    commands: list[queue.Queue[Command]] = [queue.Queue(), queue.Queue()]
    hosts = []
    for module in (0, 1):
        config: dict[str, object] = {"module": module, "image": program.image.hex(), "transport": f"inproc:{channel}"}
        if latch == "recording" and module == 0:  # module.toml's [latch] kind = "recording", connector = 1
            config["latch"] = {"kind": "recording", "connector": FRONT}
        # as a module booted by `dh2rt module` from its module.toml (no [hil] control): it
        # carries out its reach itself; under the HIL world (control on stdio) the world does
        host = ModuleHost(
            ModuleConfig.from_json({**config, "control": "none"}), commands[module], reports[module].append
        )
        hosts.append(host)
    head, tail = hosts
    try:
        head.runtime.attach(BACK, BusEnd(0, 0))
        tail.runtime.attach(FRONT, BusEnd(0, 1))
        assert head.self_motion and tail.self_motion

        def cycles(n: int) -> None:
            for _ in range(n):
                for host in hosts:
                    host._take_commands(host.runtime)
                    host.runtime.step()
                    host.end_cycle(host.runtime)
                for _ in range(3):
                    for host in hosts:
                        host.runtime.take_in()

        cycles(3)
        tail.runtime.inject(Hormone("GO", ()))
        cycles(4)
        assert head.reach is not None, head.runtime.log
        reach = head.reach
        assert isinstance(reach, SelfReach)
        cycles(3)
        assert reach.asker.known and reach.docking is not None and reach.docking.busy, head.runtime.log
        assert tail.member.holding == reach.asker.motion and set(tail.member.held) == {0, 1}
        assert isinstance(tail.driver, RecordingDriver) and tail.driver.targets == tuple(
            tail.member.held[d] for d in (0, 1)
        )
        assert not any(isinstance(r, Effect) and r.kind == "latch" for r in reports[0])

        commands[0].put(Readings({"ir_front": 12, "ir_front_align": 4}))  # the face in view
        cycles(2)
        asked = [r.args for r in reports[0] if isinstance(r, Effect) and r.kind == "latch"]
        if latch == "world":
            assert asked == [[FRONT, 1, 4]]
            assert not reach.done
            commands[0].put(LatchAnswer(FRONT, True))  # it closed in physics, the link is made
            cycles(2)
        else:
            assert asked == []  # its own latch: nothing asked of the world
            assert isinstance(head.latch, _ModuleLatch), head.runtime.log
            own = head.latch.driver
            assert isinstance(own, RecordingLatch) and own.history == [Position.CLOSED], head.runtime.log
            cycles(3)
            assert not reach.done  # closed, but no Hello on the front yet: not docked
            head.runtime.attach(FRONT, BusEnd(1, 0))  # the pins hold: the faces' channel is made
            tail.runtime.attach(RIGHT, BusEnd(1, 1))
            for _ in range(12):
                cycles(1)
                if reach.done:
                    break
        assert reach.verdict == "linked", head.runtime.log
        ended = [r for r in reports[0] if isinstance(r, Effect) and r.kind == "reach_ended"]
        assert [r.args for r in ended] == [[FRONT, "linked"]]
        cycles(1)
        assert tail.member.holding is None and tail.member.counts["end"] == 1
        assert tail.driver.targets == tuple(tail.runtime.engine.dof[:2])
        assert reach.asker.counts["stale"] == 0 and reach.asker.counts["unanswered"] == 0
    finally:
        for host in hosts:
            host.runtime.close()


def lying(x: float) -> tuple[tuple[float, float, float], ...]:
    """A module flat on the floor facing +x, centre at x: centre, front and back parts."""
    half = DEFAULT_MODEL.length / 2 + DEFAULT_MODEL.front.half[0]
    return (x, 0.0, 0.0), (x + half, 0.0, 0.0), (x - half, 0.0, 0.0)


def effects(robot: Robot, kind: str) -> list[list[object]]:
    """What the foot (m2) reported of ``kind``."""
    return [r.args for r in robot.reports[1] if isinstance(r, Effect) and r.kind == kind]


def test_the_foot_lets_go_and_walks_by_the_tracker_on_its_own_servos(robot: Robot) -> None:
    """The foot of a reach_and_dock (m2, hanging by its front on m1's back) takes a SET_OFF
    sent from outside as the asking module would send it; the test plays the world (the
    release's link cut, the tracker's report pushed). It lets go, waits for the tracker,
    walks by it on its own servos, and says what became of its trip."""
    robot.cycles(3)
    foot = robot.hosts[1]
    assert foot.runtime.engine.status[FRONT - 1] == BACK  # it hangs on m1's back
    set_off = mw.SetOff(0x0501, 1, ROUTE_2, 1, BACK, (1,), ())
    robot.send(set_off)
    robot.cycles(2)  # it takes the frame in one cycle and sets off at the next one's start
    assert foot.member.counts["setoff"] == 1, foot.runtime.log
    assert effects(robot, "release") == [[FRONT]]  # it asks its world to open its front
    assert foot.foot is not None and not foot.foot.loose
    program_joints = robot.driver(1).targets
    running = foot.foot
    robot.send(mw.SetOff(0x0501, 2, ROUTE_2, 1, BACK, (1,), ()))  # the asker's next copy
    robot.cycles(2)
    assert foot.foot is running and effects(robot, "release") == [[FRONT]]  # taken once

    robot.commands[1].put(Detach(FRONT))  # the world opens the latch: the link goes
    robot.commands[0].put(Detach(BACK))
    robot.cycles(2)
    assert foot.foot.loose and foot.foot.trip is None  # no tracker report yet: it waits, still
    assert robot.driver(1).targets == (0.0, 0.0) != program_joints

    robot.commands[1].put(Floor({1: lying(0.0), 2: lying(-0.5)}))
    robot.cycles(3)
    trip = foot.foot.trip
    # a report pushed is read from the next cycle on, as the asking module's reach reads it
    assert trip is not None and trip.cycles == 2 and trip.target == (1, BACK)
    assert robot.driver(1).targets == tuple(foot._own_held[d] for d in (0, 1)) != (0.0, 0.0)

    robot.commands[1].put(Floor({1: lying(0.0)}))  # the tracker lost the foot
    robot.cycles(2)
    set_off, (kind, detail) = effects(robot, "foot")
    assert set_off[0] == "set_off" and "to module 1" in str(set_off[1])  # the world pushes it the tracker
    assert kind == "trip_gave_up" and "module 2" in detail
    assert foot.foot.tries == 1 and not foot.foot.done  # it goes round again
