"""pcap (LINKTYPE_CAN_SOCKETCAN) files: written and read back exactly; bad files name what is wrong."""

from __future__ import annotations

import io
import struct
from pathlib import Path
from typing import BinaryIO

import pytest

from dh2rt.errors import CodecError, DecodeError, EncodeError
from dh2rt.wire.can_frames import CLASSIC_DATA, FD_DATA, SINGLE, make_arbitration_id
from tools.pcap import (
    CAN_EFF_FLAG,
    CAN_ERR_FLAG,
    CAN_RTR_FLAG,
    FD_BRS,
    FD_FDF,
    LINKTYPE_CAN_SOCKETCAN,
    PCAP_MAGIC_NS,
    PCAP_MAGIC_US,
    CapturedFrame,
    write_pcap,
)


def read_pcap(source: str | Path | BinaryIO) -> list[CapturedFrame]:
    """Read a pcap of link type 227 back into the frames written; raises DecodeError naming
    what is wrong with the file. (The tools read captures with tools.capture_files.read_can.)"""
    if isinstance(source, str | Path):
        with open(source, "rb") as fh:
            return read_pcap(fh)
    head = source.read(24)
    if len(head) < 24:
        raise DecodeError("pcap: file shorter than its 24-byte header")
    for endian in ("<", ">"):
        magic = struct.unpack(endian + "I", head[:4])[0]
        if magic in (PCAP_MAGIC_US, PCAP_MAGIC_NS):
            break
    else:
        raise DecodeError(f"pcap: bad magic number {head[:4].hex()} (not a pcap file)")
    scale = 1e-6 if magic == PCAP_MAGIC_US else 1e-9
    linktype = struct.unpack(endian + "I", head[20:24])[0] & 0x0FFFFFFF
    if linktype != LINKTYPE_CAN_SOCKETCAN:
        raise DecodeError(f"pcap: link type {linktype}, expected {LINKTYPE_CAN_SOCKETCAN} (CAN SocketCAN)")
    frames: list[CapturedFrame] = []
    index = 0
    while True:
        rec = source.read(16)
        if not rec:
            return frames
        if len(rec) < 16:
            raise DecodeError(f"pcap: record {index} header truncated")
        sec, frac, incl, _orig = struct.unpack(endian + "IIII", rec)
        body = source.read(incl)
        if len(body) < incl or incl < 8:
            raise DecodeError(f"pcap: record {index} truncated or shorter than the 8-byte CAN header")
        can_id, length, fd_flags = struct.unpack(">IBB", body[:6])
        if length > len(body) - 8 or length > FD_DATA:
            raise DecodeError(f"pcap: record {index} claims {length} data bytes, has {len(body) - 8}")
        extended = bool(can_id & CAN_EFF_FLAG)
        is_fd = bool(fd_flags & FD_FDF) or length > CLASSIC_DATA
        frames.append(
            CapturedFrame(
                timestamp=sec + frac * scale,
                arbitration_id=can_id & (0x1FFFFFFF if extended else 0x7FF),
                data=bytes(body[8 : 8 + length]),
                is_extended_id=extended,
                is_remote_frame=bool(can_id & CAN_RTR_FLAG),
                is_error_frame=bool(can_id & CAN_ERR_FLAG),
                is_fd=is_fd,
                bitrate_switch=bool(fd_flags & FD_BRS),
            )
        )
        index += 1


def test_pcap_round_trip(tmp_path: Path) -> None:
    frames = [
        CapturedFrame(1700000000.25, make_arbitration_id(0, SINGLE, 0, 7, 1), b"\x42\x00\x00\x00"),
        CapturedFrame(1700000000.5, 0x123, b"\x01", is_extended_id=False),
        CapturedFrame(1700000001.0, 0x1ABCDEF, bytes(range(12)), is_fd=True, bitrate_switch=True),
        CapturedFrame(1700000002.0, 0x7FF, b"", is_extended_id=False, is_remote_frame=True),
    ]
    path = tmp_path / "cap.pcap"
    assert write_pcap(path, frames) == 4
    raw = path.read_bytes()
    assert struct.unpack("<I", raw[20:24])[0] == 227
    # first record's CAN header: id | EFF flag, big-endian; length 4
    assert raw[40:44] == struct.pack(">I", frames[0].arbitration_id | 0x80000000) and raw[44] == 4
    assert read_pcap(path) == frames


def test_read_pcap_errors() -> None:
    with pytest.raises(CodecError, match="bad magic"):
        read_pcap(io.BytesIO(b"\x00" * 24))
    with pytest.raises(CodecError, match="shorter than"):
        read_pcap(io.BytesIO(b"\xd4\xc3"))
    header = struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1)
    with pytest.raises(CodecError, match="link type 1"):
        read_pcap(io.BytesIO(header))
    good = io.BytesIO()
    write_pcap(good, [CapturedFrame(1.0, 5, b"\x01\x02")])
    with pytest.raises(CodecError, match="record 0"):
        read_pcap(io.BytesIO(good.getvalue()[:-1]))


@pytest.mark.parametrize(
    "frame",
    [
        CapturedFrame(1.0, 0x800, b"", is_extended_id=False),
        CapturedFrame(1.0, 1 << 29, b""),
        CapturedFrame(1.0, 5, bytes(9)),
        CapturedFrame(1.0, 5, bytes(65), is_fd=True),
        CapturedFrame(-1.0, 5, b""),
    ],
)
def test_write_pcap_refuses_frames_it_cannot_hold(frame: CapturedFrame) -> None:
    """Local errors: never a masked id or a struct.error, always EncodeError (a ValueError)."""
    with pytest.raises(EncodeError):
        write_pcap(io.BytesIO(), [frame])
