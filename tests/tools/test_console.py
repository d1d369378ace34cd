"""``dh2rt console`` over serial links: two legs-to-snake modules running in real time (threads,
each a ModuleRuntime on a serial transport with its operator channel), linked by the link
emulator's pty pairs, and the console's cable a third link into the head's free front. The
console reads states, draws the robot, injects LTS at a module, pauses and resumes; a replayed
command and one signed with another key are refused and counted; bad input exits 2 naming it."""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from dh2rt.bundled import compile_bundled
from dh2rt.runtime import ModuleRuntime
from dh2rt.signed_image import private_key_pem, public_key
from dh2rt.transport.base import PortEnd
from dh2rt.transport.serial_link import SerialTransport
from dh2rt.wire import operator as op
from dh2rt.wire.frame import FrameCodec
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


@pytest.fixture
def robot(tmp_path: Path) -> Iterator[Robot]:
    emulator = LinkEmulator()
    spine, cable = emulator.add_link(), emulator.add_link()
    codec = FrameCodec(PROGRAM.vocabulary, PROGRAM.profile.connector_count)
    modules = [ModuleRuntime(PROGRAM, SerialTransport(codec), module=i, cycle_period=PERIOD) for i in range(2)]
    modules[0].attach(BACK, PortEnd(spine.paths[0]))
    modules[1].attach(FRONT, PortEnd(spine.paths[1]))
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
    try:
        yield Robot(modules, channels, cable.paths[0], tmp_path / "robot.key", tmp_path / "other.key")
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=5)
        for rt in modules:
            rt.close()
        emulator.close()


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


def test_refusals_are_answered_counted_and_exit_1(
    robot: Robot, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert run_console(robot, tmp_path, "pause\n", key=robot.other_key_file) == 1
    assert "refused by the module at .: UNTRUSTED_KEY" in capsys.readouterr().out
    transport = open_cable(robot.cable, 115200)
    link = ConsoleLink(transport, KEY, period=PERIOD).start()
    try:
        first = link.command(op.Pause(), 0.3)
        assert first.answers == () and all(rt.paused for rt in robot.modules)
        replay = op.sign(op.Pause(), first.counter, KEY)
        link.send_signed(replay)
        late = link.command(op.Resume(), 0.5)
        assert late.refused is None
    finally:
        link.close()
        transport.close()
    head = robot.channels[0].core.counters
    assert head["refused_untrusted_key"] == 1 and head["refused_replayed"] == 1, head
    assert not robot.modules[0].paused


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
