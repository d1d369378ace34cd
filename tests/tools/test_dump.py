"""`dh2rt dump`: a real capture of two module runtimes on python-can's virtual bus, taken by
python-can's own Logger in several formats (and as pcap), shown in DH2 terms; long hormones
reassembled; bad capture files end with an error naming the file and the offset."""

from __future__ import annotations

import json
import struct
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import can
import pytest

from dh2rt.hormone import Hormone
from dh2rt.program import CompiledProgram
from dh2rt.runtime import ModuleRuntime
from dh2rt.testing import FakeClock, contract_codec, long_hormone
from dh2rt.transport.base import BusEnd
from dh2rt.transport.registry import open_transport
from dh2rt.wire.can_frames import SINGLE, make_arbitration_id
from dh2rt.wire.frame import FrameCodec
from tools.capture_reader import read_can
from tools.capture_sink import FileSink
from tools.dump import main
from tools.pcap import CapturedFrame, write_pcap
from tools.pcapng import CAN_INTERFACE, PcapngWriter

ROOT = Path(__file__).resolve().parents[2]
CATERPILLAR = str(ROOT / "examples" / "caterpillar.dh2")
FRONT, BACK = 1, 2


def run_pair(program: CompiledProgram, channel: str, on_message: Callable[[can.Message], None]) -> None:
    """A head and a tail on a virtual bus for 45 cycles; every frame a listener on the bus
    sees, in order, handed to ``on_message``."""
    tap = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    codec = FrameCodec(program.vocabulary, program.profile.connector_count)
    mods = [
        ModuleRuntime(program, open_transport(f"virtual:{channel}", codec), clock=FakeClock(0.001), module=i)
        for i in range(2)
    ]
    try:
        mods[0].attach(BACK, BusEnd(5, 0))
        mods[1].attach(FRONT, BusEnd(5, 1))
        for _ in range(45):
            for m in mods:
                m.step()
            while (msg := tap.recv(0)) is not None:
                on_message(msg)
    finally:
        for m in mods:
            m.close()
        tap.shutdown()


def capture(program: CompiledProgram, tmp_path: Path, suffix: str) -> Path:
    """The pair's traffic logged by python-can's own Logger."""
    channel = f"dump-{suffix[1:]}-robot"  # no digits: BLF and ASC would make a channel number of them
    path = tmp_path / f"robot{suffix}"
    logger = can.Logger(str(path))
    try:
        run_pair(program, channel, logger.on_message_received)
    finally:
        logger.stop()
    return path


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_dump_shows_the_traffic_in_dh2_terms(
    suffix: str, caterpillar: CompiledProgram, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = capture(caterpillar, tmp_path, suffix)
    assert main([str(path), "--program", CATERPILLAR]) == 0
    lines = capsys.readouterr().out.splitlines()
    kinds = [line.split()[5] for line in lines]
    assert "hello" in kinds and "keepalive" in kinds and "hormone" in kinds
    hormones = [line for line in lines if " hormone " in line]
    # the head (side 0 of link 5) sends the caterpillar's phases through its back
    assert all("link    5 side 0" in h and "via back" in h for h in hormones)
    assert {h.split()[6] for h in hormones} <= {"X(A)", "X(B)", "X(C)", "X(D)"}
    assert "!!" not in "\n".join(lines)
    assert main([str(path), "--program", CATERPILLAR, "--kind", "hormone", "--json"]) == 0
    objs = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [o["text"] for o in objs] == [h.split()[6] for h in hormones]


def test_long_hormones_are_reassembled_and_garbage_is_marked(
    caterpillar: CompiledProgram, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from dh2rt.testing import CONTRACT_VOCABULARY
    from dh2rt.wire.can_frames import segment

    del caterpillar
    codec = contract_codec()
    routed = long_hormone(12)
    segments = segment(codec.encode(3, routed), 9, 1)
    frames = [CapturedFrame(1.0 + i / 100, f.arbitration_id, f.data) for i, f in enumerate(segments)]
    frames.append(CapturedFrame(2.0, make_arbitration_id(0, SINGLE, 0, 9, 0), b"\xff\xff"))  # not a frame
    frames.append(CapturedFrame(2.1, 0x123, b"\x01", is_extended_id=False))  # not dh2rt's
    pcap = tmp_path / "long.pcap"
    write_pcap(pcap, frames)
    program = tmp_path / "contract.dh2"
    program.write_text(
        "program contract\nconst ClockCycle = 4\nhormone X(a: A | B)\nhormone N(n: int)\n"
        "hormone P(n: int, m: int, d: up | down)\n"
    )
    assert [s.name for s in CONTRACT_VOCABULARY.by_index] == ["X", "N", "P"]
    assert main([str(pcap), "--program", str(program)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert sum(" segment " in line for line in lines) == len(frames) - 3
    reassembled = [line for line in lines if " routed " in line]
    assert len(reassembled) == 1 and "P(-123456, 2147483647, down) (reassembled)" in reassembled[0]
    assert "route" in reassembled[0] and "path" in reassembled[0]
    assert sum("!!" in line for line in lines) == 2


def test_a_spliced_train_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 27: the last frame of one hormone and the first of the next lost, the rest of the
    two would make a hormone nobody sent. dump shows it refused, as a module's transport does."""
    from dh2rt.wire.can_frames import Segmenter, segment

    codec = contract_codec()
    a = codec.encode(2, Hormone("P", (100, 200, "up"), ((1, 2),)))
    b = codec.encode(2, Hormone("P", (-700, 800, "down"), ((3, 4),)))
    restarted = [segment(p, 9, 1) for p in (a, b)]  # a sender that restarted: both trains tag 0
    sender = Segmenter()
    trains = [sender.segment(p, 9, 1) for p in (a, b)]  # one sender: tags 0 and 1
    sent = [restarted[0][0], restarted[1][1], trains[0][0], trains[1][1], *trains[1]]
    pcap = tmp_path / "spliced.pcap"
    write_pcap(pcap, [CapturedFrame(1.0 + i / 100, f.arbitration_id, f.data) for i, f in enumerate(sent)])
    program = tmp_path / "contract.dh2"
    program.write_text(
        "program contract\nconst ClockCycle = 4\nhormone X(a: A | B)\nhormone N(n: int)\n"
        "hormone P(n: int, m: int, d: up | down)\n"
    )
    assert main([str(pcap), "--program", str(program)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "segment   #0" in lines[0] and "segment   #0" in lines[2] and "segment   #1" in lines[4]
    assert lines[1].endswith(
        "!! segment 1: train refused: its check fails (spliced from two hormones, or a piece lost)"
    )
    assert lines[3].endswith("!! segment 2 out of order: lost")  # the tag tells the trains apart
    assert "P(-700, 800, down) (reassembled)" in lines[5]
    assert len(lines) == 6 and sum("!!" in line for line in lines) == 2


def test_bad_captures_name_the_file_and_offset(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    good = tmp_path / "good.pcap"
    write_pcap(good, [CapturedFrame(1.0, 5, b"\x01\x02"), CapturedFrame(2.0, 6, b"\x03")])
    raw = good.read_bytes()
    cases = {
        "cut.pcap": (raw[:-1], "offset 50: record cut short"),
        "header.pcap": (raw[:30], "offset 24: record header cut short"),
        "garbage.pcap": (b"\x00" * 40, "offset 0: not a pcap file"),
        "ether.pcap": (raw[:20] + struct.pack("<I", 1) + raw[24:], "offset 20: link type 1"),
        "notes.txt": (b"hello", "unknown capture format .txt"),
        "garbage.blf": (b"\x01" * 100, "offset 0: not a BLF file"),
    }
    for name, (data, words) in cases.items():
        path = tmp_path / name
        path.write_bytes(data)
        assert main([str(path), "--program", CATERPILLAR]) == 2, name
        err = capsys.readouterr().err
        assert str(path) in err and words in err and "Traceback" not in err, (name, err)
    assert main([str(tmp_path / "missing.pcap"), "--program", CATERPILLAR]) == 2
    assert "no such capture file" in capsys.readouterr().err


def test_the_same_frames_from_pcapng_candump_asc_and_blf(
    caterpillar: CompiledProgram, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One bus, four files written at once (ours and python-can's writers): dump reads the
    same frames from each, and the pcapng and the sidecars carry the program."""
    sinks = [
        FileSink(tmp_path / f"robot{suffix}", [caterpillar.image]) for suffix in (".pcapng", ".log", ".asc", ".blf")
    ]

    def write_all(msg: can.Message) -> None:
        for sink in sinks:
            sink.write_message(msg)

    try:
        run_pair(caterpillar, "dump-all-formats", write_all)
    finally:
        for sink in sinks:
            sink.close()
    seen = {}
    for sink in sinks:
        assert main([str(sink.path), "--json"]) == 0, sink.path  # the program comes with the capture
        objs = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
        seen[sink.path.suffix] = objs
    reference = [(o["kind"], o["link"], o["side"], o.get("text")) for o in seen[".pcapng"]]
    assert len(reference) > 80 and {"hello", "keepalive", "hormone"} <= {r[0] for r in reference}
    for suffix, objs in seen.items():
        assert [(o["kind"], o["link"], o["side"], o.get("text")) for o in objs] == reference, suffix
        # ASC keeps times relative to its start: compare each frame's time since the first
        times = [o["time"] - objs[0]["time"] for o in objs]
        ref_times = [o["time"] - seen[".pcapng"][0]["time"] for o in seen[".pcapng"]]
        assert max(abs(a - b) for a, b in zip(times, ref_times, strict=True)) < 1e-3, suffix


def test_bad_pcapng_captures_name_the_file_and_offset(
    caterpillar: CompiledProgram, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    good = tmp_path / "good.pcapng"
    writer = PcapngWriter(good, [caterpillar.image])
    for i in range(3):
        writer.write(
            CAN_INTERFACE,
            1.0 + i,
            struct.pack(">IBxxx", make_arbitration_id(2, SINGLE, 0, 1, 0) | 0x80000000, 2) + b"\x12\x01",
        )
    writer.close()
    raw = good.read_bytes()
    last = len(raw) - 44  # each packet block here is 44 bytes: 12 + 20 + 10 data padded to 12
    cases = {
        "cut.pcapng": (raw[:-1], f"offset {last}: block cut short"),
        "head.pcapng": (raw[: last + 5], f"offset {last}: block header cut short"),
        "garbage.pcapng": (b"\x01" * 64, "offset 0: not a pcapng file"),
        "order.pcapng": (raw[:8] + b"\x00\x01\x02\x03" + raw[12:], "offset 8: bad byte-order magic"),
        "length.pcapng": (
            raw[: last + 4] + struct.pack("<I", 13) + raw[last + 8 :],
            f"offset {last}: block of type 0x6 claims 13 bytes",
        ),
        "trailer.pcapng": (raw[:-4] + struct.pack("<I", 40), f"offset {last}: block's trailing length"),
        "short.pcapng": (raw[:4], "offset 0: block header cut short"),
    }
    for name, (data, words) in cases.items():
        path = tmp_path / name
        path.write_bytes(data)
        assert main([str(path)]) == 2, name
        err = capsys.readouterr().err
        assert str(path) in err and words in err and "Traceback" not in err, (name, err)
    bare = tmp_path / "bare.pcapng"
    PcapngWriter(bare).close()
    assert main([str(bare)]) == 2
    assert "carries no program image" in capsys.readouterr().err and main([str(bare), "--program", CATERPILLAR]) == 0


def test_reading_is_streaming(tmp_path: Path) -> None:
    """200,000 frames read with the memory of a few: the reader holds one record at a time."""
    path = tmp_path / "big.pcap"
    hormone = Hormone("X", ("A",))
    payload = contract_codec().encode(2, hormone)
    can_id = make_arbitration_id(0, SINGLE, 0, 3, 0)
    write_pcap(path, (CapturedFrame(i / 1000, can_id, payload) for i in range(200_000)))
    tracemalloc.start()
    count = sum(1 for _ in read_can(path))
    _current, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert count == 200_000
    assert peak < 1_000_000, peak  # bytes: constant, not proportional to the 5 MB file


def test_a_capture_without_frames_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """python-can's text readers skip lines they cannot parse: a file of such lines has no
    frames, and dump says that rather than printing nothing."""
    path = tmp_path / "notes.asc"
    path.write_text("this is not a log\nnor is this\n")
    assert main([str(path), "--program", CATERPILLAR]) == 0
    assert "no frames in it" in capsys.readouterr().err


def test_help_through_the_umbrella_command(capsys: pytest.CaptureFixture[str]) -> None:
    from dh2rt.cli import main as dh2rt

    assert dh2rt(["dump", "--help"]) == 0
    assert "DH2 terms" in capsys.readouterr().out
