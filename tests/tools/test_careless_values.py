"""Careless values given to the capture and analysis tools (issue 27): every refusal exits 2
with a message naming the option, file or field, never a traceback; the output rule
(dh2rt.output_paths) is one for every command; Ctrl-C ends every command with 130."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest

from dh2rt.cli import main as dh2rt
from dh2rt.compiler import compile_file
from dh2rt.hormone import Hormone
from dh2rt.wire.can_frames import SINGLE, make_arbitration_id
from dh2rt.wire.frame import FrameCodec
from hil import launcher
from hil.netns import in_namespace, namespace_problem
from tools.capture import main as capture
from tools.capture_reader import capture_programs, read_records
from tools.capture_sink import FileSink
from tools.dump import main as dump
from tools.follow import main as follow
from tools.stats import main as stats
from tools.topo import main as topo
from tools.wireshark.command import main as wireshark

ROOT = Path(__file__).resolve().parents[2]
CATERPILLAR = ROOT / "examples" / "caterpillar.dh2"
Command = Callable[[list[str]], int]


@pytest.fixture
def robot(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A caterpillar capture carrying its program: X(A) sent on link 4 then forwarded once."""
    monkeypatch.chdir(tmp_path)
    program = compile_file(str(CATERPILLAR))
    codec = FrameCodec(program.vocabulary, program.profile.connector_count)
    path = tmp_path / "robot.pcapng"
    sink = FileSink(path, [program.image])
    sent = Hormone("X", ("A",))
    for t, link, hormone in ((1.0, 4, sent), (1.02, 5, Hormone("X", ("A",), ((2, 1),)))):
        msg = can.Message(
            timestamp=t, arbitration_id=make_arbitration_id(0, SINGLE, 0, link, 1), data=codec.encode(2, hormone)
        )
        sink.write_message(msg)
    sink.close()
    return path


def refused(capsys: pytest.CaptureFixture[str], code: int, *named: str) -> str:
    """Assert exit 2, no traceback and every ``named`` in the message; the message."""
    out = capsys.readouterr()
    assert code == 2, out
    assert "Traceback" not in out.err
    for name in named:
        assert name in out.err, out.err
    return out.err


# ------------------------------------------------------------------ the output rule


def test_an_output_that_cannot_be_written_is_refused_before_the_run(
    robot: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bus = ["-i", "udp_multicast", "-c", "239.74.163.2", "--duration", "1"]  # never opened: refused first
    refused(capsys, capture(["-o", "/proc/x.pcapng", *bus]), "-o /proc/x.pcapng", "/proc")
    refused(capsys, capture(["-o", str(tmp_path), *bus]), "is a folder")
    refused(capsys, wireshark(["--capture", str(robot), "-o", str(tmp_path)]), "-o", "is a folder")
    elsewhere = tmp_path.parent / f"{tmp_path.name}-missing" / "plugins" / "dh2rt.lua"  # outside the current folder
    err = refused(capsys, wireshark(["--capture", str(robot), "-o", str(elsewhere)]), "mkdir -p")
    assert str(elsewhere.parent) in err and not elsewhere.parent.parent.exists()
    assert dh2rt(["image", str(CATERPILLAR), "-o", "/nonexistent-dh2rt/x.img"]) == 2
    assert not Path("/nonexistent-dh2rt").exists()
    refused(capsys, 2, "/nonexistent-dh2rt")
    # inside the current folder a missing folder is made: that is where outputs go
    assert wireshark(["--capture", str(robot), "-o", "plugins/dh2rt.lua"]) == 0
    assert (tmp_path / "plugins" / "dh2rt.lua").read_text().startswith("--")


def test_a_capture_or_a_key_is_never_overwritten_without_force(
    robot: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = robot.read_bytes()
    bus = ["-i", "udp_multicast", "-c", "239.74.163.2", "--duration", "1"]
    refused(capsys, capture(["-o", str(robot), *bus]), "robot.pcapng", "--force")
    refused(capsys, wireshark(["--capture", str(robot), "-o", str(robot)]), "is a capture", "--force")
    key = tmp_path / "signing"
    key.write_text("-----BEGIN PRIVATE KEY-----\nMC4CAQAwBQYDK2VwBCIEI\n-----END PRIVATE KEY-----\n")
    refused(capsys, wireshark(["--capture", str(robot), "-o", str(key)]), "is a key", "--force")
    refused(capsys, dh2rt(["image", str(CATERPILLAR), "-o", str(key)]), "is a key")
    assert robot.read_bytes() == before and key.read_text().startswith("-----BEGIN PRIVATE KEY")
    # what the command writes anyway is written again; with --force anything is
    lua = tmp_path / "dh2rt.lua"
    assert wireshark(["--capture", str(robot), "-o", str(lua)]) == 0
    assert wireshark(["--capture", str(robot), "-o", str(lua)]) == 0
    assert wireshark(["--capture", str(robot), "-o", str(key), "--force"]) == 0
    assert key.read_text().startswith("--")


def test_png_dir_follows_the_same_rule(robot: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    refused(capsys, topo([str(robot), "--png-dir", str(robot)]), "--png-dir", "is a file")
    refused(capsys, topo([str(robot), "--png-dir", "/nonexistent-dh2rt/topo"]), "--png-dir", "mkdir -p")
    assert not Path("/nonexistent-dh2rt").exists()


# ------------------------------------------------------------------ values


@pytest.mark.parametrize("option", ["--bitrate", "--baud"])
@pytest.mark.parametrize("value", ["0", "-1"])
def test_stats_rates_must_be_positive(option: str, value: str, robot: Path, capsys: pytest.CaptureFixture[str]) -> None:
    refused(capsys, stats([str(robot), option, value]), option, "1 or more")


def test_capture_refuses_a_duration_that_never_ends(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for value in ("nan", "inf", "-1"):
        out = tmp_path / f"{value}.pcapng"
        code = capture(["-o", str(out), "-i", "udp_multicast", "-c", "239.74.163.2", "--duration", value])
        refused(capsys, code, "--duration")
        assert not out.exists()


def test_capture_refuses_a_virtual_bus_nobody_can_send_on(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = capture(["-o", str(tmp_path / "x.pcapng"), "-i", "virtual", "-c", "nobody-here", "--duration", "1"])
    refused(capsys, code, "-i virtual", "only inside the process", "--capture")


def test_a_name_too_long_is_named_not_a_traceback(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    long = str(tmp_path / ("a" * 5000))
    for command in (dump, stats):
        err = refused(capsys, command([long]), "characters)", "too long")
        assert len(err) < 400


@pytest.mark.parametrize("command", [dump, stats, topo], ids=["dump", "stats", "topo"])
def test_a_damaged_program_in_a_capture_is_named(
    command: Command, robot: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    image = capture_programs(robot)[0].replace(b'"op":"/"', b'"op":"%%"', 1)  # the compiler: KeyError
    damaged = tmp_path / "damaged.pcapng"
    sink = FileSink(damaged, [image])
    sink.close()
    refused(capsys, command([str(damaged)]), "damaged.pcapng", "damaged capture", "program image 1", "%%")


def test_follow_names_a_hormone_that_is_malformed_or_not_the_programs(
    robot: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    refused(capsys, follow([str(robot), "NOPE"]), "NOPE", "no hormone NOPE in the program")
    refused(capsys, follow([str(robot), "X(("]), "X((", "malformed")
    refused(capsys, follow([str(robot), "X(Q)"]), "X(Q)", "'Q'")
    assert follow([str(robot), "X( A )", "--no-chain"]) == 0  # written loosely, still the program's X(A)
    assert "X(A) from 1.000000 s" in capsys.readouterr().out
    assert follow([str(robot), "X(B)", "--no-chain"]) == 1  # the program's, but not in the capture
    assert "no X(B) sent" in capsys.readouterr().err


def test_dump_names_a_hormone_the_program_has_not(robot: Path, capsys: pytest.CaptureFixture[str]) -> None:
    refused(capsys, dump([str(robot), "--hormone", "NOPE"]), "--hormone", "NOPE", "no hormone NOPE in the program")
    assert dump([str(robot), "--hormone", "X(A)"]) == 0
    assert len(capsys.readouterr().out.splitlines()) == 2


def test_an_image_given_as_program_is_loaded_or_refused(
    robot: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    image = tmp_path / "caterpillar.img"
    assert dh2rt(["image", str(CATERPILLAR), "-o", str(image)]) == 0
    capsys.readouterr()
    assert dump([str(robot), "--program", str(image)]) == 0  # the tools load an image as the program
    assert "X(A) via back" in capsys.readouterr().out
    err = refused(capsys, dh2rt(["image", str(image), "-o", str(tmp_path / "again.img")]), "image already")
    assert "\ufffd" not in err and "\x00" not in err
    (tmp_path / "broken.img").write_bytes(b"DH2S" + bytes(range(200)))
    refused(capsys, dump([str(robot), "--program", str(tmp_path / "broken.img")]), "--program", "broken.img")


# ------------------------------------------------------------------ Ctrl-C


def run_command(*args: str) -> list[str]:
    return [sys.executable, "-m", "dh2rt.cli", *args]


@pytest.fixture
def fifo(tmp_path: Path) -> Iterator[Path]:
    """A capture that is a named pipe: a command reading it waits for frames as long as it is
    let, which is where Ctrl-C comes."""
    path = tmp_path / "live.pcapng"
    os.mkfifo(path)
    yield path


def writer_once_read(path: Path, proc: subprocess.Popen[str], timeout: float = 60.0) -> int:
    """The write end of the pipe ``path``, opened once ``proc`` has it open to read (a
    non-blocking open for writing fails until a reader has)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        try:
            return os.open(path, os.O_WRONLY | os.O_NONBLOCK)
        except OSError:
            time.sleep(0.05)
    raise AssertionError(f"{proc.args!r} never read {path}")


def interrupted(proc: subprocess.Popen[str]) -> tuple[int, str]:
    proc.send_signal(signal.SIGINT)
    _out, err = proc.communicate(timeout=60)
    return proc.returncode, err


@pytest.mark.parametrize(
    "args",
    [
        ["dump", "{capture}"],
        ["stats", "{capture}"],
        ["follow", "{capture}", "X"],
        ["topo", "{capture}"],
        ["diff", "{capture}", "{capture}"],
        ["wireshark", "--capture", "{capture}"],
    ],
    ids=lambda args: args[0],
)
def test_ctrl_c_ends_every_reading_command_with_130(args: list[str], fifo: Path) -> None:
    cmd = run_command(*(a.format(capture=fifo) for a in args))
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    fd = writer_once_read(fifo, proc)
    try:
        time.sleep(0.2)
        code, err = interrupted(proc)
    finally:
        os.close(fd)
    assert code == 130 and "interrupted" in err and "Traceback" not in err, err


def test_ctrl_c_ends_a_capture_with_130_and_a_readable_file(tmp_path: Path) -> None:
    if why := namespace_problem():
        pytest.skip(f"udp_multicast needs a private network namespace: {why}")
    out = tmp_path / "ctrl-c.pcapng"
    cmd = run_command(
        "capture", "-o", str(out), "-i", "udp_multicast", "-c", "239.74.163.2", "--duration", "600",
        "--program", str(CATERPILLAR),
    )  # fmt: skip
    proc = subprocess.Popen(in_namespace(cmd), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    deadline = time.monotonic() + 60
    while not out.exists():  # the file is made once the bus is open
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.05)
    time.sleep(0.3)
    code, err = interrupted(proc)
    assert code == 130 and "Traceback" not in err, err
    assert list(read_records(out)) == []  # closed whole: it reads to its end
    assert capture_programs(out) == [compile_file(str(CATERPILLAR)).image]


def test_the_launchers_own_log_named_dot_log_is_written_again_only_with_force(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A name ending in .log reads as a candump capture, so a second run with the same
    ``--log run.log`` is refused; ``--force`` writes over it (hil.pace passes it to a run it
    makes again: a CI run's remake was refused here)."""
    log = tmp_path / "run.log"
    args = ["--transport", "inproc", "--module-count", "1", "--cycles", "0", "--stand-in", "none", "--log", str(log)]
    assert launcher.main(args) == 0 and log.exists()
    refused(capsys, launcher.main(args), "--log", "--force")
    assert launcher.main([*args, "--force"]) == 0
