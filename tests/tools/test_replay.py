"""``dh2rt replay``: a loop run's capture (the caterpillar on serial links, cut in the middle)
rebuilds every module's trace records exactly; planted breakpoints of each kind stop at the
cycle the run's own trace says; a frame removed from the capture is said, with where, and
replay carries on; bad input exits 2 naming it.

Where each breakpoint should stop is read from the run's own trace (what the robot did),
never from replay."""

from __future__ import annotations

import itertools
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from hil import launcher
from hil.pace import PACE
from tools import dump
from tools.capture_cycles import CycleMark, LinkMark, UnlinkMark, marks_path, read_marks
from tools.capture_reader import read_records
from tools.pcapng import LINKTYPE_CAN_SOCKETCAN, LINKTYPE_USER0, PcapngReader, PcapngWriter
from tools.reading import open_capture
from tools.replay import main

pytestmark = pytest.mark.realtime

ROOT = Path(__file__).resolve().parents[2]
CYCLES = 90
CUT_AT = 45  # world cycle of the cut between m3's back and m4's front
Record = dict[str, Any]


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Record]]:
    """The caterpillar on 8 modules over serial links, cut between m3 and m4: its capture
    and its own trace records."""
    folder = tmp_path_factory.mktemp("replay")
    capture, trace = folder / "robot.pcapng", folder / "robot.jsonl"
    code = PACE.call(
        launcher.main,
        ["--transport", "serial", "--module-count", "8", "--cycles", str(CYCLES), "--stand-in", "none",
         "--event", f"{CUT_AT}:cut:3.back", "--capture", str(capture), "--trace", str(trace)],
    )  # fmt: skip
    assert code == 0
    return capture, [json.loads(line) for line in trace.read_text().splitlines()]


def replay(capsys: pytest.CaptureFixture[str], *args: str | Path, code: int = 0) -> tuple[str, str]:
    assert main([str(a) for a in args]) == code
    out = capsys.readouterr()
    return out.out, out.err


def key(rec: Record) -> tuple[int, int, int]:
    return rec["module"], rec.get("life", 0), rec["cycle"]


def rewrite(source: Path, target: Path, keep: Callable[[int], bool]) -> Path:
    """``source`` again, with its cycle marks, keeping only the serial frames ``keep(i)``
    keeps (``i`` counts them from 0)."""
    interface = {LINKTYPE_CAN_SOCKETCAN: 0, LINKTYPE_USER0: 1}
    with source.open("rb") as fh:
        reader = PcapngReader(fh, source)
        reader.read_header()
        writer = PcapngWriter(target, reader.comments)
        serial = -1
        for packet in reader:
            serial += packet.linktype == LINKTYPE_USER0
            if packet.linktype != LINKTYPE_USER0 or keep(serial):
                writer.write(interface[packet.linktype], packet.timestamp, packet.data)
        writer.close()
    shutil.copyfile(marks_path(source), marks_path(target))
    return target


# ----------------------------------------------------------------------------- the capture


def test_the_capture_keeps_a_mark_per_reported_cycle_and_the_frames_read_as_before(
    run: tuple[Path, list[Record]], capsys: pytest.CaptureFixture[str]
) -> None:
    capture, records = run
    marks = list(read_marks(capture))
    cycles = [m for m in marks if isinstance(m, CycleMark)]
    links = {m.link: m.ends for m in marks if isinstance(m, LinkMark)}
    assert sorted((m.module, m.life, m.cycle) for m in cycles) == sorted(map(key, records))
    assert links == {i: ((i, 2), (i + 1, 1)) for i in range(7)}  # mi's back to mi+1's front
    by_key = {key(r): r for r in records}
    for m in cycles:
        rec = by_key[(m.module, m.life, m.cycle)]
        assert (m.timer, dict(m.status), m.t) == (rec["timer"], rec["status"], rec["t"])
        assert sum(m.took.values()) == len(rec["received"])
    # the capture itself is the wire's, as before: dump reads every frame, and only frames
    frames = list(read_records(capture))
    assert dump.main([str(capture)]) == 0
    assert len(capsys.readouterr().out.splitlines()) == len(frames)
    assert marks_path(capture).name == "robot.pcapng.cycles.jsonl"


# ----------------------------------------------------------------------------- the rebuild


def test_replay_rebuilds_every_modules_trace_records(
    run: tuple[Path, list[Record]], capsys: pytest.CaptureFixture[str]
) -> None:
    capture, records = run
    out, err = replay(capsys, capture)
    rebuilt = [json.loads(line) for line in out.splitlines()]
    assert {key(r): r for r in rebuilt} == {key(r): r for r in records}
    assert len(rebuilt) == len(records)
    assert not_run_facts(err) == []  # a complete capture: nothing replay cannot know, no divergence


def not_run_facts(err: str) -> list[str]:
    """The notes in replay's standard error other than frames a module ignored (a fact of
    the run: on a busy machine a link may fall silent for a moment, and the module then
    ignores what comes until its peer is verified again)."""
    return [line for line in err.splitlines() if not line.startswith("replay: ignored: ")]


def first_by_time(records: list[Record], wanted: Callable[[Record], bool]) -> tuple[int, int]:
    hit = min((r for r in records if wanted(r)), key=lambda r: r["t"])
    return hit["module"], hit["cycle"]


def stops(capsys: pytest.CaptureFixture[str], capture: Path, *args: str) -> list[dict[str, Any]]:
    out, _ = replay(capsys, capture, "--json", *args)
    found: list[dict[str, Any]] = json.loads(out)["stops"]
    return found


def test_a_receptor_breakpoint_stops_where_the_head_first_ran_it(
    run: tuple[Path, list[Record]], capsys: pytest.CaptureFixture[str]
) -> None:
    capture, records = run
    # head_a: the head's DOF1(+45) and X(A) out of its back, at LocalTimer 0
    expected = first_by_time(
        records, lambda r: r["type"] == "head" and {"hormone": "X(A)", "through": "back"} in r["sent"]
    )
    (stop,) = stops(capsys, capture, "--break", "receptor head_a fires", "--first")
    assert (stop["module"], stop["cycle"]) == expected
    assert stop["fired"] == ["head_a"] and stop["record"]["timer"] == 0


def test_a_hormone_breakpoint_stops_where_it_is_first_taken_in_or_sent(
    run: tuple[Path, list[Record]], capsys: pytest.CaptureFixture[str]
) -> None:
    capture, records = run
    expected = first_by_time(records, lambda r: any(h["hormone"] == "X(C)" for h in (*r["received"], *r["sent"])))
    (stop,) = stops(capsys, capture, "--break", "hormone X(C)", "--first")
    assert (stop["module"], stop["cycle"]) == expected


def test_a_type_breakpoint_stops_at_every_change_of_that_module(
    run: tuple[Path, list[Record]], capsys: pytest.CaptureFixture[str]
) -> None:
    capture, records = run
    m3 = sorted((r for r in records if r["module"] == 3), key=key)
    expected = [b["cycle"] for a, b in itertools.pairwise(m3) if a["type"] != b["type"]]
    assert expected, "the cut changes m3's type (its back is lost): the run must show it"
    found = stops(capsys, capture, "--break", "type of m3 changes")
    assert [s["cycle"] for s in found] == expected
    assert found[0]["record"]["type"] == m3[[r["cycle"] for r in m3].index(expected[0])]["type"]
    # the text form says where and the state
    out, _ = replay(capsys, capture, "--break", "type of 3 changes", "--first")
    assert out.startswith(f"break at m3 (module 3) cycle {expected[0]}, t ")
    assert "  receptors: head_a active" in out


# ----------------------------------------------------------------------------- gaps


def test_a_frame_removed_from_the_capture_is_said_with_where_and_replay_carries_on(
    run: tuple[Path, list[Record]], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    capture, records = run
    hops = list(open_capture(capture).hops())
    # the third hormone m4 sent m5 (link 4, side 0): which serial frame it is, and which of
    # m5's cycles took it in (the third hormone it took in at its front)
    serial = [h for h in hops if h.medium == "serial"]
    sent = [i for i, h in enumerate(serial) if (h.link, h.side, h.kind) == (4, 0, "hormone") and not h.lost]
    m5 = sorted((r for r in records if r["module"] == 5), key=key)
    taken = [r["cycle"] for r in m5 for a in r["received"] if a["at"] == "front"]
    removed = rewrite(capture, tmp_path / "removed.pcapng", lambda i: i != sent[2])
    out, _err = replay(capsys, removed, "--json")
    doc = json.loads(out)
    missing = [n for n in doc["notes"] if n["kind"] == "missing"]
    assert [(n["module"], n["cycle"]) for n in missing] == [(5, taken[2])]
    assert "at front" in missing[0]["text"] and "missing from the capture" in missing[0]["text"]
    # m4 sent it and the capture lacks it: said at m4
    assert any(n["module"] == 4 and n["kind"] == "diverged" and "not in the capture" in n["text"] for n in doc["notes"])
    # carried on: every cycle rebuilt, every other module's records as the run's
    rebuilt, _ = replay(capsys, removed)
    again = {key(r): r for r in map(json.loads, rebuilt.splitlines())}
    assert set(again) == {key(r) for r in records}
    assert all(again[key(r)] == r for r in records if r["module"] != 5)
    assert all(again[key(r)] == r for r in m5 if r["cycle"] < taken[2])


# ----------------------------------------------------------------------------- bad input


def test_a_file_that_is_not_a_capture_exits_2_naming_it(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    bogus = tmp_path / "bogus.pcapng"
    bogus.write_text("not a capture\n")
    _, err = replay(capsys, bogus, code=2)
    assert str(bogus) in err and "not a pcapng file" in err
    _, err = replay(capsys, tmp_path / "absent.pcapng", code=2)
    assert "absent.pcapng: no such capture file" in err


def test_a_capture_with_only_the_wire_exits_2_saying_what_replay_lacks(
    run: tuple[Path, list[Record]], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    wire = tmp_path / "wire.pcapng"
    shutil.copyfile(run[0], wire)  # the capture without the marks beside it: what a real robot's has
    _, err = replay(capsys, wire, code=2)
    assert f"{wire}: no cycle marks beside it (wire.pcapng.cycles.jsonl)" in err and "timer phase" in err


def test_a_program_the_hellos_do_not_name_exits_2(
    run: tuple[Path, list[Record]], capsys: pytest.CaptureFixture[str]
) -> None:
    other = ROOT / "examples" / "legs_to_snake.dh2"
    _, err = replay(capsys, run[0], "--program", other, code=2)
    assert f"--program {other}: digest " in err and "not the program the robot ran" in err
    # the robot's own program is taken
    _, err = replay(capsys, run[0], "--program", ROOT / "examples" / "caterpillar.dh2")
    assert not_run_facts(err) == []


@pytest.mark.parametrize(
    ("spec", "says"),
    [
        ("receptor head_z fires", "no receptor head_z in the program"),
        ("type of m9 changes", "no module m9 in the capture"),
        ("hormone Q", "no hormone Q in the program"),
        ("when it moves", "a breakpoint is 'hormone H'"),
    ],
)
def test_a_breakpoint_that_names_nothing_exits_2(
    run: tuple[Path, list[Record]], capsys: pytest.CaptureFixture[str], spec: str, says: str
) -> None:
    _, err = replay(capsys, run[0], "--break", spec, code=2)
    assert f"--break {spec!r}" in err or "--break hormone" in err
    assert says in err


def test_damaged_cycle_marks_exit_2_naming_the_file_and_line(
    run: tuple[Path, list[Record]], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    damaged = rewrite(run[0], tmp_path / "damaged.pcapng", lambda _i: True)
    marks = marks_path(damaged)
    lines = marks.read_text().splitlines()
    marks.write_text("\n".join([*lines[:5], '{"kind": "cycle", "time": 1}', *lines[5:]]) + "\n")
    _, err = replay(capsys, damaged, code=2)
    assert f"{marks}:6: not a cycle mark (KeyError: 'module')" in err
    marks.write_text("hello\n")
    _, err = replay(capsys, damaged, code=2)
    assert f"{marks}:1: not a cycle marks file" in err


def test_the_command_is_registered() -> None:
    exe = Path(sys.executable).with_name("dh2rt")
    proc = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 0 and "  replay     Rebuild every module's engine" in proc.stdout
    proc = subprocess.run([str(exe), "replay", "--help"], capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 0 and proc.stdout.startswith("usage: dh2rt replay")


# ----------------------------------------------------------------------------- the prompt


def test_the_prompts_commands_step_forward_and_back_from_a_script(
    run: tuple[Path, list[Record]], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    capture, records = run
    module, cycle = first_by_time(
        records, lambda r: r["type"] == "head" and {"hormone": "X(A)", "through": "back"} in r["sent"]
    )
    script = tmp_path / "walk.txt"
    script.write_text("break receptor head_a fires\ncontinue\nnext 2\nback 2\nreverse\nstate m3\n")
    out, _ = replay(capsys, capture, "--script", script)
    here = f"break at m{module} (module {module}) cycle {cycle}, t "
    assert out.count(here) == 2  # continue, then back 2 after next 2
    assert "replay> reverse\nno breakpoint hit that way" in out
    state = out.split("replay> state m3\n")[1]
    m3 = max((r for r in records if r["module"] == 3 and r["t"] <= records_t(records, module, cycle)), key=key)
    assert state.startswith(f"at m3 (module 3) cycle {m3['cycle']}, t ")
    script.write_text("next\ngoto m9 3\n")
    _, err = replay(capsys, capture, "--script", script, code=2)
    assert f"{script}:2: no module 'm9' in the capture" in err


def records_t(records: list[Record], module: int, cycle: int) -> float:
    t: float = next(r["t"] for r in records if (r["module"], r["cycle"]) == (module, cycle))
    return t


def spawn_prompt(capture: Path, home: Path) -> Any:
    """``dh2rt replay CAPTURE --step`` on a pty, at its first prompt, as a person starts it."""
    import pexpect

    exe = Path(sys.executable).with_name("dh2rt")
    env = {**os.environ, "HOME": str(home), "TERM": "dumb"}
    child = pexpect.spawn(str(exe), ["replay", str(capture), "--step"], env=env, encoding="utf-8", timeout=30)
    child.expect_exact("replay> ")
    return child


def test_the_interactive_prompt_completes_steps_and_leaves_on_ctrl_d(
    run: tuple[Path, list[Record]], tmp_path: Path
) -> None:
    pexpect = pytest.importorskip("pexpect", reason="pexpect (the dev extra) drives the interactive prompt")
    child = spawn_prompt(run[0], tmp_path)
    try:
        child.send("break rec\t")  # completion: the kind of breakpoint
        child.expect_exact("receptor")
        child.send(" head_\t")  # no single completion: complete the name by hand
        child.send("b fires\r")
        child.expect_exact("breakpoint 1: receptor head_b fires")
        child.sendline("continue")
        child.expect_exact(": receptor head_b fires")
        child.expect_exact("fired: head_b")
        child.expect_exact("replay> ")
        child.sendeof()  # Ctrl-D
        child.expect(pexpect.EOF)
    finally:
        child.close()
    assert child.exitstatus == 0, child.before
    assert "break receptor head_b fires" in (tmp_path / ".dh2rt_replay_history").read_text()


def test_ctrl_c_at_the_prompt_exits_130_without_a_traceback(run: tuple[Path, list[Record]], tmp_path: Path) -> None:
    pexpect = pytest.importorskip("pexpect", reason="pexpect (the dev extra) drives the interactive prompt")
    child = spawn_prompt(run[0], tmp_path)
    try:
        child.sendintr()  # Ctrl-C
        child.expect(pexpect.EOF)
        said = child.before
    finally:
        child.close()
    assert child.exitstatus == 130 and "interrupted" in said and "Traceback" not in said, said


# ----------------------------------------------------------------------------- the model


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Record]]:
    """The caterpillar on 8 modules over serial links, nothing cut: its capture and trace."""
    folder = tmp_path_factory.mktemp("replay-clean")
    capture, trace = folder / "clean.pcapng", folder / "clean.jsonl"
    code = PACE.call(
        launcher.main,
        ["--transport", "serial", "--module-count", "8", "--cycles", "60", "--stand-in", "none",
         "--capture", str(capture), "--trace", str(trace)],
    )  # fmt: skip
    assert code == 0
    return capture, [json.loads(line) for line in trace.read_text().splitlines()]


def test_a_clean_run_agrees_with_the_in_process_model(
    clean_run: tuple[Path, list[Record]], capsys: pytest.CaptureFixture[str]
) -> None:
    out, _ = replay(capsys, clean_run[0], "--model")
    assert out.startswith("no divergence between clean.pcapng.replayed.jsonl and model.jsonl\ncompared 8 modules")
    assert "the model cannot know" not in out


def test_a_planted_divergence_is_the_first_the_model_comparison_finds(
    clean_run: tuple[Path, list[Record]], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    capture = clean_run[0]
    hops = [h for h in open_capture(capture).hops() if h.medium == "serial"]
    sent = [i for i, h in enumerate(hops) if (h.link, h.side, h.kind) == (4, 0, "hormone") and not h.lost]
    planted = rewrite(capture, tmp_path / "planted.pcapng", lambda i: i != sent[1])
    out, _ = replay(capsys, planted, "--model", "--json", code=1)
    model = json.loads(out)["model"]
    first = model["divergence"]
    assert first["owner"] == "m5 (module 5)" and first["stream"].startswith("arrivals at front from back")
    assert first["index"] == 2  # m5's second hormone at its front is the one planted away
    assert model["after_unknown"] is False
    assert any(line.endswith("the run's own") for line in model["lines"]), model["lines"]


def test_the_model_says_what_it_cannot_know_of_a_cut(
    run: tuple[Path, list[Record]], capsys: pytest.CaptureFixture[str]
) -> None:
    out, _ = replay(capsys, run[0], "--model", "--json", code=1)
    model = json.loads(out)["model"]
    # m3's back to m4's front: undocked (the cut's unlink mark), then frames lost into it
    undocked, lost = model["unknown"]
    assert undocked.startswith("link 3 undocked (m3.back in its cycle ") and ", m4.front in its cycle " in undocked
    assert lost.startswith("link 3 lost frames from t ")
    # the first divergence is behind the cut (m4 becomes a head and starts a wave of its own),
    # none in front of it, where the model and the run had the same inputs
    assert model["divergence"]["owner"] in {f"m{m} (module {m})" for m in range(4, 8)}
    assert model["after_unknown"] is True
    judged = "it comes after what the model cannot know (the first: link 3 undocked"
    assert any(line.startswith(judged) for line in model["lines"])


def test_a_run_on_a_can_bus_is_rebuilt_too(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """python-can's virtual bus: the modules negotiate their link ids, and the link marks come
    from their logs of it; at the cut each end releases the link, and what the engine still
    sends through it is refused (not on the wire, not in the record)."""
    capture, trace = tmp_path / "bus.pcapng", tmp_path / "bus.jsonl"
    code = PACE.call(
        launcher.main,
        ["--transport", "virtual", "--module-count", "8", "--cycles", "70", "--stand-in", "none",
         "--event", "30:cut:3.back", "--capture", str(capture), "--trace", str(trace)],
    )  # fmt: skip
    assert code == 0
    capsys.readouterr()  # what the launcher said
    records = [json.loads(line) for line in trace.read_text().splitlines()]
    out, err = replay(capsys, capture)
    assert {key(r): r for r in map(json.loads, out.splitlines())} == {key(r): r for r in records}
    assert not_run_facts(err) == []
    # the cut is marked once, with the ends the modules negotiated the link at
    unlinked = [m for m in read_marks(capture) if isinstance(m, UnlinkMark)]
    assert [sorted(m.ends) for m in unlinked] == [[(3, 2), (4, 1)]]


def test_an_operators_pause_and_inject_are_rebuilt(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """The console on the launcher's cable pauses every module, resumes them and injects a
    hormone at the head: the paused cycles (LocalTimer stands still) hold the engine, what
    came meanwhile is taken in when it resumes, and the injected hormone is the head's."""
    from tools import console

    exe = Path(sys.executable).with_name("dh2rt")
    assert subprocess.run([str(exe), "keys", "new", "-o", "robot"], cwd=tmp_path, capture_output=True).returncode == 0
    argv = ["--transport", "serial", "--module-count", "4", "--cycles", "200", "--cycle-ms", "20", "--key", "robot",
            "--console", "cable", "--stand-in", "none", "--capture", "pz.pcapng", "--trace", "pz.jsonl"]  # fmt: skip
    run = subprocess.Popen([str(exe), *argv], cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        cable = tmp_path / "cable"
        deadline = time.monotonic() + 60
        while not (cable.exists() and cable.read_text().strip()):
            assert run.poll() is None and time.monotonic() < deadline, "the launcher never plugged the cable in"
            time.sleep(0.1)
        time.sleep(0.5)  # the modules' first cycles
        port = cable.read_text().strip()
        common = ["--port", port, "--key", str(tmp_path / "robot"), "--program", str(ROOT / "examples/caterpillar.dh2")]
        for commands in ("pause\n", "resume\ninject X(C)\n"):
            (tmp_path / "commands").write_text(commands)
            assert console.main([*common, "--cycle-ms", "20", "--script", str(tmp_path / "commands")]) == 0
        assert run.wait(timeout=120) in (0, launcher.EXIT_TOO_SLOW)  # late cycles do not matter here
    finally:
        if run.poll() is None:
            run.kill()
            run.wait()
    capsys.readouterr()
    records = [json.loads(line) for line in (tmp_path / "pz.jsonl").read_text().splitlines()]
    out, err = replay(capsys, tmp_path / "pz.pcapng")
    assert {key(r): r for r in map(json.loads, out.splitlines())} == {key(r): r for r in records}
    assert {line.split(" (module")[0] for line in err.splitlines() if line.startswith("replay: paused: ")} == {
        f"replay: paused: m{m}" for m in range(4)
    }
    assert any(a["at"] is None and a["hormone"] == "X(C)" for r in records for a in r["received"])


@pytest.mark.parametrize("seed", range(4))
def test_a_link_emulator_held_up_between_reading_and_delivering_does_not_lose_a_frame(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, seed: int
) -> None:
    """The emulator's process held up between reading a frame from its sender and writing
    it to the receiver (descheduled: here stopped with SIGSTOP for 20-100 ms at random
    moments) delivers it cycles after it was sent. Replay must take it in where the module
    did: stamped when it was read from the sender (as before), such a frame looked ignored
    and then missing (CI saw that, one run in many); stamped on delivery, it cannot."""
    exe = Path(sys.executable).with_name("dh2rt")
    argv = ["--transport", "serial", "--module-count", "4", "--cycles", "150", "--cycle-ms", "20",
            "--stand-in", "none", "--capture", "h.pcapng", "--trace", "h.jsonl"]  # fmt: skip
    rng = random.Random(seed)
    run = subprocess.Popen([str(exe), *argv], cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        while run.poll() is None:
            time.sleep(rng.uniform(0.02, 0.1))
            try:
                os.kill(run.pid, signal.SIGSTOP)
                time.sleep(rng.uniform(0.02, 0.1))
            finally:
                os.kill(run.pid, signal.SIGCONT)
        assert run.returncode in (0, launcher.EXIT_TOO_SLOW)  # late cycles are the point here
    finally:
        if run.poll() is None:
            run.kill()
            run.wait()
    records = [json.loads(line) for line in (tmp_path / "h.jsonl").read_text().splitlines()]
    out, err = replay(capsys, tmp_path / "h.pcapng")
    assert {key(r): r for r in map(json.loads, out.splitlines())} == {key(r): r for r in records}
    # (a link silent through a long hold goes down: what came meanwhile is ignored, as said)
    assert [line for line in err.splitlines() if line.startswith("replay: missing")] == []


@pytest.mark.long
def test_legs_to_snake_diverges_from_the_model_only_after_the_foot_is_released(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """The loop releases the winning foot and walks it by motion; the model (dh2rt run's
    rules) docks it at once. The first divergence is said to come after the release, which
    the unlink mark names with both ends' cycles."""
    capture = tmp_path / "lts.pcapng"
    code = PACE.call(
        launcher.main,
        ["--transport", "serial", "--program", str(ROOT / "examples" / "legs_to_snake.dh2"), "--topology", "dragon",
         "--cycles", "100", "--event", "5:inject:tail2:LTS", "--capture", str(capture)],
    )  # fmt: skip
    assert code == 0
    capsys.readouterr()
    out, _ = replay(capsys, capture, "--model", "--json", code=1)
    model = json.loads(out)["model"]
    assert model["after_unknown"] is True
    assert model["unknown"][0].startswith("link ") and " undocked (spine1." in model["unknown"][0]
    assert any(" undocked (spine1." in line and line.startswith("it comes after") for line in model["lines"])
