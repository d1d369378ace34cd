"""``dh2rt console`` over serial links: two legs-to-snake modules running in real time (threads,
each a ModuleRuntime on a serial transport with its operator channel), linked by the link
emulator's pty pairs, and the console's cable a third link into the head's free front. The
console reads states, draws the robot, injects LTS at a module, pauses and resumes; a replayed
command and one signed with another key are refused and counted by every module; bad input
exits 2 naming it."""

from __future__ import annotations

import io
import itertools
import os
import re
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from dh2rt.bundled import compile_bundled
from dh2rt.program import CompiledProgram
from dh2rt.runtime import ModuleRuntime
from dh2rt.signed_image import private_key_pem, public_key
from dh2rt.transport.base import BusEnd, PortEnd
from dh2rt.transport.can_bus import VirtualCanTransport
from dh2rt.transport.serial_link import SerialTransport
from dh2rt.wire import operator as op
from dh2rt.wire.frame import FrameCodec
from firmware.flash.cable import hello_codec
from firmware.operator import OperatorChannel
from hil.link_emulator import LinkEmulator
from tools import console
from tools.console_link import ConsoleLink
from tools.flash import open_cable

pytestmark = pytest.mark.realtime

FRONT, BACK = 1, 2
KEY = bytes(range(32))
OTHER = bytes(range(50, 82))
PERIOD = 0.02
PROGRAM = compile_bundled("legs_to_snake.dh2")
SOURCE = Path(__file__).resolve().parents[2] / "dh2rt" / "programs" / "legs_to_snake.dh2"
DH2RT = Path(sys.executable).parent / "dh2rt"


@dataclass
class Robot:
    modules: list[ModuleRuntime]
    channels: list[OperatorChannel]
    cable: str
    key_file: Path
    other_key_file: Path


@contextmanager
def snake(tmp_path: Path, n: int, program: CompiledProgram = PROGRAM, *, at_tail: bool = False) -> Iterator[Robot]:
    """``n`` modules running ``program`` in real time, each back on the next one's front over
    the link emulator's serial links, the console's cable into the head's front (or the
    tail's back)."""
    emulator = LinkEmulator()
    links, cable = [emulator.add_link() for _ in range(n - 1)], emulator.add_link()
    codec = FrameCodec(program.vocabulary, program.profile.connector_count)
    modules = [ModuleRuntime(program, SerialTransport(codec), module=i, cycle_period=PERIOD) for i in range(n)]
    for i, link in enumerate(links):
        modules[i].attach(BACK, PortEnd(link.paths[0]))
        modules[i + 1].attach(FRONT, PortEnd(link.paths[1]))
    if at_tail:
        modules[-1].attach(BACK, PortEnd(cable.paths[1]))
    else:
        modules[0].attach(FRONT, PortEnd(cable.paths[1]))
    channels = []
    for i, rt in enumerate(modules):
        (tmp_path / f"m{i}").mkdir()
        channels.append(OperatorChannel(rt, (public_key(KEY),), tmp_path / f"m{i}"))
    stop = threading.Event()
    threads = [threading.Thread(target=rt.run, kwargs={"stop_event": stop}, daemon=True) for rt in modules]
    for t in threads:
        t.start()
    (tmp_path / "robot.key").write_bytes(private_key_pem(KEY))
    (tmp_path / "other.key").write_bytes(private_key_pem(OTHER))

    def linked() -> bool:  # every module's engine sees its neighbours (the tests read types)
        inner = [modules[i].engine.status[BACK - 1] for i in range(n - 1)]
        return all(inner) and all(modules[i].engine.status[FRONT - 1] for i in range(1, n))

    try:
        # a busy machine may take a while to link the snake; what follows is not about that
        assert until(linked, 20.0), [rt.engine.status for rt in modules]
        yield Robot(modules, channels, cable.paths[0], tmp_path / "robot.key", tmp_path / "other.key")
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=5)
        for rt in modules:
            rt.close()
        emulator.close()


@pytest.fixture
def robot(tmp_path: Path) -> Iterator[Robot]:
    with snake(tmp_path, 2) as r:
        yield r


def run_console(robot: Robot, tmp_path: Path, script: str, key: Path | None = None) -> int:
    path = tmp_path / "commands.txt"
    path.write_text(script)
    argv = ["--port", robot.cable, "--key", str(key or robot.key_file), "--program", str(SOURCE)]
    return console.main([*argv, "--cycle-ms", "20", "--script", str(path)])


def test_state_topology_pause_resume_and_inject(
    robot: Robot, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    script = "state .\nstate back>front\ntopology\npause\nstate back>front\nresume\ninject LTS at back>front\n"
    code = run_console(robot, tmp_path, script)
    out = capsys.readouterr().out
    assert code == 0, out
    head, tail = robot.modules
    assert "module .: head (T1)" in out and "ConnectorStatus front=0 back=front left=0 right=0" in out
    assert "module back>front: tail (T2)" in out and "variables waiting=" in out and "receptors " in out
    assert "(cable): head (T1)\n  back>front: tail (T2)" in out
    assert "paused (flooded to every module)" in out and ", PAUSED" in out
    assert "injected LTS at back>front" in out
    assert not head.paused and not tail.paused
    # every command passes the head; the tail takes those routed to it or flooded: 8 and 6
    assert [ch.core.accepted for ch in robot.channels] == [8, 6]
    assert any("injected LTS" in line for line in tail.log)


def test_refusals_are_answered_counted_by_every_module_and_exit_1(
    robot: Robot, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A PAUSE signed with another key, a STATE likewise, and a replayed PAUSE: each refused
    and counted by both modules, each answered once (the flood by the module at the cable,
    the routed STATE by its route's end)."""

    def counted(name: str) -> list[int]:
        return [ch.core.counters.get(name, 0) for ch in robot.channels]

    assert run_console(robot, tmp_path, "pause\n", key=robot.other_key_file) == 1
    assert capsys.readouterr().out.splitlines()[-1] == "refused by the module at .: UNTRUSTED_KEY"
    assert until(lambda: counted("refused_untrusted_key") == [1, 1]), counted("refused_untrusted_key")
    assert run_console(robot, tmp_path, "state back>front\n", key=robot.other_key_file) == 1
    assert capsys.readouterr().out.splitlines()[-1] == "refused by the module at back>front: UNTRUSTED_KEY"
    assert counted("refused_untrusted_key") == [2, 2]
    transport = open_cable(robot.cable, 115200)
    link = ConsoleLink(transport, KEY, period=PERIOD).start()
    try:
        first = link.command(op.Pause(), 0.3)
        assert first.answers == () and until(lambda: all(rt.paused for rt in robot.modules))
        replay = op.sign(op.Pause(), first.counter, KEY)
        link.send_signed(replay)
        assert until(lambda: counted("refused_replayed") == [1, 1]), counted("refused_replayed")
        late = link.command(op.Resume(), 0.5)
        assert late.refused is None
    finally:
        link.close()
        transport.close()
    assert until(lambda: not any(rt.paused for rt in robot.modules))
    assert counted("refused_untrusted_key") == [2, 2] and counted("accepted")[1] == 2  # the tail: PAUSE, RESUME


@pytest.mark.parametrize(
    ("script", "says"),
    [
        ("inject NOPE\n", "commands.txt:1: hormone 'NOPE': program legs_to_snake declares no such hormone"),
        ("state\nstate back>nowhere\n", "commands.txt:2: path 'back>nowhere': no connector 'nowhere'"),
        ("dance\n", "commands.txt:1: unknown command 'dance'"),
    ],
)
def test_bad_script_lines_exit_2_naming_the_line(
    robot: Robot, tmp_path: Path, capsys: pytest.CaptureFixture[str], script: str, says: str
) -> None:
    assert run_console(robot, tmp_path, script) == 2
    assert says in capsys.readouterr().err


def test_bad_options_exit_2_naming_them(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "none.key"
    assert console.main(["--port", "/dev/null", "--key", str(missing), "--program", str(SOURCE)]) == 2
    assert str(missing) in capsys.readouterr().err
    (tmp_path / "k").write_bytes(private_key_pem(KEY))
    assert console.main(["--key", str(tmp_path / "k"), "--program", str(SOURCE)]) == 2
    assert "give the cable: --port DEV" in capsys.readouterr().err


def spawn_console(robot: Robot, tmp_path: Path) -> Any:
    """``dh2rt console`` at its interactive prompt on a pty, as a person starts it."""
    pexpect = pytest.importorskip("pexpect", reason="pexpect (the dev extra) drives the interactive prompt")
    argv = ["console", "--port", robot.cable, "--key", str(robot.key_file), "--program", str(SOURCE)]
    env = {**os.environ, "HOME": str(tmp_path), "TERM": "dumb"}
    child = pexpect.spawn(str(DH2RT), [*argv, "--cycle-ms", "20"], env=env, encoding="utf-8", timeout=10)
    child.expect_exact("dh2rt> ")
    return child


def test_the_prompt_completes_runs_and_leaves_on_ctrl_d(robot: Robot, tmp_path: Path) -> None:
    child = spawn_console(robot, tmp_path)
    try:
        child.send("sta\t")  # completion: the command
        child.expect_exact("state")
        child.send(" back>fr\t")  # and a hop's connector
        child.expect_exact("back>front")
        child.send("\r")
        child.expect_exact("module back>front: tail (T2)")
        child.expect_exact("dh2rt> ")
        child.sendline("inject NOPE")
        child.expect_exact("error: hormone 'NOPE': program legs_to_snake declares no such hormone")
        child.expect_exact("dh2rt> ")
        child.sendeof()  # Ctrl-D
        child.expect(pexpect_eof(child))
    finally:
        child.close()
    assert child.exitstatus == 0, child.before
    assert "state back>front" in (tmp_path / ".dh2rt_console_history").read_text()


def test_ctrl_c_at_the_prompt_exits_130_without_a_traceback(robot: Robot, tmp_path: Path) -> None:
    child = spawn_console(robot, tmp_path)
    try:
        child.sendintr()  # Ctrl-C
        child.expect(pexpect_eof(child))
        said = child.before
    finally:
        child.close()
    assert child.exitstatus == 130 and "interrupted" in said and "Traceback" not in said, said


def pexpect_eof(child: Any) -> Any:
    """pexpect's EOF (imported where the prompt's tests skip without it)."""
    import pexpect

    return pexpect.EOF


def until(condition: Callable[[], bool], timeout: float = 2.0) -> bool:
    """Whether ``condition`` holds within ``timeout`` s (tests of what is counted and held,
    not of how fast: a busy machine may hold a module's thread a while)."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


class PauseWatch:
    """When (monotonic s) and at which of its cycles each pause()/resume() reached a module."""

    def __init__(self, modules: list[ModuleRuntime]) -> None:
        self.calls: list[list[tuple[bool, float, int]]] = [[] for _ in modules]
        for i, rt in enumerate(modules):
            rt.pause = self._wrap(i, rt, rt.pause)  # type: ignore[method-assign, assignment]

    def _wrap(self, i: int, rt: ModuleRuntime, pause: Callable[[bool], bool]) -> Callable[[bool], bool]:
        def watched(paused: bool) -> bool:
            self.calls[i].append((paused, time.monotonic(), rt.cycle))
            return pause(paused)

        return watched

    def times(self, n: int) -> list[float]:
        return [calls[n][1] for calls in self.calls]

    def cycles(self, n: int) -> list[int]:
        return [calls[n][2] for calls in self.calls]


def test_pause_holds_an_8_module_wave_within_2_cycles_and_state_reads_every_module(tmp_path: Path) -> None:
    """The caterpillar's wave on 8 modules: PAUSE reaches each module within 2 cycles of
    reaching its neighbour towards the cable, no joint moves while paused, STATE then reads each module exactly as
    its engine stands, and RESUME goes on from the LocalTimer each stopped at."""
    caterpillar = compile_bundled("caterpillar.dh2")
    with snake(tmp_path, 8, caterpillar) as robot:
        watch = PauseWatch(robot.modules)
        time.sleep(40 * PERIOD)  # the wave runs
        transport = open_cable(robot.cable, 115200)
        link = ConsoleLink(transport, KEY, period=PERIOD).start()
        try:
            assert len({tuple(rt.engine.dof) for rt in robot.modules}) > 1  # the wave is under way
            assert link.command(op.Pause(), 10 * PERIOD).answers == ()
            assert until(lambda: all(rt.paused for rt in robot.modules))
            # each module holds within 2 cycles of the frame's arrival: of its neighbour
            # towards the cable passing it on (the flood's copies leave before the flash write)
            reached = watch.times(0)
            hops = [b - a for a, b in itertools.pairwise(reached)]
            assert max(hops) <= 2 * PERIOD, reached
            timers = [rt.engine.timer for rt in robot.modules]
            dofs = [rt.commanded for rt in robot.modules]
            cycles = [rt.cycle for rt in robot.modules]
            time.sleep(10 * PERIOD)
            assert [rt.engine.timer for rt in robot.modules] == timers  # held
            assert [rt.commanded for rt in robot.modules] == dofs  # no joint moved
            assert all(rt.cycle > c for rt, c in zip(robot.modules, cycles, strict=True))  # links cycle on
            for i, rt in enumerate(robot.modules):
                reply = link.command(op.StateRequest(((BACK, FRONT),) * i), 40 * PERIOD).reply
                assert reply is not None, i
                s, e = reply.status, rt.engine
                assert (s.timer, s.type_index, s.connectors) == (e.timer, e.type_index, tuple(e.status)), i
                assert (s.variables, s.receptors, s.paused) == (tuple(e.vars), tuple(e.rstatus), True), i
            assert link.command(op.Resume(), 10 * PERIOD).answers == ()
            time.sleep(10 * PERIOD)
            assert link.command(op.Pause(), 10 * PERIOD).answers == ()  # hold it again, to read it still
            stepped = [p - r for p, r in zip(watch.cycles(2), watch.cycles(1), strict=True)]
            clock = caterpillar.clock_cycle
            expected = [(t + n) % clock for t, n in zip(timers, stepped, strict=True)]
            assert [rt.engine.timer for rt in robot.modules] == expected, stepped
        finally:
            link.close()
            transport.close()


def test_the_console_on_a_can_bus(tmp_path: Path) -> None:
    """The same commands over python-can's virtual bus: every signed command is a segment
    train of classic CAN frames, each answer one or a train; a replay is refused there too."""
    channel = f"console-{os.getpid()}-{time.monotonic_ns()}"
    codec = FrameCodec(PROGRAM.vocabulary, PROGRAM.profile.connector_count)
    modules = [
        ModuleRuntime(PROGRAM, VirtualCanTransport(codec, channel=channel), module=i, cycle_period=PERIOD)
        for i in range(2)
    ]
    modules[0].attach(BACK, BusEnd(1, 0))
    modules[1].attach(FRONT, BusEnd(1, 1))
    modules[0].attach(FRONT, BusEnd(2, 1))
    for i, rt in enumerate(modules):
        (tmp_path / f"m{i}").mkdir()
        OperatorChannel(rt, (public_key(KEY),), tmp_path / f"m{i}")
    stop = threading.Event()
    threads = [threading.Thread(target=rt.run, kwargs={"stop_event": stop}, daemon=True) for rt in modules]
    for t in threads:
        t.start()
    cable = VirtualCanTransport(hello_codec(), channel=channel)
    cable.attach(BACK, BusEnd(2, 0))
    link = ConsoleLink(cable, KEY, connector=BACK, period=PERIOD).start()
    out = io.StringIO()
    try:
        assert until(lambda: bool(modules[0].engine.status[BACK - 1] and modules[1].engine.status[FRONT - 1]), 20.0)
        session = console.Session(link, PROGRAM, PERIOD, out)
        session.state("back>front")
        session.pause()
        session.topology()
        session.resume()
        first = link.command(op.StateRequest(()), 1.0)
        link.send_signed(op.sign(op.StateRequest(()), first.counter, KEY))
        time.sleep(10 * PERIOD)
    finally:
        link.close()
        cable.close()
        stop.set()
        for t in threads:
            t.join(timeout=5)
        for rt in modules:
            rt.close()
    text = out.getvalue()
    assert session.failures == 0, text
    assert "module back>front: tail (T2)" in text and "(cable): head (T1)\n  back>front: tail (T2)" in text
    assert first.reply is not None and first.reply.status.type_index == modules[0].engine.type_index
    assert not any(rt.paused for rt in modules)
    assert modules[0].stats.log and any("REPLAYED" in line for line in modules[0].log)


def test_watch_shows_the_hormones_the_cables_module_receives(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The cable in a caterpillar tail's back: ``watch X`` shows the wave's hormones as they
    reach it, each as dump writes a hop; ``watch`` alone shows every hormone."""
    source = SOURCE.with_name("caterpillar.dh2")
    with snake(tmp_path, 2, compile_bundled("caterpillar.dh2"), at_tail=True) as robot:
        time.sleep(10 * PERIOD)
        path = tmp_path / "commands.txt"
        path.write_text("watch X for 0.5\nwatch for 0.2\n")
        argv = ["--port", robot.cable, "--key", str(robot.key_file), "--program", str(source), "--cycle-ms", "20"]
        code = console.main([*argv, "--script", str(path)])
        tail = robot.channels[1].core
    out = capsys.readouterr().out
    assert code == 0, out
    lines = [line for line in out.splitlines() if line.startswith("cycle ")]
    assert len(lines) >= 2 and all(" at front  hormone   X(" in line and " via back" in line for line in lines), out
    assert {line.split("X(")[1][0] for line in lines} <= {"A", "B", "C", "D"}
    first = re.search(r"watched 0.5 s: (\d+) hormone", out)
    assert first is not None and int(first[1]) >= 2, out
    assert re.search(r"watched 0.2 s: [1-9]\d* hormone", out), out
    assert tail.watch is None or tail.watch[2] <= tail.module.cycle + 1  # a watch ends by itself
