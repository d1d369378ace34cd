"""``dh2rt replay``: a loop run's capture (the caterpillar on serial links, cut in the middle)
rebuilds every module's trace records exactly; planted breakpoints of each kind stop at the
cycle the run's own trace says; a frame removed from the capture is said, with where, and
replay carries on; bad input exits 2 naming it.

Where each breakpoint should stop is read from the run's own trace (what the robot did),
never from replay."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from hil import launcher
from hil.pace import PACE
from tools import dump
from tools.capture_cycles import CycleMark, LinkMark, read_marks
from tools.capture_reader import read_records
from tools.pcapng import LINKTYPE_CAN_SOCKETCAN, LINKTYPE_USER0, LINKTYPE_USER1, Packet, PcapngReader, PcapngWriter

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


def key(rec: Record) -> tuple[int, int, int]:
    return rec["module"], rec.get("life", 0), rec["cycle"]


def rewrite(source: Path, target: Path, keep: Callable[[int, Packet], bool]) -> Path:
    """``source`` again with only the packets ``keep(i, packet)`` keeps (``i`` counts serial
    frames from 0, -1 for other packets)."""
    interface = {LINKTYPE_CAN_SOCKETCAN: 0, LINKTYPE_USER0: 1, LINKTYPE_USER1: 2}
    with source.open("rb") as fh:
        reader = PcapngReader(fh, source)
        reader.read_header()
        writer = PcapngWriter(target, reader.comments)
        serial = -1
        for packet in reader:
            serial += packet.linktype == LINKTYPE_USER0
            if keep(serial if packet.linktype == LINKTYPE_USER0 else -1, packet):
                writer.write(interface[packet.linktype], packet.timestamp, packet.data)
        writer.close()
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
    # frame readers skip the marks: dump reads every frame, and only frames
    frames = list(read_records(capture))
    assert dump.main([str(capture)]) == 0
    assert len(capsys.readouterr().out.splitlines()) == len(frames)
