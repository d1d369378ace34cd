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
from dh2rt.transport.base import BusEnd, FrameFamily, Inbound
from dh2rt.transport.inproc import InprocTransport
from dh2rt.wire import motion as mw
from dh2rt.wire import operator as op
from dh2rt.wire.frame import FrameCodec
from drivers.recording import RecordingDriver
from firmware.config import ModuleConfig
from firmware.main_loop import ModuleHost
from firmware.motion.member import IDLE_CYCLES

ROOT = Path(__file__).resolve().parents[2]
FRONT, BACK = 1, 2
ROUTE_2 = ((BACK, FRONT), (BACK, FRONT))


class Robot:
    """The asker's transport, its back on m1's front; m1's back on m2's front. Modules are
    stepped by hand, frames carried between them at once."""

    def __init__(self) -> None:
        program = compile_file(str(ROOT / "examples" / "caterpillar.dh2"))
        channel = f"motion-{uuid.uuid4().hex}"
        self.hosts: list[ModuleHost] = []
        for module in (1, 2):
            config = {"module": module, "image": program.image.hex(), "transport": f"inproc:{channel}"}
            self.hosts.append(ModuleHost(ModuleConfig.from_json(config), queue.Queue(), lambda _r: None))
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
