"""`dh2rt diff`: the in-process robot and a clean run in the loop (modules as threads on
python-can's virtual bus) agree hop by hop; a divergence planted in one of two traces is
found, named by module, stream, index and cycle; tails cut by the end of a run are not
divergences, a stream that stops while its module runs on is; arrivals along different
routes may interleave differently, along one route they may not; captures compare per link
end; a file that is not a trace ends with exit 2 and a message naming file, line and field."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from dh2rt import cli
from dh2rt.compiler import compile_file
from dh2rt.hormone import Hormone
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from dh2rt.wire.can_frames import segment
from dh2rt.wire.frame import FrameCodec
from hil import launcher
from hil.pace import PACE
from tests.marks import sweep
from tools.diff import main
from tools.pcap import CapturedFrame, write_pcap

ROOT = Path(__file__).resolve().parents[2]
CATERPILLAR = str(ROOT / "examples" / "caterpillar.dh2")
CYCLES = 120
Record = dict[str, Any]
#: an arrival as (hormone, at, from, path)
Arrived = tuple[str, str, str, list[list[str]]]


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


def in_process(path: Path, seed: int) -> Path:
    assert cli.main(["run", CATERPILLAR, "--cycles", str(CYCLES), "--seed", str(seed), "--trace", str(path)]) == 0
    return path


def in_the_loop(path: Path, seed: int) -> Path:
    code = PACE.call(
        launcher.main,
        ["--transport", "virtual", "--module-count", "8", "--cycles", str(CYCLES), "--seed", str(seed),
         "--stand-in", "none", "--trace", str(path)]
    )  # fmt: skip
    assert code == 0
    return path


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The caterpillar with seed 3, in process and in the loop (the loop's trace is where
    divergences are planted below)."""
    folder = tmp_path_factory.mktemp("runs")
    return in_process(folder / "robot.jsonl", 3), in_the_loop(folder / "loop.jsonl", 3)


def diff_json(capsys: pytest.CaptureFixture[str], *args: str, code: int) -> dict[str, Any]:
    assert main([*args, "--json"]) == code
    out: dict[str, Any] = json.loads(capsys.readouterr().out)
    return out


def read(path: Path) -> list[Record]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def write(path: Path, records: list[Record]) -> Path:
    path.write_text("".join(json.dumps(r) + "\n" for r in records))
    return path


def planted(source: Path, target: Path, change: Callable[[list[Record]], None]) -> Path:
    records = read(source)
    change(records)
    return write(target, records)


def module_records(records: list[Record], module: int) -> list[Record]:
    return sorted((r for r in records if r["module"] == module), key=lambda r: r["cycle"])


def with_arrivals(records: list[Record], module: int) -> list[Record]:
    return [r for r in module_records(records, module) if r["received"]]


# ------------------------------------------------------------------ the in-process robot and the loop


@pytest.mark.parametrize("seed", sweep([1, 4]))
def test_a_clean_loop_run_agrees_with_the_in_process_robot(
    seed: int, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    robot = in_process(tmp_path / "robot.jsonl", seed)
    loop = in_the_loop(tmp_path / "loop.jsonl", seed)
    capsys.readouterr()
    out = diff_json(capsys, str(robot), str(loop), code=0)
    assert out["divergence"] is None
    arrivals = {f"m{m} (module {m})": 0 for m in range(8)}
    moves = dict(arrivals)
    for s in out["streams"]:
        assert s["compared"] >= min(s["a"], s["b"]) and max(s["a"], s["b"]) - s["compared"] <= 2  # cut tails only
        if s["stream"] == "actuator changes":
            moves[s["owner"]] += s["compared"]
        else:
            assert s["stream"] == "arrivals at front from back, path (none)"  # head to tail, one link at a time
            arrivals[s["owner"]] += s["compared"]
    # every module took part: the head moved 6 times in 120 cycles, sending a hormone each
    # time; each module after it took in ~11 (seed's phase) and moved at every other one
    assert all(n >= 5 for n in moves.values()) and len(moves) == 8, moves
    assert arrivals.pop("m0 (module 0)") == 0 and all(n >= 10 for n in arrivals.values()), arrivals
    assert main([str(robot), str(loop)]) == 0
    assert capsys.readouterr().out.startswith("no divergence between robot.jsonl and loop.jsonl\ncompared 8 modules")


# ------------------------------------------------------------------ planted divergences


def test_a_changed_hormone_is_the_first_divergence(
    runs: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    robot, loop = runs
    loop_records = read(loop)
    target = with_arrivals(loop_records, 4)[5]  # m4's 6th arrival, in the middle of the run
    before = target["received"][0]["hormone"]
    after = "X(A)" if before != "X(A)" else "X(B)"
    target["received"][0]["hormone"] = after
    bad = write(tmp_path / "bad.jsonl", loop_records)
    out = diff_json(capsys, str(robot), str(bad), code=1)
    d = out["divergence"]
    assert (d["owner"], d["stream"], d["index"]) == ("m4 (module 4)", "arrivals at front from back, path (none)", 6)
    assert (d["a"]["event"], d["b"]["event"]) == (before, after)
    assert d["b"]["where"] == f"cycle {target['cycle']}, line {loop_records.index(target) + 1}"
    robot_cycle = with_arrivals(read(robot), 4)[5]["cycle"]
    assert d["a"]["where"].startswith(f"cycle {robot_cycle},")
    # in words, with the cycle in each file for orientation
    assert main([str(robot), str(bad)]) == 1
    text = capsys.readouterr().out.splitlines()
    assert text[0] == "robot.jsonl and bad.jsonl diverge at m4 (module 4), 6th arrival at front from back, path (none):"
    assert text[1].split() == ["robot.jsonl", before, "[cycle", f"{robot_cycle},", "line", text[1].split()[-1]]
    assert text[2].split()[:4] == ["bad.jsonl", after, "[cycle", f"{target['cycle']},"]
    assert text[3] == "  (the 5 before it agree)"


def test_a_changed_angle_is_found(runs: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    robot, loop = runs

    def bend(records: list[Record]) -> None:
        for r in module_records(records, 2)[60:]:  # from the middle on, m2's DOF2 reads 10
            r["actuators"]["DOF2"] = 10.0

    out = diff_json(capsys, str(robot), str(planted(loop, tmp_path / "bent.jsonl", bend)), code=1)
    d = out["divergence"]
    assert (d["owner"], d["stream"]) == ("m2 (module 2)", "actuator changes")
    assert d["a"]["event"].endswith("DOF2 0") and d["b"]["event"].endswith("DOF2 10")
    assert d["b"]["where"].startswith("cycle 60,")


def test_a_hormone_lost_midway_is_found_but_a_tail_cut_by_the_end_is_not(
    runs: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    robot, loop = runs
    robot_records = read(robot)
    last = with_arrivals(robot_records, 6)[-1]

    def cut_tail(records: list[Record]) -> None:  # the robot's run ends before m6's last hormone
        records[:] = [r for r in records if not (r["module"] == 6 and r["cycle"] >= last["cycle"])]

    short = planted(robot, tmp_path / "short.jsonl", cut_tail)
    out = diff_json(capsys, str(short), str(loop), code=0)
    [cut] = [s for s in out["streams"] if s["owner"] == "m6 (module 6)" and s["cut"] and "arrivals" in s["stream"]]
    # the last one, and the loop's own extra one if it ran a little ahead of the robot
    assert cut["cut"].startswith("loop.jsonl has ") and cut["b"] - cut["compared"] in (1, 2), cut

    def lose(records: list[Record]) -> None:  # m6 runs on to the end, but one hormone never came
        with_arrivals(records, 6)[4]["received"] = []

    out = diff_json(capsys, str(robot), str(planted(loop, tmp_path / "lost.jsonl", lose)), code=1)
    d = out["divergence"]
    assert d["owner"] == "m6 (module 6)" and d["stream"].startswith("arrivals") and d["index"] == 5
    lost_robot = with_arrivals(robot_records, 6)
    # the loop's 5th is the robot's 6th: the first that differs (X cycles through four contents)
    assert (d["a"]["event"], d["b"]["event"]) == (
        lost_robot[4]["received"][0]["hormone"],
        lost_robot[5]["received"][0]["hormone"],
    )

    def stop_hearing(records: list[Record]) -> None:  # m6's last 3 hormones never came, it ran on
        for r in with_arrivals(records, 6)[-3:]:
            r["received"] = []

    out = diff_json(capsys, str(robot), str(planted(loop, tmp_path / "deaf.jsonl", stop_hearing)), code=1)
    d = out["divergence"]
    assert d["owner"] == "m6 (module 6)" and d["b"] is None and d["a"]["event"].startswith("X(")
    # as far as m6 ran in the loop (fewer than CYCLES when the machine held it: it counts the
    # periods it lost), and past the first hormone that never came: it ran on, deaf
    ran = 1 + max(int(r["cycle"]) for r in read(loop) if r["module"] == 6)
    assert ran > int(with_arrivals(read(loop), 6)[-3]["cycle"]), ran
    assert "it would have come about its" in d["note"] and f"went on to its {ran}th cycle" in d["note"]


def test_a_module_missing_from_one_file_is_a_divergence(
    runs: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    robot, loop = runs

    def drop_m7(records: list[Record]) -> None:
        records[:] = [r for r in records if r["module"] != 7]

    seven = planted(loop, tmp_path / "seven.jsonl", drop_m7)
    assert main([str(robot), str(seven)]) == 1
    assert capsys.readouterr().out.splitlines()[0] == "m7 (module 7) is in robot.jsonl only"


# ------------------------------------------------------------------ what order is significant


def rec(cycle: int, module: int, received: list[Arrived], dof1: float = 0.0) -> Record:
    """A record in the trace format, with arrivals as (hormone, at, from, path)."""
    return {
        "cycle": cycle,
        "module": module,
        "name": f"m{module}",
        "actuators": {"DOF1": dof1, "DOF2": 0.0},
        "received": [{"hormone": h, "at": at, "from": rem, "path": path} for h, at, rem, path in received],
        "sent": [],
    }


def test_arrivals_along_different_routes_may_interleave_along_one_route_they_may_not(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    x: Arrived = ("X(A)", "front", "back", [])
    y: Arrived = ("Y", "back", "front", [])
    z: Arrived = ("X(B)", "front", "back", [])
    forwarded: Arrived = ("X(C)", "front", "back", [["back", "left"]])  # came to the neighbour from its left
    # A: X(A) alone, then Y and X(B) together, then the forwarded one; B: other groupings
    a = write(tmp_path / "a.jsonl", [rec(0, 0, [x]), rec(1, 0, [z, y]), rec(2, 0, [forwarded]), rec(3, 0, [])])
    b = write(tmp_path / "b.jsonl", [rec(0, 0, [y]), rec(1, 0, [x, forwarded, z]), rec(2, 0, []), rec(3, 0, [])])
    assert main([str(a), str(b)]) == 0
    assert capsys.readouterr().out.startswith("no divergence")
    swapped = write(
        tmp_path / "swapped.jsonl", [rec(0, 0, [y, z]), rec(1, 0, [x, forwarded]), rec(2, 0, []), rec(3, 0, [])]
    )
    out = diff_json(capsys, str(a), str(swapped), code=1)
    d = out["divergence"]
    assert (d["stream"], d["index"], d["a"]["event"], d["b"]["event"]) == (
        "arrivals at front from back, path (none)",
        1,
        "X(A)",
        "X(B)",
    )


def test_actuator_changes_in_order_not_their_cycles(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a = write(tmp_path / "a.jsonl", [rec(c, 0, [], d) for c, d in enumerate([0, 45, 45, -45, -45, 45])])
    b = write(tmp_path / "b.jsonl", [rec(c, 0, [], d) for c, d in enumerate([0, 0, 45, -45, 45, 45])])
    assert main([str(a), str(b)]) == 0
    capsys.readouterr()
    c = write(tmp_path / "c.jsonl", [rec(c, 0, [], d) for c, d in enumerate([0, 0, 45, 45, 45, 45])])
    out = diff_json(capsys, str(a), str(c), "--slack", "0", code=1)
    d = out["divergence"]
    assert (d["stream"], d["index"], d["a"]["event"], d["b"]) == ("actuator changes", 2, "DOF1 -45, DOF2 0", None)
    capsys.readouterr()
    assert main([str(a), str(b), "--all"]) == 0


# ------------------------------------------------------------------ captures


def robot_capture(path: Path, seed: int, clock: float, plant: int | None = None) -> Path:
    """The caterpillar's hormones on CAN frames as the transport sends them, link ids by the
    topology's links; ``plant``: the frame number whose hormone becomes X(A)."""
    program = compile_file(CATERPILLAR)
    topo = parse_spec("snake:8", program.profile)
    robot = Robot(program, topo, seed=seed, record=True)
    codec = FrameCodec(program.vocabulary, program.profile.connector_count)
    ends: dict[tuple[int, int], tuple[int, int]] = {}
    for i, link in enumerate(topo.links):
        ends[(link.a, link.a_conn)] = (i, 0)
        ends[(link.b, link.b_conn)] = (i, 1)
    frames: list[CapturedFrame] = []
    for cycle in robot.iter_cycles(CYCLES):
        for r in robot.records:
            for through, h in r.sent:
                if (r.module, through) not in ends:
                    continue  # the tail's "emit via back": nothing docked there, nothing sent
                if plant is not None and len(frames) == plant:
                    h = Hormone("X", ("A",) if h.args != ("A",) else ("B",), h.path)
                link_id, side = ends[(r.module, through)]
                for f in segment(codec.encode(through, h), link_id, side):
                    frames.append(CapturedFrame(clock + cycle * 0.02 + r.module * 0.001, f.arbitration_id, f.data))
        robot.records.clear()
    write_pcap(path, frames)
    return path


def test_captures_compare_per_link_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a = robot_capture(tmp_path / "a.pcap", 1, clock=100.0)
    b = robot_capture(tmp_path / "b.pcap", 1, clock=5000.0)  # another clock: times are not compared
    assert main([str(a), str(b), "--program", CATERPILLAR]) == 0
    assert "compared 7 link ends" in capsys.readouterr().out
    c = robot_capture(tmp_path / "c.pcap", 1, clock=5000.0, plant=30)
    out = diff_json(capsys, str(a), str(c), "--program", CATERPILLAR, code=1)
    d = out["divergence"]
    assert d["owner"].startswith("link ") and d["stream"] == "hormones sent, path (none)"
    assert d["a"]["event"] != d["b"]["event"] and d["b"]["event"].endswith("via back")


# ------------------------------------------------------------------ bad input


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('{"cycle": 0}\n{"cycle": 1,,}\n', "bad.jsonl:1: no field 'module'"),
        ("not json\n", "bad.jsonl:1:1: not JSON"),
        ('{"cycle": 0, "module": 0, "name": "m0", "actuators": {"DOF1": 0, "DOF2": 0}, "received": []}\n'
         '{"cycle": 1, "module": 0, "name": "m0", "actuators": {"DOF1": 0, "DOF2": 0}, "received": [5]}\n',
         "bad.jsonl:2: field received[0]: expected an object, got a whole number (5)"),
        ('{"cycle": 0, "module": 0, "name": "m0", "actuators": {"DOF1": "up", "DOF2": 0}, "received": []}\n',
         "bad.jsonl:1: field actuators.DOF1: expected a number, got a string"),
        ('{"cycle": -1, "module": 0, "name": "m0", "actuators": {"DOF1": 0, "DOF2": 0}, "received": []}\n',
         "bad.jsonl:1: field cycle: expected a whole number 0 or more"),
        ('{"cycle": 0, "module": 0, "name": "m0", "actuators": {"DOF1": 0, "DOF2": 0},'
         ' "received": [{"hormone": "X(A)", "at": "front", "from": "back", "path": [["back"]]}]}\n',
         "bad.jsonl:1: field received[0].path[0]: expected [sent through, received at]"),
        ("[1, 2]\n", "bad.jsonl:1: not a trace record (a JSON object per line), but a list"),
        ("\n", "bad.jsonl: no trace records in it"),
    ],
)  # fmt: skip
def test_a_file_that_is_not_a_trace_is_named_with_line_and_field(
    text: str, message: str, runs: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.jsonl"
    bad.write_text(text)
    assert main([str(runs[0]), str(bad)]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err, err


def test_runs_that_cannot_be_compared(
    runs: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    robot, loop = runs

    def rename(records: list[Record]) -> None:
        for r in records:
            r["name"] = f"x{r['module']}"

    renamed = planted(loop, tmp_path / "renamed.jsonl", rename)
    assert main([str(robot), str(renamed)]) == 2
    assert "not runs of the same robot: module 0 is m0 in one, x0 in the other" in capsys.readouterr().err
    twice = write(tmp_path / "twice.jsonl", read(robot) + read(robot))
    assert main([str(robot), str(twice)]) == 2
    assert "module 0's cycle 0 again (line 1); two runs in one file?" in capsys.readouterr().err
    capture = robot_capture(tmp_path / "a.pcap", 1, clock=0.0)
    assert main([str(robot), str(capture), "--program", CATERPILLAR]) == 2
    assert "a trace and a capture" in capsys.readouterr().err
    assert main([str(robot), str(tmp_path / "none.jsonl")]) == 2
    assert "none.jsonl: cannot read it" in capsys.readouterr().err
