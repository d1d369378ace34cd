"""pcap (LINKTYPE_CAN_SOCKETCAN) files: written and read back exactly; bad files name what is wrong."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import pytest

from dh2rt.errors import CodecError, EncodeError
from dh2rt.wire.can_frames import SINGLE, make_arbitration_id
from tools.pcap import CapturedFrame, read_pcap, write_pcap


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
