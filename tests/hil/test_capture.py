"""`dh2rt --capture`: a loop run over serial links, a python-can `virtual` bus and
`udp_multicast` (in the launcher's private network namespace) captured to pcapng, then read
back with the capture tools and nothing else (the program comes from inside the capture).

Every hormone the modules' own trace says they sent through a docked connector is in the
capture on the right link end, every module announced its program on each link, every link
end's keep-alives are all there (consecutive numbers), and the capture's frames add up to
the frames the modules counted as sent."""

from __future__ import annotations

import itertools
import json
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import pytest

from dh2rt.bundled import compile_bundled
from dh2rt.topology import parse_spec
from dh2rt.transport.can_bus import socketcan_problem
from dh2rt.wire.frame import program_digest
from hil.netns import namespace_problem
from hil.pace import PACE
from tools.capture_reader import capture_programs
from tools.reading import open_capture

ROOT = Path(__file__).resolve().parents[2]
MODULES = 4
CYCLES = 120


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


def launch(transport: str, tmp_path: Path, *extra: str) -> tuple[int, dict[str, Any], str, Path, Path]:
    capture, trace = tmp_path / f"{transport}.pcapng", tmp_path / f"{transport}.jsonl"
    cmd = [
        sys.executable, "-m", "hil.launcher", "--transport", transport, "--module-count", str(MODULES),
        "--cycles", str(CYCLES), "--cycle-ms", "30", "--stand-in", "none", "--silence-cycles", "6",
        "--capture", str(capture), "--trace", str(trace), "--json", "--log", str(tmp_path / "run.log"), *extra,
    ]  # fmt: skip
    proc = PACE.run(cmd, text=True, timeout=120, cwd=ROOT)
    summary = json.loads(proc.stdout) if proc.stdout.strip() else {}
    return proc.returncode, summary, proc.stderr, capture, trace


NEGOTIATED = re.compile(r"^m(\d+): link negotiated: connector (\d+) is link (\d+) side ([01])$")


def link_ends(summary: dict[str, Any]) -> dict[tuple[int, str], tuple[int, int]]:
    """(module, connector name) -> (link id, side). On serial links the world numbers its
    emulator's links in topology order; on a bus the modules negotiated their link ids, and
    each said which in its log."""
    topo = parse_spec(f"snake:{MODULES}")
    name = topo.profile.connector_name
    ends = {}
    negotiated = [m.groups() for line in summary["log"] if (m := NEGOTIATED.match(line))]
    if negotiated:
        for module, connector, link, side in negotiated:
            ends[(int(module), name(int(connector)))] = (int(link), int(side))
        assert len(ends) == 2 * len(topo.links), negotiated
        return ends
    for i, lk in enumerate(topo.links):
        ends[(lk.a, name(lk.a_conn))] = (i, 0)
        ends[(lk.b, name(lk.b_conn))] = (i, 1)
    return ends


@pytest.mark.parametrize("transport", ["serial", "virtual", "udp", "vcan0"])
def test_capture_of_a_loop_run_holds_every_frame(transport: str, tmp_path: Path) -> None:
    if transport == "udp" and (why := namespace_problem()):
        pytest.skip(why)
    if transport == "vcan0" and (why := socketcan_problem("vcan0")):
        pytest.skip(f"SocketCAN vcan0: {why} (the same capture runs on virtual and udp above)")
    code, summary, err, capture_path, trace_path = launch(transport, tmp_path)
    assert code == 0, (summary.get("problems"), err[-2000:])
    assert "capture:" in err  # with --json, the capture's line goes to stderr

    program = compile_bundled("caterpillar.dh2")
    assert capture_programs(capture_path) == [program.image]  # the capture carries its program
    capture = open_capture(capture_path)  # no --program: read from the capture
    hops = list(capture.hops())
    assert not [h for h in hops if h.kind == "error"]

    ends = link_ends(summary)
    sent_in_trace: Counter[tuple[int, int, str]] = Counter()
    for line in trace_path.read_text().splitlines():
        rec = json.loads(line)
        for emission in rec["sent"]:
            end = ends.get((rec["module"], emission["through"]))
            if end is not None:  # a head's emission through its free front goes nowhere
                sent_in_trace[(*end, emission["hormone"])] += 1
    on_wire = Counter((h.link, h.side, h.text) for h in hops if h.kind == "hormone")
    assert sum(sent_in_trace.values()) > 20
    assert on_wire == sent_in_trace

    digest = program_digest(program.image).hex()
    for end in set(ends.values()):
        hellos = [h for h in hops if (h.link, h.side) == end and h.kind == "hello"]
        assert hellos and all(h.text == digest for h in hellos), end
        seqs = [int(h.text[1:]) for h in hops if (h.link, h.side) == end and h.kind == "keepalive"]
        assert len(seqs) > CYCLES // 2, end
        assert all((b - a) & 0xFF == 1 for a, b in itertools.pairwise(seqs)), end  # none missing

    frames = summary["frames"]
    # one capture record per frame sent (and, on a bus, the links' negotiation: its claims
    # and re-announcements on the management id, which no module counts as a link frame)
    negotiation = [h for h in hops if h.kind == "link"]
    assert (len(negotiation) > 0) == (transport != "serial")
    claimed = {h.link for h in negotiation if h.text.startswith("CLAIM")}
    if transport != "serial":
        assert {end[0] for end in ends.values()} <= claimed  # each link was claimed before use
    assert len(hops) - len(negotiation) == frames["sent"], (len(hops), frames)
    assert all(h.medium == ("serial" if transport == "serial" else "can") for h in hops)


def test_capture_over_lossy_serial_links_marks_the_lost_frames(tmp_path: Path) -> None:
    code, summary, err, capture_path, _trace = launch("serial", tmp_path, "--frame-loss", "0.05", "--seed", "3")
    assert code in (0, 1), err[-2000:]  # losses may cost a link; the capture is what matters here
    hops = list(open_capture(capture_path).hops())
    lost = [h for h in hops if h.lost]
    assert len(lost) == summary["frames"]["lost_on_link"] > 0
    assert all(h.kind != "error" for h in lost)  # a lost frame still decodes from the bytes sent


def test_capture_refuses_what_it_cannot_write(tmp_path: Path) -> None:
    def run(*args: str) -> subprocess.CompletedProcess[str]:
        cmd = [sys.executable, "-m", "hil.launcher", "--cycles", "5", "--stand-in", "none", *args]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=ROOT)

    proc = run("--transport", "serial", "--capture", str(tmp_path / "x.log"))
    assert proc.returncode == 2 and ".pcapng" in proc.stderr, proc.stderr
    proc = run("--transport", "inproc", "--capture", str(tmp_path / "x.pcapng"))
    assert proc.returncode == 2 and "no frames on a wire" in proc.stderr, proc.stderr
    proc = run("--transport", "virtual", "--capture", str(tmp_path / "x.txt"))
    assert proc.returncode == 2 and "--capture" in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
