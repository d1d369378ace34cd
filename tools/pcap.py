"""pcap files of CAN frames (LINKTYPE_CAN_SOCKETCAN, 227), as Wireshark, tshark and
``candump`` read them: the capture tools' file format. File I/O lives here, above the core;
the core's codecs stay bytes-in, frames-out."""

from __future__ import annotations

import struct
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from dh2rt.errors import DecodeError, EncodeError
from dh2rt.wire.can_frames import CLASSIC_DATA, FD_DATA

LINKTYPE_CAN_SOCKETCAN = 227
CAN_EFF_FLAG = 0x80000000
CAN_RTR_FLAG = 0x40000000
CAN_ERR_FLAG = 0x20000000
FD_BRS, FD_ESI, FD_FDF = 0x01, 0x02, 0x04
_PCAP_MAGIC_US = 0xA1B2C3D4
_PCAP_MAGIC_NS = 0xA1B23C4D


@dataclass(frozen=True, slots=True)
class CapturedFrame:
    """One CAN frame in a capture: time (seconds since the epoch), id, data and flags."""

    timestamp: float
    arbitration_id: int
    data: bytes
    is_extended_id: bool = True
    is_remote_frame: bool = False
    is_error_frame: bool = False
    is_fd: bool = False
    bitrate_switch: bool = False


def write_pcap(target: str | Path | BinaryIO, frames: Iterable[CapturedFrame]) -> int:
    """Write frames as a pcap file of link type 227 (Wireshark/tshark read it); returns count."""
    if isinstance(target, str | Path):
        with open(target, "wb") as fh:
            return write_pcap(fh, frames)
    target.write(struct.pack("<IHHiIII", _PCAP_MAGIC_US, 2, 4, 0, 0, 0xFFFF, LINKTYPE_CAN_SOCKETCAN))
    count = 0
    for fr in frames:
        target.write(_record(fr))
        count += 1
    return count


def _check(fr: CapturedFrame) -> None:
    """A frame the file cannot hold as given is our mistake (EncodeError), not something to
    mask or truncate into a different frame."""
    id_limit = 0x1FFFFFFF if fr.is_extended_id else 0x7FF
    if not 0 <= fr.arbitration_id <= id_limit:
        raise EncodeError(f"pcap: CAN id {fr.arbitration_id:#x} is outside 0..{id_limit:#x}")
    data_limit = FD_DATA if fr.is_fd else CLASSIC_DATA
    if len(fr.data) > data_limit:
        raise EncodeError(f"pcap: {len(fr.data)} data bytes exceed {data_limit}")
    if not 0 <= fr.timestamp < 2**32:
        raise EncodeError(f"pcap: timestamp {fr.timestamp} is outside the format's 32-bit seconds")


def socketcan_packet(fr: CapturedFrame) -> bytes:
    """The frame as Linux SocketCAN hands it to a capture (link type 227, in pcap and pcapng):
    the 8-byte header (big-endian id with the EFF/RTR/ERR flags, length, FD flags), the data."""
    _check(fr)
    can_id = fr.arbitration_id
    if fr.is_extended_id:
        can_id |= CAN_EFF_FLAG
    if fr.is_remote_frame:
        can_id |= CAN_RTR_FLAG
    if fr.is_error_frame:
        can_id |= CAN_ERR_FLAG
    fd_flags = (FD_FDF | (FD_BRS if fr.bitrate_switch else 0)) if fr.is_fd else 0
    return struct.pack(">IBBxx", can_id, len(fr.data), fd_flags) + bytes(fr.data)


def _record(fr: CapturedFrame) -> bytes:
    """One pcap record: its 16-byte header, the 8-byte SocketCAN header, the data."""
    body = socketcan_packet(fr)
    sec = int(fr.timestamp)
    usec = min(round((fr.timestamp - sec) * 1e6), 999_999)
    return struct.pack("<IIII", sec, usec, len(body), len(body)) + body


def read_pcap(source: str | Path | BinaryIO) -> list[CapturedFrame]:
    """Read a pcap of link type 227; raises DecodeError naming what is wrong with the file."""
    if isinstance(source, str | Path):
        with open(source, "rb") as fh:
            return read_pcap(fh)
    head = source.read(24)
    if len(head) < 24:
        raise DecodeError("pcap: file shorter than its 24-byte header")
    for endian in ("<", ">"):
        magic = struct.unpack(endian + "I", head[:4])[0]
        if magic in (_PCAP_MAGIC_US, _PCAP_MAGIC_NS):
            break
    else:
        raise DecodeError(f"pcap: bad magic number {head[:4].hex()} (not a pcap file)")
    scale = 1e-6 if magic == _PCAP_MAGIC_US else 1e-9
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


class PcapWriter:
    """A pcap file of link type 227 written frame by frame (a capture of any length)."""

    def __init__(self, path: str | Path) -> None:
        self._fh: BinaryIO = open(path, "wb")  # noqa: SIM115 - closed by close()
        self._fh.write(struct.pack("<IHHiIII", _PCAP_MAGIC_US, 2, 4, 0, 0, 0xFFFF, LINKTYPE_CAN_SOCKETCAN))
        self.count = 0

    def write(self, frame: CapturedFrame) -> None:
        self._fh.write(_record(frame))
        self.count += 1

    def close(self) -> None:
        self._fh.close()
