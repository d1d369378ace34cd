"""The decoder's memo (a frame seen before is not decoded again, its line not formatted
again) changes nothing but the speed, and its memory is bounded.

`dh2rt dump` of a pcapng of a million frames runs in constant memory: the reader, the
decoder and the output hold a few frames at a time. The capture is written streaming (frames
of a caterpillar: hormones, every keep-alive sequence number, Hellos, segmented hormones,
garbage and serial link frames), and dumped in a child process so that its peak resident
memory is its own: the peak after the first 100,000 lines and at the end must be the same,
give or take what the allocator rounds."""

from __future__ import annotations

import json
import random
import struct
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from dh2rt.compiler import compile_file
from dh2rt.hormone import Hormone
from dh2rt.program import CompiledProgram
from dh2rt.wire.can_frames import MIDDLE, SINGLE, CanFrame, make_arbitration_id, segment
from dh2rt.wire.frame import FrameCodec, Hello, KeepAlive, program_digest
from dh2rt.wire.negotiation import MANAGEMENT_ID, BusMessage, BusOp, encode_bus
from dh2rt.wire.serial_framing import encode_serial
from tools import decode, serial_records
from tools.capture_reader import CanRecord, Record
from tools.pcap import CAN_EFF_FLAG
from tools.pcapng import CAN_INTERFACE, SERIAL_INTERFACE, PcapngWriter
from tools.serial_records import SerialRecord

ROOT = Path(__file__).resolve().parents[2]
CATERPILLAR = ROOT / "examples" / "caterpillar.dh2"
FRAMES = 1_000_000
FRONT, BACK = 1, 2

#: Run in the child: dump the capture into a sink that counts lines and notes the peak
#: resident memory (ru_maxrss, KiB on Linux) once 100,000 lines are out and at the end.
CHILD = """
import json, resource, sys
from tools.dump import main

class Sink:
    lines = 0
    early = 0
    def write(self, text):
        self.lines += text.count("\\n")
        if not self.early and self.lines >= 100_000:
            self.early = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return len(text)
    def flush(self):
        pass

sink = Sink()
sys.stdout = sink
code = main(sys.argv[1:])
sys.stdout = sys.__stdout__
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"code": code, "lines": sink.lines, "early_kib": sink.early, "peak_kib": peak}))
"""


def tangle(programs: list[CompiledProgram], n: int, seed: int = 7) -> list[Record]:
    """``n`` records that test a memo: the same bytes over and over from a few link ends,
    Hellos that switch an end to another program (the same bytes then mean another hormone),
    segments of several ends interleaved with single frames (some lost), garbage, management
    and serial link frames."""
    rng = random.Random(seed)
    codec = FrameCodec(programs[0].vocabulary, programs[0].profile.connector_count)
    ends = [(link, side) for link in (1, 2, 3) for side in (0, 1)]
    waiting: dict[tuple[int, int], list[CanFrame]] = {}
    out: list[Record] = []
    for i in range(n):
        at = 100.0 + i / 1000
        link, side = rng.choice(ends)
        r = rng.random()
        if r < 0.35:  # X(A).. with a path of 0 to 20 hops: one frame or several, the rest later
            path = tuple((2, 1) for _ in range(rng.choice((0, 0, 3, 9, 20))))
            frames = segment(codec.encode(2, Hormone("X", (rng.choice("ABCD"),), path)), link, side)
            if len(frames) > 1:
                waiting.setdefault((link, side), []).extend(frames[1:])
            out.append(CanRecord(at, frames[0].arbitration_id, frames[0].data, True))
        elif r < 0.5 and waiting:  # the next segment of some end (one in twenty lost)
            end = rng.choice(sorted(waiting))
            frame = waiting[end].pop(0)
            if not waiting[end]:
                del waiting[end]
            if rng.random() > 0.05:
                out.append(CanRecord(at, frame.arbitration_id, frame.data, True))
        elif r < 0.75:
            beacon = codec.encode(1 + side, KeepAlive(rng.randrange(4)))
            out.append(CanRecord(at, make_arbitration_id(2, SINGLE, 0, link, side), beacon, True))
        elif r < 0.8:  # a Hello: one of the programs, or one the capture does not carry
            image = rng.choice([*(p.image for p in programs), b"another program"])
            hello = codec.encode(1 + side, Hello(program_digest(image)))
            out.append(CanRecord(at, make_arbitration_id(3, SINGLE, 0, link, side), hello, True))
        elif r < 0.85:
            out.append(CanRecord(at, rng.randrange(0x800), rng.randbytes(2), False))
        elif r < 0.88:
            claim = encode_bus(BusMessage(BusOp.CLAIM, link, 0x1234))
            out.append(CanRecord(at, MANAGEMENT_ID, rng.choice((claim, rng.randbytes(5))), True))
        elif r < 0.9:
            wire = encode_serial(codec.encode(2, Hormone("X", ("B",))))
            out.append(SerialRecord(at, link, side, wire, lost=rng.random() < 0.3))
        else:  # bytes that are a hormone for one program and not for another, or garbage
            data = rng.choice((b"\xc2\x00\x01\x00", b"\xc2\x00\x02\x01\x02", rng.randbytes(rng.randrange(1, 9))))
            out.append(CanRecord(at, make_arbitration_id(0, SINGLE, 0, link, side), data, True))
    return out


def afresh(programs: list[CompiledProgram], records: list[Record]) -> list[str]:
    """Each record's line with every frame decoded anew: the decoder with its memo turned off."""
    return [hop.describe() for hop in decode.Decoder(programs, memo=False).hops(records)]


@pytest.mark.parametrize("memo_size", [1, 7, decode.MEMO_SIZE])
def test_the_memo_changes_nothing_but_the_speed(
    examples: Path, monkeypatch: pytest.MonkeyPatch, memo_size: int
) -> None:
    """lines() (what dump prints) and hops() give, with a memo of any size (7: often emptied),
    what decoding every frame anew gives."""
    programs = [
        compile_file(str(examples / name)) for name in ("caterpillar.dh2", "locomotion.dh2", "legs_to_snake.dh2")
    ]
    records = tangle(programs, 6000)
    reference = afresh(programs, records)
    kinds = {line.split()[5] for line in reference if " ? side ?" not in line}
    assert {"hormone", "keepalive", "hello", "segment", "error", "link"} <= kinds, kinds
    # after a Hello of locomotion.dh2, the caterpillar's X(A) bytes mean its L(0)
    assert any("L(0)" in line for line in reference) and any("X(A)" in line for line in reference)
    assert any("(reassembled)" in line for line in reference) and any("out of order" in line for line in reference)
    monkeypatch.setattr(decode, "MEMO_SIZE", memo_size)
    assert list(decode.Decoder(programs).lines(records)) == reference
    assert [hop.describe() for hop in decode.Decoder(programs).hops(records)] == reference


def packets(program: CompiledProgram, n: int) -> Iterator[tuple[int, bytes]]:
    """``n`` packets (interface, bytes) of a caterpillar's traffic, round and round: 16 rounds
    on different links, so that more frames differ than the decoder's memo holds."""
    codec = FrameCodec(program.vocabulary, program.profile.connector_count)
    hello = codec.encode(BACK, Hello(program_digest(program.image)))
    long_path = tuple((BACK, FRONT) for _ in range(12))
    frames: list[tuple[int, bytes, bool]] = []  # (arbitration id, data, extended)

    def send(payload: bytes, link: int, side: int) -> None:
        frames.extend((f.arbitration_id, f.data, True) for f in segment(payload, link, side))

    for first in range(1, 16 * 7, 7):
        links = range(first, first + 7)
        for link in links:
            send(hello, link, 0)
        for seq in range(256):
            link = links[seq % 7]
            phase = "ABCD"[seq % 4]
            send(codec.encode(BACK, Hormone("X", (phase,))), link, 0)
            send(codec.encode(BACK, KeepAlive(seq)), link, 0)
            send(codec.encode(FRONT, KeepAlive(seq)), link, 1)
            if seq % 16 == 0:  # a hormone that carries its path (segmented), and some garbage
                send(codec.encode(BACK, Hormone("X", (phase,), long_path)), link, 0)
                frames.append((0x123, bytes([seq]), False))
                frames.append((make_arbitration_id(0, MIDDLE, 1, link, 0), b"\x00" * 8, True))
                frames.append((make_arbitration_id(0, SINGLE, 0, link, 0), b"\x42\x00\x00\x00", True))
    can_packets = [
        (CAN_INTERFACE, struct.pack(">IBBxx", can_id | (CAN_EFF_FLAG if ext else 0), len(data), 0) + data)
        for can_id, data, ext in frames
    ]
    wire = encode_serial(codec.encode(BACK, Hormone("X", ("A",))))
    serial = (SERIAL_INTERFACE, serial_records.pack(SerialRecord(0.0, 9, 0, wire)))
    for i in range(n):
        yield serial if i % 100 == 99 else can_packets[i % len(can_packets)]


@pytest.mark.slow
def test_dump_of_a_million_frame_pcapng_runs_in_constant_memory(caterpillar: CompiledProgram, tmp_path: Path) -> None:
    path = tmp_path / "million.pcapng"
    writer = PcapngWriter(path, [caterpillar.image])
    try:
        for i, (interface, data) in enumerate(packets(caterpillar, FRAMES)):
            writer.write(interface, 1_700_000_000 + i / 6600, data)
    finally:
        writer.close()
    assert path.stat().st_size > 40 * FRAMES  # the file is far larger than the memory allowed below
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(path), "--program", str(CATERPILLAR)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got["code"] == 0 and got["lines"] == FRAMES, got
    # 900,000 more frames (36 MB of file) may not add more than 4 MiB of resident memory
    assert got["peak_kib"] - got["early_kib"] < 4096, got
