"""The packet layout of dh2rt's serial link captures (pcapng link type 147, ``LINKTYPE_USER0``).

Each packet is one frame one module sent through one emulated infrared link, as the link
emulator's tap saw it::

    bytes 0..1   "D2"        magic: a dh2rt serial record
    byte  2      version     1
    byte  3      flags       bit 0: the side that sent it (0 or 1)
                             bit 1: lost (the link dropped it: sent, never delivered)
                             bit 2: corrupted (what was delivered fails COBS or CRC-32)
    bytes 4..7   link id     big-endian
    bytes 8..    the frame   as on the wire: COBS(payload + CRC-32) and the 0x00 delimiter;
                             for a lost frame the bytes sent, otherwise the bytes delivered

Wireshark's dissector (``tools/wireshark/dh2rt.lua``) reads the same layout.
"""

from __future__ import annotations

import struct
from typing import NamedTuple

from dh2rt.errors import DecodeError

MAGIC = b"D2"
VERSION = 1
HEADER = struct.Struct(">2sBBI")
FLAG_SIDE, FLAG_LOST, FLAG_CORRUPTED = 0x01, 0x02, 0x04


class SerialRecord(NamedTuple):
    """One frame on one emulated serial link."""

    timestamp: float
    link: int
    side: int  # the side that sent it
    wire: bytes
    lost: bool = False
    corrupted: bool = False


def pack(record: SerialRecord) -> bytes:
    flags = (record.side & 1) | (FLAG_LOST if record.lost else 0) | (FLAG_CORRUPTED if record.corrupted else 0)
    return HEADER.pack(MAGIC, VERSION, flags, record.link) + bytes(record.wire)


def unpack(timestamp: float, data: bytes) -> SerialRecord:
    """The record in a packet's bytes; DecodeError for bytes that are not one."""
    if len(data) < HEADER.size:
        raise DecodeError(f"serial record of {len(data)} bytes is shorter than its {HEADER.size}-byte header")
    magic, version, flags, link = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise DecodeError(f"serial record: magic {magic!r}, expected {MAGIC!r}")
    if version != VERSION:
        raise DecodeError(f"serial record: version {version}, expected {VERSION}")
    return SerialRecord(
        timestamp,
        link,
        flags & FLAG_SIDE,
        bytes(data[HEADER.size :]),
        bool(flags & FLAG_LOST),
        bool(flags & FLAG_CORRUPTED),
    )
