"""`dh2rt topo`: a robot's topology rebuilt from its traffic alone.

Made-up traffic (each module one burst of frames a cycle, at a phase of its own; links cut;
hormones forwarded or answered) written as a CAN capture shows each kind of evidence, the
liveness bound, rings, settling and the trace comparison on its own. Real runs of the
launcher (`snake:8` cut in two, the dragon) are rebuilt and checked against the link ids
the modules negotiated."""

from __future__ import annotations

import json
import re
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from dh2rt.compiler import compile_file
from dh2rt.hormone import Hormone
from dh2rt.profile import CONRO
from dh2rt.wire.can_frames import segment
from dh2rt.wire.frame import Frame, FrameCodec, Hello, KeepAlive, program_digest
from hil.pace import PACE
from tools.pcap import CapturedFrame, write_pcap
from tools.reading import open_capture
from tools.topo import main
from tools.topology_rebuild import Rebuilt, Traffic, rebuild

ROOT = Path(__file__).resolve().parents[2]
CATERPILLAR = ROOT / "examples" / "caterpillar.dh2"
LOCOMOTION = ROOT / "examples" / "locomotion.dh2"
FRONT, BACK = CONRO.connector_index("front"), CONRO.connector_index("back")
PERIOD = 0.02
T0 = 1000.0  # the made-up capture's clock
PHASES = (0.0, 0.006, 0.012, 0.018)  # where in the cycle each module sends: apart from each other


# ----------------------------------------------------------------------------- made-up robots


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


@dataclass
class MadeUp:
    """A made-up robot: modules (their link ends as (connector, link, side)), each sending
    one frame per linked end per cycle, back to back (``spacing`` apart) at its phase."""

    ends: list[list[tuple[int, int, int]]]
    cycles: int = 100
    spacing: float = 0.0001
    down: dict[int, range] = field(default_factory=dict)  # link -> cycles it is cut
    hormones: dict[tuple[int, int, int], Hormone] = field(default_factory=dict)  # (cycle, module, connector)

    def up(self, link: int, cycle: int) -> bool:
        return cycle not in self.down.get(link, range(0))

    def frames(self) -> list[tuple[float, int, int, int, Frame]]:
        """(time, link, side, connector, frame), in time order: a Hello first on each link
        (and again after a break), then a hormone where one is due, else a KeepAlive."""
        out: list[tuple[float, int, int, int, Frame]] = []
        digest = program_digest(compile_file(str(CATERPILLAR)).image)
        seq: Counter[tuple[int, int]] = Counter()
        for cycle in range(self.cycles):
            for m, ends in enumerate(self.ends):
                live = [e for e in ends if self.up(e[1], cycle)]
                for k, (conn, link, side) in enumerate(live):
                    at = T0 + cycle * PERIOD + PHASES[m % len(PHASES)] + (m // len(PHASES)) * 0.003 + k * self.spacing
                    frame: Frame
                    if cycle == 0 or not self.up(link, cycle - 1):
                        frame = Hello(digest)
                    elif (cycle, m, conn) in self.hormones:
                        frame = self.hormones[(cycle, m, conn)]
                    else:
                        seq[(link, side)] += 1
                        frame = KeepAlive(seq[(link, side)] & 0xFF)
                    out.append((at, link, side, conn, frame))
        return sorted(out, key=lambda f: f[0])

    def write(self, path: Path) -> Path:
        program = compile_file(str(CATERPILLAR))
        codec = FrameCodec(program.vocabulary, program.profile.connector_count)
        captured = [
            CapturedFrame(at, f.arbitration_id, f.data)
            for at, link, side, conn, frame in self.frames()
            for f in segment(codec.encode(conn, frame), link, side)
        ]
        write_pcap(path, captured)
        return path

    def rebuilt(self, tmp_path: Path, **options: Any) -> Rebuilt:
        capture = open_capture(self.write(tmp_path / "made.pcap"), CATERPILLAR)
        return rebuild(Traffic(CONRO).extend(capture.hops()), **options)


def snake(n: int, **kw: Any) -> MadeUp:
    """Module i's back on link i (side 0), its front on link i-1 (side 1)."""
    ends = [[(FRONT, i - 1, 1)] * (i > 0) + [(BACK, i, 0)] * (i < n - 1) for i in range(n)]
    return MadeUp(ends, **kw)


def ring(n: int, **kw: Any) -> MadeUp:
    return MadeUp([[(FRONT, (i - 1) % n, 1), (BACK, i, 0)] for i in range(n)], **kw)


def types(rebuilt: Rebuilt, snapshot: int) -> list[list[str | None]]:
    """Per piece of a snapshot, its modules' types in label order."""
    s = rebuilt.snapshots[snapshot]
    by_label = {m.label: m.type_name for m in s.modules}
    return [[by_label[label] for label in piece] for piece in s.pieces]


# ----------------------------------------------------------------------------- the rebuild


def test_a_snake_cut_in_two_by_the_timing_of_its_frames(tmp_path: Path) -> None:
    made = snake(4, down={1: range(50, 100)})
    rebuilt = made.rebuilt(tmp_path)
    assert rebuilt.period == pytest.approx(PERIOD, rel=1e-3)
    assert [len(m.ends) for m in rebuilt.modules] == [1, 2, 2, 1]
    assert [m.grouped_by for m in rebuilt.modules] == ["alone", "timing", "timing", "alone"]
    assert len(rebuilt.snapshots) == 2
    assert types(rebuilt, 0) == [["head", "body", "body", "tail"]]
    assert types(rebuilt, 1) == [["head", "tail"], ["head", "tail"]]
    cut = rebuilt.snapshots[1]
    assert cut.changes == ("M1.back-M2.front down",)
    # down from the last frame of the end that went silent first: module 1's back (its second frame a cycle)
    assert cut.time == pytest.approx(T0 + 49 * PERIOD + PHASES[1] + 0.0001, abs=1e-6)


def test_without_evidence_each_end_is_a_module_of_its_own(tmp_path: Path) -> None:
    # a module's two ends 3 ms apart: not one burst
    rebuilt = snake(4, spacing=0.003).rebuilt(tmp_path)
    assert [m.grouped_by for m in rebuilt.modules] == ["alone"] * 6
    assert len(rebuilt.snapshots[0].pieces) == 3


def flood(n: int, every: int = 10, cycles: int = 100) -> dict[tuple[int, int, int], Hormone]:
    """X(A) sent down a snake from module 0 and carried on, its path growing: each module
    sends later in the cycle than the one before, so it carries it on in the same cycle."""
    out = {}
    for start in range(1, cycles, every):
        for i in range(n - 1):
            out[(start, i, BACK)] = Hormone("X", ("A",), ((BACK, FRONT),) * i)
    return out


def test_hormones_carried_on_tie_link_ends(tmp_path: Path) -> None:
    rebuilt = snake(4, spacing=0.003, hormones=flood(4)).rebuilt(tmp_path)
    assert [m.grouped_by for m in rebuilt.modules] == ["alone", "forwarded", "forwarded", "alone"]
    assert types(rebuilt, 0) == [["head", "body", "body", "tail"]]


def test_hormones_answered_in_the_next_cycle_tie_link_ends(tmp_path: Path) -> None:
    phases = "ABCD"
    answered = {
        (start, i, BACK): Hormone("X", (phases[i],)) for start in range(1, 90, 10) for i in range(3)
    }  # module i answers what arrived at its front before its cycle began, fresh (no path)
    rebuilt = snake(4, spacing=0.003, hormones=answered).rebuilt(tmp_path)
    assert [m.grouped_by for m in rebuilt.modules] == ["alone", "relayed", "relayed", "alone"]


def test_a_ring_is_closed_by_hormone_paths_only(tmp_path: Path) -> None:
    by_timing = ring(4).rebuilt(tmp_path)
    assert len(by_timing.modules) == 5  # the merge that would close the ring is refused
    around = {
        (start + i, i % 4, BACK): Hormone("X", ("A",), ((BACK, FRONT),) * i) for start in (1, 30, 60) for i in range(6)
    }
    by_paths = ring(4, hormones=around).rebuilt(tmp_path)
    assert len(by_paths.modules) == 4
    assert {m.type_name for m in by_paths.snapshots[0].modules} == {"body"}
    assert by_paths.snapshots[0].pieces == (("M0", "M1", "M2", "M3"),)


def test_a_link_is_gone_only_after_the_liveness_bound(tmp_path: Path) -> None:
    short = snake(2, down={0: range(40, 42)}).rebuilt(tmp_path)  # 2 silent cycles: within 3.5
    assert len(short.snapshots) == 1
    long = snake(2, down={0: range(40, 46)}).rebuilt(tmp_path)
    assert [s.changes for s in long.snapshots[1:]] == [("M0.back-M1.front down",), ("M0.back-M1.front up",)]
    assert long.snapshots[1].silent == ("M0", "M1")
    assert snake(2, down={0: range(40, 42)}).rebuilt(tmp_path, silence_cycles=1).snapshots[1:] != ()


def test_changes_closer_than_the_settle_time_are_one(tmp_path: Path) -> None:
    made = snake(4, down={0: range(50, 100), 2: range(51, 100)})
    together = made.rebuilt(tmp_path)
    assert len(together.snapshots) == 2 and len(together.snapshots[1].changes) == 2
    apart = made.rebuilt(tmp_path, settle=0.015)  # the links came up 6 ms apart, went down 20 ms apart
    assert [len(s.changes) for s in apart.snapshots] == [3, 1, 1]


def test_a_status_the_profile_forbids_has_no_type(tmp_path: Path) -> None:
    made = MadeUp([[(FRONT, 0, 0)], [(FRONT, 0, 1)]])  # two female connectors docked
    rebuilt = made.rebuilt(tmp_path)
    assert [m.type_name for m in rebuilt.snapshots[0].modules] == [None, None]
    capture = made.write(tmp_path / "ff.pcap")
    assert main([str(capture), "--program", str(CATERPILLAR)]) == 0


def test_no_link_traffic_is_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ValueError, match="no link traffic"):
        rebuild(Traffic(CONRO))
    empty = tmp_path / "empty.pcap"
    write_pcap(empty, [])
    assert main([str(empty), "--program", str(CATERPILLAR)]) == 2
    assert "no link traffic" in capsys.readouterr().err


# ----------------------------------------------------------------------------- the command


def test_the_command_prints_draws_and_writes_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    capture = snake(4, down={1: range(50, 100)}).write(tmp_path / "snake.pcap")
    assert main([str(capture), "--program", str(CATERPILLAR)]) == 0
    out = capsys.readouterr().out
    assert "4 modules, 3 links; cycle 20.00 ms" in out
    assert "piece 1 (4): M0=head (T1) M1=body (T16) M2=body (T16) M3=tail (T2)" in out
    assert "piece 2 (2): M2=head (T1) M3=tail (T2)" in out
    assert main([str(capture), "--program", str(CATERPILLAR), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [s["pieces"] for s in doc["snapshots"]] == [[["M0", "M1", "M2", "M3"]], [["M0", "M1"], ["M2", "M3"]]]
    assert doc["modules"][1]["ends"] == [
        {"medium": "can", "link": 0, "side": 1, "connector": "front"},
        {"medium": "can", "link": 1, "side": 0, "connector": "back"},
    ]
    pytest.importorskip("matplotlib")
    monkeypatch.chdir(tmp_path)  # a missing folder is made inside the current one (docs/capture.md, output files)
    pictures = tmp_path / "pictures"
    assert main([str(capture), "--program", str(CATERPILLAR), "--png-dir", "pictures"]) == 0
    written = sorted(pictures.iterdir())
    assert [p.name for p in written] == ["topo-000.png", "topo-001.png"]
    assert all(p.read_bytes().startswith(b"\x89PNG") for p in written)


def test_bad_input_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capture = snake(2).write(tmp_path / "two.pcap")
    program = ["--program", str(CATERPILLAR)]
    assert main([str(tmp_path / "none.pcap"), *program]) == 2
    assert main([str(capture), *program, "--cycle-ms", "0"]) == 2
    assert "--cycle-ms 0.0: must be a positive number" in capsys.readouterr().err
    assert main([str(capture), *program, "--trace", str(tmp_path / "none.jsonl")]) == 2
    assert "none.jsonl: cannot read it" in capsys.readouterr().err
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"cycle": 0}\n')
    assert main([str(capture), *program, "--trace", str(bad)]) == 2
    assert f"{bad}:1:" in capsys.readouterr().err
    assert main([str(capture), *program, "--no-such-option"]) == 2


# ----------------------------------------------------------------------------- against a trace

OFFSET = 500.0  # the trace's clock runs this far behind the capture's


def made_up_trace(made: MadeUp, path: Path, lag: int = 2, wrong: int | None = None) -> Path:
    """What a snake's modules would write: each cycle's start on a clock of their own, their
    hormones, and their status as the links say, ``lag`` cycles late (module ``wrong`` never
    notices a cut)."""
    name = CONRO.connector_name
    lines = []
    for cycle in range(made.cycles):
        for m, ends in enumerate(made.ends):
            seen = 0 if m == wrong else max(0, cycle - lag)  # the cycle whose links it believes
            status = {c: "0" for c in CONRO.connectors}
            for conn, link, _ in ends:
                if made.up(link, seen):
                    status[name(conn)] = name(BACK if conn == FRONT else FRONT)
            t = CONRO.type_of([CONRO.connector_index(status[c]) if status[c] != "0" else 0 for c in CONRO.connectors])
            sent = [
                {"hormone": h.content(), "through": name(conn)}
                for (c, mod, conn), h in made.hormones.items()
                if c == cycle and mod == m
            ]
            lines.append(
                json.dumps(
                    {
                        "cycle": cycle,
                        "module": m,
                        "name": f"m{m}",
                        "type": t.name,
                        "T": t.alias,
                        "timer": 0,
                        "actuators": {"DOF1": 0, "DOF2": 0},
                        "status": status,
                        "received": [],
                        "sent": sent,
                        "t": T0 - OFFSET + cycle * PERIOD + PHASES[m] - 0.0005,
                    }
                )
            )
    path.write_text("\n".join(lines) + "\n")
    return path


def test_a_trace_that_agrees_with_the_traffic(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    made = snake(4, down={1: range(50, 100)}, hormones=flood(4))
    capture = made.write(tmp_path / "snake.pcap")
    trace = made_up_trace(made, tmp_path / "trace.jsonl")
    assert main([str(capture), "--program", str(CATERPILLAR), "--trace", str(trace)]) == 0
    out = capsys.readouterr().out
    assert "4 of 4 modules matched to the traffic" in out
    assert "clocks aligned by the hormones the trace sent, capture = trace +500.000" in out
    assert "matched: m0=M0 m1=M1 m2=M2 m3=M3" in out
    assert "every matched module's own type agrees with the traffic" in out


def test_a_module_that_misses_a_cut_is_flagged(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    made = snake(4, down={1: range(50, 100)}, hormones=flood(4))
    capture = made.write(tmp_path / "snake.pcap")
    late = made_up_trace(made, tmp_path / "late.jsonl", lag=8)  # later than the liveness bound
    assert main([str(capture), "--program", str(CATERPILLAR), "--trace", str(late)]) == 1
    out = capsys.readouterr().out
    # both modules beside the cut took 8 cycles to see it: from the liveness bound and two
    # cycles after its last frame (cycle 49) to their 8th cycle after it
    assert "!! M1 (m1, life 0) cycles 55-57, +1.100 to +1.140 s: says body (T16), the traffic shows tail (T2)" in out
    assert "!! M2 (m2, life 0) cycles 55-57, +1.106 to +1.146 s: says body (T16), the traffic shows head (T1)" in out
    wrong = made_up_trace(made, tmp_path / "wrong.jsonl", wrong=1)
    assert main([str(capture), "--program", str(CATERPILLAR), "--trace", str(wrong), "--json"]) == 1
    found = json.loads(capsys.readouterr().out)["trace"]["disagreements"]
    assert [(d["name"], d["says"], d["shows"]) for d in found] == [("m1", "body", "tail")]
    assert found[0]["first_cycle"] == 55 and found[0]["last_cycle"] == 99


# ----------------------------------------------------------------------------- real runs

NEGOTIATED = re.compile(r"^(\w+): link negotiated: connector (\d+) is link (\d+) side ([01])$")


@dataclass(frozen=True)
class Run:
    capture: Path
    trace: Path
    truth: dict[tuple[str, int, int], str]  # link end -> the module's name in the run


def launch(tmp: Path, name: str, *args: str) -> Run:
    """A loop run over python-can's virtual bus, its capture and trace, and which module
    each link end is (the modules say, in the log, which link ids they negotiated)."""
    capture, trace = tmp / f"{name}.pcapng", tmp / f"{name}.jsonl"
    cmd = [
        sys.executable, "-m", "hil.launcher", "--transport", "virtual", "--stand-in", "none", "--cycle-ms", "30",
        "--capture", str(capture), "--trace", str(trace), "--json", "--log", str(tmp / f"{name}.log"), *args,
    ]  # fmt: skip
    proc = PACE.run(cmd, text=True, timeout=180, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    truth = {}
    for line in summary["log"]:
        if m := NEGOTIATED.match(line):
            truth[("can", int(m[3]), int(m[4]))] = m[1]
    return Run(capture, trace, truth)


@pytest.fixture(scope="module")
def cut_snake(tmp_path_factory: pytest.TempPathFactory) -> Run:
    return launch(
        tmp_path_factory.mktemp("snake"), "snake", "--module-count", "8", "--cycles", "160", "--event", "80:cut:m3.back"
    )


@pytest.fixture(scope="module")
def dragon(tmp_path_factory: pytest.TempPathFactory) -> Run:
    tmp = tmp_path_factory.mktemp("dragon")
    return launch(tmp, "dragon", "--topology", "dragon", "--program", str(LOCOMOTION), "--cycles", "120")


def rebuilt_json(run: Run, capsys: pytest.CaptureFixture[str], *extra: str) -> dict[str, Any]:
    assert main([str(run.capture), "--json", *extra]) in (0, 1)
    doc: dict[str, Any] = json.loads(capsys.readouterr().out)
    return doc


def same_modules(doc: dict[str, Any], run: Run) -> dict[str, str]:
    """Each rebuilt module is one module of the run, every module of the run is one rebuilt
    module: label -> name."""
    names = {}
    for m in doc["modules"]:
        owners = {run.truth[("can", e["link"], e["side"])] for e in m["ends"]}
        assert len(owners) == 1, (m, owners)
        names[m["label"]] = owners.pop()
    assert sorted(names.values()) == sorted(set(run.truth.values()))
    return names


def piece_types(snapshot: dict[str, Any], names: dict[str, str]) -> list[list[tuple[str, str]]]:
    types = {m["label"]: m["type"] for m in snapshot["modules"]}
    return [sorted((names[label], types[label]) for label in piece) for piece in snapshot["pieces"]]


@pytest.mark.slow
def test_topo_rebuilds_snake8_and_after_a_cut_two_pieces(cut_snake: Run, capsys: pytest.CaptureFixture[str]) -> None:
    doc = rebuilt_json(cut_snake, capsys)
    names = same_modules(doc, cut_snake)
    whole, halves = doc["snapshots"][0], doc["snapshots"][-1]
    body = [(f"m{i}", "body") for i in range(1, 7)]
    assert piece_types(whole, names) == [[("m0", "head"), *body, ("m7", "tail")]]
    assert len(doc["snapshots"]) == 2
    assert len(halves["changes"]) == 1 and halves["changes"][0].endswith(" down")  # the cut, nothing else
    assert sorted(piece_types(halves, names)) == [
        [("m0", "head"), ("m1", "body"), ("m2", "body"), ("m3", "tail")],
        [("m4", "head"), ("m5", "body"), ("m6", "body"), ("m7", "tail")],
    ]
    cut = halves["changes"][0].removesuffix(" down").split("-")
    assert sorted((names[end.split(".")[0]], end.split(".")[1]) for end in cut) == [("m3", "back"), ("m4", "front")]


@pytest.mark.slow
def test_the_modules_own_types_agree_and_a_doctored_one_is_flagged(
    cut_snake: Run, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = rebuilt_json(cut_snake, capsys, "--trace", str(cut_snake.trace))
    assert doc["trace"]["aligned_by"] == "hormones"
    assert doc["trace"]["disagreements"] == []
    names = same_modules(doc, cut_snake)
    assert {names[m["labels"][0]]: doc["trace"]["modules"][str(m["module"])] for m in doc["trace"]["matched"]} == {
        f"m{i}": f"m{i}" for i in range(8)
    }
    # the surgery bug: m3 never notices its back was cut and keeps calling itself a body
    doctored = tmp_path / "doctored.jsonl"
    with doctored.open("w") as out:
        for line in cut_snake.trace.read_text().splitlines():
            rec = json.loads(line)
            if rec["name"] == "m3" and rec["cycle"] >= 80:
                rec.update(type="body", T=16, status={**rec["status"], "back": "front"})
            out.write(json.dumps(rec) + "\n")
    doc = rebuilt_json(cut_snake, capsys, "--trace", str(doctored))
    found = doc["trace"]["disagreements"]
    assert [(d["name"], d["says"], d["shows"]) for d in found] == [("m3", "body", "tail")]
    assert 80 < found[0]["first_cycle"] <= 80 + 8 and found[0]["last_cycle"] >= 150


@pytest.mark.slow
def test_topo_rebuilds_the_dragon(dragon: Run, capsys: pytest.CaptureFixture[str]) -> None:
    doc = rebuilt_json(dragon, capsys, "--trace", str(dragon.trace))
    names = same_modules(doc, dragon)
    assert len(doc["snapshots"]) == 1
    (piece,) = piece_types(doc["snapshots"][0], names)
    assert piece == sorted(
        [
            ("spine0", "spine_front"), ("spine1", "spine"),
            ("left_leg0", "left_foot"), ("right_leg0", "right_foot"),
            ("left_leg1", "left_foot"), ("right_leg1", "right_foot"),
            ("tail0", "body"), ("tail1", "body"), ("tail2", "body"), ("tail3", "body"), ("tail4", "tail"),
        ]
    )  # fmt: skip
    assert doc["trace"]["disagreements"] == []
