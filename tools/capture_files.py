"""Reading CAN captures, streaming: pcap (link type 227, as Wireshark and ``tools.pcap``
write it) and every log format python-can reads (candump ``.log``, ``.asc``, ``.blf``,
``.csv``, ``.trc``, through ``can.LogReader``). Frames come one at a time, so memory stays
constant whatever the length of the capture.

A file that is not what it claims, or ends in the middle of a record, raises
:class:`~dh2rt.errors.CaptureError` naming the file and the byte offset (pcap) or the record.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO, NamedTuple

from dh2rt.errors import CaptureError
from tools.pcap import CAN_EFF_FLAG, LINKTYPE_CAN_SOCKETCAN

_PCAP_MAGICS = {0xA1B2C3D4: 1e-6, 0xA1B23C4D: 1e-9}
#: The suffixes python-can's LogReader knows (and what it makes of them).
PYTHON_CAN_SUFFIXES = (".log", ".asc", ".blf", ".csv", ".trc", ".db")


class CanRecord(NamedTuple):
    """One CAN frame of a capture."""

    timestamp: float
    arbitration_id: int
    data: bytes
    is_extended_id: bool


def read_can(path: Path) -> Iterator[CanRecord]:
    """The frames of a capture file, in file order."""
    if not path.exists():
        raise CaptureError(f"{path}: no such capture file")
    suffix = path.suffix.lower()
    if suffix in (".pcap", ".cap"):
        with path.open("rb") as fh:
            yield from _read_pcap(fh, path)
        return
    if suffix in PYTHON_CAN_SUFFIXES:
        yield from _read_python_can(path)
        return
    known = ", ".join((".pcap", *PYTHON_CAN_SUFFIXES))
    raise CaptureError(f"{path}: unknown capture format {suffix or '(no suffix)'} (known: {known})")


def _read_pcap(fh: BinaryIO, path: Path) -> Iterator[CanRecord]:
    head = fh.read(24)
    if len(head) < 24:
        raise CaptureError(f"{path}: offset 0: shorter than a pcap header (24 bytes)")
    for endian in ("<", ">"):
        magic = struct.unpack(endian + "I", head[:4])[0]
        if magic in _PCAP_MAGICS:
            scale = _PCAP_MAGICS[magic]
            break
    else:
        raise CaptureError(f"{path}: offset 0: not a pcap file (magic {head[:4].hex()})")
    linktype = struct.unpack(endian + "I", head[20:24])[0] & 0x0FFFFFFF
    if linktype != LINKTYPE_CAN_SOCKETCAN:
        raise CaptureError(f"{path}: offset 20: link type {linktype}, expected {LINKTYPE_CAN_SOCKETCAN} (SocketCAN)")
    offset = 24
    record = struct.Struct(endian + "IIII")
    while True:
        rec = fh.read(16)
        if not rec:
            return
        if len(rec) < 16:
            raise CaptureError(f"{path}: offset {offset}: record header cut short ({len(rec)} of 16 bytes)")
        sec, frac, incl, _orig = record.unpack(rec)
        body = fh.read(incl)
        if len(body) < incl:
            raise CaptureError(f"{path}: offset {offset}: record cut short ({len(body)} of {incl} bytes)")
        if incl < 8:
            raise CaptureError(f"{path}: offset {offset}: record of {incl} bytes has no CAN header")
        can_id, length = struct.unpack(">IB", body[:5])
        if length > incl - 8:
            raise CaptureError(f"{path}: offset {offset}: CAN frame claims {length} bytes, the record has {incl - 8}")
        extended = bool(can_id & CAN_EFF_FLAG)
        can_id &= 0x1FFFFFFF if extended else 0x7FF
        yield CanRecord(sec + frac * scale, can_id, body[8 : 8 + length], extended)
        offset += 16 + incl


def _read_python_can(path: Path) -> Iterator[CanRecord]:
    import can

    if path.suffix.lower() == ".blf":
        # python-can's BLF reader leaves the file open when the header is wrong: look first
        with path.open("rb") as fh:
            if fh.read(4) != b"LOGG":
                raise CaptureError(f"{path}: offset 0: not a BLF file (no LOGG signature)")

    try:
        reader = can.LogReader(str(path))
    except Exception as exc:  # python-can raises what its parsers raise: name the file
        raise CaptureError(f"{path}: python-can cannot read it ({type(exc).__name__}: {exc})") from None
    count = 0
    try:
        for msg in reader:
            count += 1
            yield CanRecord(float(msg.timestamp), int(msg.arbitration_id), bytes(msg.data), bool(msg.is_extended_id))
    except CaptureError:
        raise
    except Exception as exc:
        raise CaptureError(f"{path}: record {count}: python-can cannot read it ({type(exc).__name__}: {exc})") from None
    finally:
        stop = getattr(reader, "stop", None)
        if callable(stop):
            stop()
