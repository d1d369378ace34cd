"""The dh2rt command: exit codes, messages, summaries and traces."""

from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dh2rt.cli import main
from dh2rt.plugins import OptionAdder

ROOT = Path(__file__).resolve().parents[2]


def test_check_ok(examples: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(examples / "caterpillar.dh2")]) == 0
    out = capsys.readouterr().out
    assert "8 receptors" in out and "1 hormones" in out and "ClockCycle 40" in out


def test_check_error_prints_position_line_and_caret(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.dh2"
    bad.write_text("const ClockCycle = 4\nhormone X\nreceptor r when T == head {\n  emit X via flank\n}\n")
    assert main(["check", str(bad)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0] == f"{bad}:4:14: unknown connector 'flank' (profile conro: front, back, left, right)"
    assert err[1] == "      emit X via flank"
    assert err[2] == "                 ^"


def test_run_prints_summary_and_writes_trace(
    examples: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    trace = tmp_path / "t.jsonl"
    code = main(
        [
            "run",
            str(examples / "caterpillar.dh2"),
            "--topology",
            "snake:4",
            "--cycles",
            "60",
            "--seed",
            "2",
            "--event",
            "30:cut:m1.back",
            "--trace",
            str(trace),
        ]
    )
    assert code == 0
    out = capsys.readouterr().out
    assert "snake:4: 4 modules, 60 cycles" in out and "cycle 30: 30:cut:m1.back" in out
    lines = [json.loads(x) for x in trace.read_text().splitlines()]
    assert len(lines) == 4 * 60
    first = lines[0]
    assert {"cycle", "module", "type", "T", "actuators", "received", "sent"} <= set(first)
    assert first["cycle"] == 0 and first["module"] == 0 and first["type"] == "head" and first["T"] == 1
    assert set(first["actuators"]) == {"DOF1", "DOF2"}
    sent = [x for x in lines if x["sent"]]
    assert sent and sent[0]["sent"][0]["through"] == "back"
    received = [x for x in lines if x["received"]]
    assert received[0]["received"][0]["at"] == "front" and received[0]["received"][0]["from"] == "back"
    # after the cut at cycle 30, module 2 is a head
    assert [x["type"] for x in lines if x["module"] == 2 and x["cycle"] == 31] == ["head"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--topology", "snake:q"], "expected snake:N"),
        (["--event", "10:cut:m9.back"], "no module 'm9'"),
        (["--event", "10:cut:m1.tail"], "unknown connector 'tail'"),
        (["--event", "10:inject:m1:Q"], "unknown hormone 'Q'"),
        (["--event", "10:inject:m1:X(E)"], "'E' is not one of A | B | C | D"),
        (["--event", "ten:cut:m1.back"], "expected CYCLE:KIND:ARGS"),
        (["--event", "1:explode:m1"], "unknown kind 'explode'"),
    ],
)
def test_run_bad_input_exits_2_with_a_clear_message(
    examples: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    assert main(["run", str(examples / "caterpillar.dh2"), "--cycles", "5", *args]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_run_missing_program(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "nope.dh2"]) == 2
    assert "nope.dh2: cannot read program" in capsys.readouterr().err


def test_image_and_types(examples: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "c.img"
    assert main(["image", str(examples / "caterpillar.dh2"), "-o", str(out)]) == 0
    assert out.read_bytes().startswith(b"DH2IMG1\n")
    assert main(["types"]) == 0
    text = capsys.readouterr().out
    assert "body" in text and "T16" in text


def test_demo_runs_and_reports_ok(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo"]) == 0
    out = capsys.readouterr().out
    assert "demo ok" in out and "11-module snake" in out


@pytest.mark.parametrize(
    "args",
    [
        ["--help"],
        ["check", "--help"],
        ["run", "--help"],
        ["image", "--help"],
        ["demo", "--help"],
        ["console", "--help"],
    ],
)
def test_console_script_help(args: list[str]) -> None:
    exe = Path(sys.executable).with_name("dh2rt")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "dh2rt"]
    proc = subprocess.run([*cmd, *args], capture_output=True, text=True, timeout=60, cwd=ROOT, env={**os.environ})
    assert proc.returncode == 0, proc.stderr
    assert "usage: dh2rt" in proc.stdout


@pytest.mark.parametrize("args", [["types"], ["image", "--inspect", "IMAGE"], ["check", "PROGRAM"]])
def test_a_reader_that_went_away_is_no_traceback(args: list[str], tmp_path: Path) -> None:
    """``dh2rt ... | head``: the reader closed the pipe before the command wrote; it ends
    quietly with its exit code, as a Unix filter does."""
    program = ROOT / "examples" / "caterpillar.dh2"
    image = tmp_path / "cat.img"
    assert main(["image", str(program), "-o", str(image)]) == 0
    argv = [str(image) if a == "IMAGE" else str(program) if a == "PROGRAM" else a for a in args]
    exe = Path(sys.executable).with_name("dh2rt")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "dh2rt"]
    read, write = os.pipe()
    os.close(read)  # nobody will read: every write fails with EPIPE
    try:
        proc = subprocess.run([*cmd, *argv], stdout=write, stderr=subprocess.PIPE, text=True, timeout=60, cwd=ROOT)
    finally:
        os.close(write)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr, proc.stderr


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_only_on_a_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    from dh2rt import cmdline

    clock = iter(float(x) for x in range(1000))
    monkeypatch.setattr(cmdline.time, "perf_counter", lambda: next(clock))  # type: ignore[attr-defined]
    tty, pipe = _Tty(), io.StringIO()
    for stream in (tty, pipe):
        p = cmdline.Progress(1280, 10, stream)
        for cycle in range(1, 1281):
            p.update(cycle)
        p.done()
    assert "cycle 64/1280 (5%)" in tty.getvalue() and "module-cycles/s" in tty.getvalue()
    assert tty.getvalue().endswith("\r")  # the line is cleared at the end
    assert pipe.getvalue() == ""


def test_ctrl_c_stops_at_a_whole_cycle(examples: Path, caterpillar: object) -> None:
    """Ctrl-C: exit 130 and a summary of every module at one cycle, the very state a run of
    exactly that many cycles ends in (the run goes in skewed windows; none is left half done)."""
    import signal
    import time

    from dh2rt.robot import Robot
    from dh2rt.topology import parse_spec

    args = ["run", str(examples / "caterpillar.dh2"), "--topology", "snake:3000", "--cycles", "10000000", "--json"]
    exe = Path(sys.executable).with_name("dh2rt")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "dh2rt"]
    # how long start-up takes on this machine now (about 1 s; much more on a loaded one)
    started = time.monotonic()
    subprocess.run([*cmd, *args[:-3], "--cycles", "1"], capture_output=True, cwd=ROOT, timeout=120, check=True)
    startup = time.monotonic() - started
    proc = subprocess.Popen([*cmd, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        time.sleep(max(3.0, 2 * startup))  # well into the run
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    summary = json.loads(out)
    cycles = summary["cycles"]
    assert 0 < cycles < 10000000 and f"interrupted at cycle {cycles}" in err
    robot = Robot(caterpillar, parse_spec("snake:3000"), seed=0)  # type: ignore[arg-type]
    robot.advance(cycles)
    expected = json.loads(json.dumps(robot.summary()))
    assert summary["modules"] == expected


def test_second_ctrl_c_stops_at_once() -> None:
    import signal

    from dh2rt.cmdline import StopAtCycleEnd

    before = signal.getsignal(signal.SIGINT)
    with StopAtCycleEnd() as stop:
        assert signal.getsignal(signal.SIGINT) is not before
        stop.check()  # nothing asked yet
        signal.raise_signal(signal.SIGINT)
        assert stop.requested and not stop.forced
        with pytest.raises(KeyboardInterrupt):
            stop.check()
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
        assert stop.forced
    assert signal.getsignal(signal.SIGINT) is before


def test_registered_commands_are_listed_and_dispatched(capsys: pytest.CaptureFixture[str]) -> None:
    """Upper layers' commands come through the entry-point groups, not imports in the core."""
    from dh2rt.plugins import COMMAND_GROUP, SIMULATOR_GROUP, registered

    assert "launch" in registered(COMMAND_GROUP)
    assert "pybullet" in registered(SIMULATOR_GROUP)
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "registered commands" in out and "launch" in out and "hardware-in-the-loop" in out
    assert main(["launch", "--help"]) == 0  # the launcher turns argparse's exit into its code
    assert "--transport" in capsys.readouterr().out


def test_missing_registered_command_is_a_usage_error(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from dh2rt import cli

    monkeypatch.setattr(cli, "registered", lambda group: {})
    assert main(["--transport", "serial"]) == 2
    assert "no command 'launch' is installed" in capsys.readouterr().err
    assert main(["run", "examples/caterpillar.dh2", "--cycles", "1"]) == 0  # the core still runs


class _FakeSimulator:
    """A simulator as a ``dh2rt.simulators`` entry point names one: its own options, its run."""

    def __init__(self) -> None:
        self.ran_with: list[object] = []

    def add_arguments(self, parser: OptionAdder) -> None:
        parser.add_argument("--wind", type=float, default=0.0, help="the fake's own option")

    def check(self, options: argparse.Namespace) -> None:
        pass

    def run(self, robot: object, options: argparse.Namespace, events: object) -> int:
        self.ran_with.append(options.wind)
        return 0


class _FakeEntryPoint:
    def __init__(self, obj: object) -> None:
        self.obj = obj

    def load(self) -> object:
        return self.obj


def test_simulators_bring_their_own_run_options(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The core declares no simulator option: each registered simulator adds its own, they are
    listed by ``run --help``, refused without their ``--sim`` and handed to the simulator."""
    from dh2rt import cli
    from dh2rt.plugins import COMMAND_GROUP, SIMULATOR_GROUP

    core = (ROOT / "dh2rt" / "cli.py").read_text()
    assert "pybullet" not in core and "--record" not in core and "--gui" not in core
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    out = capsys.readouterr().out
    assert "with --sim pybullet" in out
    for option in ("--record", "--camera", "--record-speed", "--plot", "--gui"):
        assert option in out

    fake = _FakeSimulator()
    groups = {COMMAND_GROUP: {}, SIMULATOR_GROUP: {"fake": _FakeEntryPoint(fake)}}
    monkeypatch.setattr(cli, "registered", lambda group: groups[group])
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    out = capsys.readouterr().out
    assert "with --sim fake" in out and "--wind" in out and "--record" not in out
    program = str(ROOT / "examples" / "caterpillar.dh2")
    assert main(["run", program, "--cycles", "1", "--wind", "3"]) == 2
    assert "--wind: these options need --sim fake" in capsys.readouterr().err
    assert main(["run", program, "--cycles", "1", "--sim", "fake", "--wind", "3"]) == 0
    assert fake.ran_with == [3.0]


def test_variables_and_sensors_are_in_the_trace_the_json_summary_and_with_vars_the_text(
    examples: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Legs to snake's V.waiting and V.quiet, and its S.docking, by name (issue 29): in every
    trace record as the cycle left them, in --json's rows as the run ended, and with --vars
    after the text summary's table."""
    trace = tmp_path / "t.jsonl"
    run = ["run", str(examples / "legs_to_snake.dh2"), "--topology", "dragon", "--cycles", "300",
           "--event", "5:inject:tail2:LTS"]  # fmt: skip
    assert main([*run, "--trace", str(trace), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["modules"]
    records = [json.loads(x) for x in trace.read_text().splitlines()]
    assert all(set(r["variables"]) == {"waiting", "quiet"} and set(r["sensors"]) == {"docking"} for r in records)
    # the program changed them: a foot waited to re-arm, a tail counted quiet cycles
    assert max(r["variables"]["waiting"] for r in records) > 0
    assert max(r["variables"]["quiet"] for r in records) > 1
    last = {r["name"]: r["variables"] for r in records}
    assert {r["name"]: r["variables"] for r in rows} == last
    assert main([*run, "--vars"]) == 0
    text = capsys.readouterr().out
    assert "variables and sensors:" in text
    for r in rows:
        v = r["variables"]
        assert f"  {r['name']}: V.waiting={v['waiting']} V.quiet={v['quiet']} S.docking=0" in text.splitlines()
    assert main(run) == 0
    assert "variables and sensors:" not in capsys.readouterr().out  # only when asked
    assert main([*run, "--trace", "-"]) == 0  # the trace on standard output, the summary on stderr
    out = capsys.readouterr().out
    assert [json.loads(x)["variables"] for x in out.splitlines()] == [r["variables"] for r in records]
