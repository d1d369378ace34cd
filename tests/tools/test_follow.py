"""`dh2rt follow`: a hormone flooded down a snake by the real engine, put on CAN frames as the
transport would, followed hop by hop by its growing path."""

from __future__ import annotations

from pathlib import Path

import pytest

from dh2rt.compiler import compile_source
from dh2rt.hormone import Hormone
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from dh2rt.wire.can_frames import SINGLE, make_arbitration_id, segment
from dh2rt.wire.frame import FrameCodec
from hil.pace import PACE
from tools.follow import main
from tools.pcap import CapturedFrame, write_pcap

SOURCE = "program flood\nconst ClockCycle = 4\nhormone Y\nhormone Z(n: int)\n"


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


def flood_capture(tmp_path: Path) -> tuple[Path, Path]:
    program_path = tmp_path / "flood.dh2"
    program_path.write_text(SOURCE)
    program = compile_source(SOURCE)
    topo = parse_spec("snake:4")
    robot = Robot(program, topo, seed=0, record=True)
    robot.inject(0, Hormone("Y"))
    codec = FrameCodec(program.vocabulary, program.profile.connector_count)
    links = {}
    for i, link in enumerate(topo.links):
        links[(link.a, link.a_conn)] = (i, 0)
        links[(link.b, link.b_conn)] = (i, 1)
    frames = []
    for cycle in robot.iter_cycles(8):
        for rec in robot.records:
            for through, h in rec.sent:
                link_id, side = links[(rec.module, through)]
                for f in segment(codec.encode(through, h), link_id, side):
                    frames.append(CapturedFrame(cycle * 0.02 + rec.module * 0.001, f.arbitration_id, f.data))
        robot.records.clear()
    frames.append(CapturedFrame(9.0, make_arbitration_id(0, SINGLE, 0, 0, 0), codec.encode(2, Hormone("Z", (3,)))))
    capture = tmp_path / "flood.pcap"
    write_pcap(capture, frames)
    return capture, program_path


def test_follow_a_flooded_hormone_to_the_end_of_the_snake(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capture, program = flood_capture(tmp_path)
    assert main([str(capture), "Y", "--program", str(program)]) == 0
    out = capsys.readouterr().out.splitlines()
    hops = [line.strip() for line in out if line.strip().startswith("hop ")]
    # m0 -> m1 -> m2 -> m3 over links 0, 1, 2, one cycle (20 ms) a hop, each sent through back
    assert [h.split()[:2] for h in hops] == [["hop", "0:"], ["hop", "1:"], ["hop", "2:"]]
    assert [h.split()[4] for h in hops] == ["0", "1", "2"]  # the link ids
    assert all("sent via back" in h for h in hops)
    assert "+21.0 ms" in hops[1] and "+21.0 ms" in hops[2]
    assert out[-1].strip() == "ended: at the module it reached (bound there, or no link to go on)"


def test_follow_reports_what_is_missing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capture, program = flood_capture(tmp_path)
    assert main([str(capture), "Y", "--program", str(program), "--at", "5"]) == 1
    assert "no Y sent at or after 5.0 s" in capsys.readouterr().err
    assert main([str(capture), "Z(3)", "--program", str(program), "--json"]) == 0
    assert '"next": []' in capsys.readouterr().out
    assert main([str(tmp_path / "none.pcap"), "Y", "--program", str(program)]) == 2


def test_follow_a_caterpillar_hormone_down_the_snake_as_table_i_implies(tmp_path: Path) -> None:
    """A loop run captured: the head's X(A) reaches the next module, which answers X(B) through
    its back in the next cycle, and so on to the tail: Table I's wave, A B C D A B C, told from
    the traffic alone (which link ends are one module: tools.topology_rebuild)."""
    import json
    import subprocess
    import sys

    from dh2rt.profile import CONRO
    from tools.reading import open_capture
    from tools.topology_rebuild import Traffic, rebuild

    root = Path(__file__).resolve().parents[2]
    capture = tmp_path / "snake.pcapng"
    cmd = [sys.executable, "-m", "hil.launcher", "--transport", "virtual", "--module-count", "8", "--cycles", "150",
           "--cycle-ms", "30", "--stand-in", "none", "--capture", str(capture), "--json"]  # fmt: skip
    assert PACE.run(cmd, timeout=120, cwd=root).returncode == 0
    rebuilt = rebuild(Traffic(CONRO).extend(open_capture(capture).hops()))
    head = next(s for s in rebuilt.snapshots[-1].modules if s.type_name == "head")
    (head_end,) = [e for m in rebuilt.modules if m.label == head.label for e in m.ends]
    out = tmp_path / "journey.json"
    args = [str(capture), "X(A)", "--link", str(head_end[1]), "--at", "0", "--json"]
    proc = subprocess.run([sys.executable, "-m", "dh2rt", "follow", *args], capture_output=True, text=True, cwd=root)
    assert proc.returncode == 0, proc.stderr
    out.write_text(proc.stdout)
    step = json.loads(proc.stdout)
    texts, modules = [], []
    while True:
        texts.append(step["text"])
        assert step["sender"] == "back"  # each passes the wave on through its back
        if "answer" not in step:
            break
        modules.append(step["module"])
        assert 0 < step["answer"]["latency"] < 0.06  # answered within two cycles of 30 ms
        step = step["answer"]
    assert texts == ["X(A)", "X(B)", "X(C)", "X(D)", "X(A)", "X(B)", "X(C)"]
    assert len(set(modules)) == 6  # six modules in between, each once; the seventh hop ends at the tail
