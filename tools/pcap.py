"""pcap files of CAN frames (LINKTYPE_CAN_SOCKETCAN, 227), as Wireshark, tshark and
``candump`` read them: the capture tools' file format. File I/O lives here, above the core;
the core's codecs stay bytes-in, frames-out."""

from __future__ import annotations

import struct
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from dh2rt.errors import EncodeError
from dh2rt.wire.can_frames import CLASSIC_DATA, FD_DATA

LINKTYPE_CAN_SOCKETCAN = 227
CAN_EFF_FLAG = 0x80000000
CAN_RTR_FLAG = 0x40000000
CAN_ERR_FLAG = 0x20000000
FD_BRS, FD_ESI, FD_FDF = 0x01, 0x02, 0x04
#: a pcap file's first four bytes: timestamps in microseconds, or in nanoseconds
PCAP_MAGIC_US = 0xA1B2C3D4
PCAP_MAGIC_NS = 0xA1B23C4D


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
    target.write(struct.pack("<IHHiIII", PCAP_MAGIC_US, 2, 4, 0, 0, 0xFFFF, LINKTYPE_CAN_SOCKETCAN))
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


class PcapWriter:
    """A pcap file of link type 227 written frame by frame (a capture of any length)."""

    def __init__(self, path: str | Path) -> None:
        self._fh: BinaryIO = open(path, "wb")  # noqa: SIM115 - closed by close()
        self._fh.write(struct.pack("<IHHiIII", PCAP_MAGIC_US, 2, 4, 0, 0, 0xFFFF, LINKTYPE_CAN_SOCKETCAN))
        self.count = 0

    def write(self, frame: CapturedFrame) -> None:
        self._fh.write(_record(frame))
        self.count += 1

    def close(self) -> None:
        self._fh.close()
