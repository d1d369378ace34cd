"""Dynamixel Protocol 2.0 packets, sans-IO: bytes in, packets out; no ports, no clocks.

Wire format (all multi-byte fields little-endian)::

    FF FF FD 00 | ID | LEN_L LEN_H | INST | PARAMS ... | CRC_L CRC_H

``LEN`` counts INST, the (stuffed) params and the CRC, so ``LEN = len(params) + 3`` before
stuffing. The CRC is CRC-16/BUYPASS (polynomial 0x8005, init 0, not reflected) over every byte
from the header to the last param. Inside INST+params, each ``FF FF FD`` is sent as
``FF FF FD FD`` so that the header ``FF FF FD 00`` never appears inside a packet. A status
packet is INST ``0x55``; its first param is the error byte (bit 0x80 = hardware alert, low bits
an error number).

Error policy, in the manner of h11:

* :class:`PacketParser` never raises on received bytes. Bytes that do not start a packet are
  *garbage*: skipped by design and counted in :attr:`PacketParser.skipped_bytes`. A
  well-framed packet whose CRC fails comes out as a :class:`CorruptPacket` event (a servo
  answers those with a CRC error status) and the parser resynchronises one byte after its
  header, so a packet swallowed by a corrupted length field is still found.
* The strict helpers (:func:`decode_packet`, the encoders, the status accessors) raise
  :class:`DxlProtocolError` (a :class:`dh2rt.errors.CodecError`), or
  :class:`DxlCrcError` for a bad CRC; nothing else.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Final

from dh2rt.errors import DxlCrcError, DxlDecodeError, DxlEncodeError

HEADER: Final = b"\xff\xff\xfd\x00"
STUFF_PATTERN: Final = b"\xff\xff\xfd"
BROADCAST_ID: Final = 0xFE
MAX_ID: Final = 0xFC  # highest unicast id
STATUS_INSTRUCTION: Final = 0x55
# dynamixel-sdk rejects status packets longer than 1024 bytes; so do we, which also bounds how
# long a corrupted length field can make the parser wait.
MAX_LENGTH: Final = 1024
MIN_LENGTH: Final = 3  # INST + CRC
_HEAD_LEN: Final = 7  # header, id, length


class Instruction(enum.IntEnum):
    """Protocol 2.0 instruction codes."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    FACTORY_RESET = 0x06
    REBOOT = 0x08
    CLEAR = 0x10
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    FAST_SYNC_READ = 0x8A
    BULK_READ = 0x92
    BULK_WRITE = 0x93


def _make_table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE: Final = _make_table()


def crc16(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """CRC-16/BUYPASS (poly 0x8005, init 0, not reflected) of ``data``, continuing ``crc``."""
    table = _CRC_TABLE
    for byte in data:
        crc = ((crc << 8) & 0xFFFF) ^ table[(crc >> 8) ^ byte]
    return crc


def stuff(body: bytes) -> bytes:
    """Byte-stuff INST+params: every ``FF FF FD`` becomes ``FF FF FD FD``."""
    # Occurrences of FF FF FD cannot overlap, so a left-to-right replace finds them all.
    return body.replace(STUFF_PATTERN, STUFF_PATTERN + b"\xfd")


def unstuff(body: bytes) -> bytes:
    """Undo :func:`stuff`: every ``FF FF FD FD`` becomes ``FF FF FD``."""
    return body.replace(STUFF_PATTERN + b"\xfd", STUFF_PATTERN)


@dataclass(frozen=True, slots=True)
class Packet:
    """One decoded packet: instruction or status (``instruction == 0x55``)."""

    id: int
    instruction: int
    params: bytes = b""

    @property
    def is_status(self) -> bool:
        return self.instruction == STATUS_INSTRUCTION

    @property
    def error(self) -> int:
        """The status packet's error byte."""
        if not self.is_status or not self.params:
            raise DxlDecodeError(
                f"packet from id {self.id} (instruction 0x{self.instruction:02x}) "
                "is not a status packet with an error byte"
            )
        return self.params[0]

    @property
    def data(self) -> bytes:
        """The status packet's data (the params after the error byte)."""
        self.error  # noqa: B018 - validates that this is a status packet
        return self.params[1:]


@dataclass(frozen=True, slots=True)
class CorruptPacket:
    """A framed packet whose CRC failed; ``raw`` is the bytes as received."""

    id: int
    raw: bytes


def _check_byte(name: str, value: int, high: int = 0xFF) -> None:
    if not isinstance(value, int) or not 0 <= value <= high:
        raise DxlEncodeError(f"{name} must be an integer in 0..{high}, got {value!r}")


def encode_packet(packet: Packet) -> bytes:
    """Serialise ``packet`` with stuffing and CRC."""
    _check_byte("id", packet.id)
    _check_byte("instruction", packet.instruction)
    body = stuff(bytes((packet.instruction,)) + bytes(packet.params))
    length = len(body) + 2
    if _HEAD_LEN + length > MAX_LENGTH:
        raise DxlEncodeError(
            f"packet too long: {len(packet.params)} params make {_HEAD_LEN + length} bytes (max {MAX_LENGTH})"
        )
    frame = HEADER + bytes((packet.id, length & 0xFF, length >> 8)) + body
    crc = crc16(frame)
    return frame + bytes((crc & 0xFF, crc >> 8))


def encode_instruction(dxl_id: int, instruction: int, params: bytes = b"") -> bytes:
    """An instruction packet for ``dxl_id`` (0..252, or 254 for broadcast)."""
    return encode_packet(Packet(dxl_id, instruction, bytes(params)))


def encode_status(dxl_id: int, error: int = 0, data: bytes = b"") -> bytes:
    """A status packet from ``dxl_id`` with ``error`` byte and ``data``."""
    _check_byte("error", error)
    return encode_packet(Packet(dxl_id, STATUS_INSTRUCTION, bytes((error,)) + bytes(data)))


def _frame_length(buf: bytes | bytearray, start: int = 0) -> int:
    return buf[start + 5] | (buf[start + 6] << 8)


def decode_packet(frame: bytes) -> Packet:
    """Decode exactly one whole packet; raise :class:`DxlProtocolError` if it is not one."""
    frame = bytes(frame)
    if len(frame) < _HEAD_LEN + MIN_LENGTH or not frame.startswith(HEADER):
        raise DxlDecodeError(f"not a Protocol 2.0 packet: {frame[:16].hex(' ')!r}")
    length = _frame_length(frame)
    if length < MIN_LENGTH or _HEAD_LEN + length != len(frame):
        raise DxlDecodeError(f"length field says {length} but {len(frame) - _HEAD_LEN} bytes follow it")
    expected = frame[-2] | (frame[-1] << 8)
    actual = crc16(frame[:-2])
    if expected != actual:
        raise DxlCrcError(f"CRC mismatch from id {frame[4]}: packet says 0x{expected:04x}, computed 0x{actual:04x}")
    body = unstuff(frame[_HEAD_LEN:-2])
    return Packet(frame[4], body[0], body[1:])


Event = Packet | CorruptPacket


class PacketParser:
    """Incremental decoder: :meth:`feed` bytes as they arrive, get the packets completed.

    The events are the same whether the bytes come whole or one at a time. Never raises on
    input: see the module docstring for how garbage and bad CRCs are handled.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.skipped_bytes = 0
        self.corrupt_packets = 0

    @property
    def pending(self) -> int:
        """Bytes held while waiting for the rest of a packet."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Event]:
        """Add received bytes; return the events they complete, in order."""
        buf = self._buf
        buf += data
        events: list[Event] = []
        while True:
            start = buf.find(HEADER)
            if start < 0:
                # Keep a possible partial header (up to 3 bytes) for the next feed.
                keep = next((k for k in (3, 2, 1) if len(buf) >= k and HEADER.startswith(buf[-k:])), 0)
                drop = len(buf) - keep
                self.skipped_bytes += drop
                del buf[:drop]
                return events
            if start:
                self.skipped_bytes += start
                del buf[:start]
            if len(buf) < _HEAD_LEN:
                return events
            length = _frame_length(buf)
            if not MIN_LENGTH <= length <= MAX_LENGTH - _HEAD_LEN:
                self._skip_one()
                continue
            total = _HEAD_LEN + length
            if len(buf) < total:
                return events
            frame = bytes(buf[:total])
            if crc16(frame[:-2]) != (frame[-2] | (frame[-1] << 8)):
                self.corrupt_packets += 1
                events.append(CorruptPacket(frame[4], frame))
                # Resync one byte on: if the length field was the corrupted part, the next real
                # packet starts inside this span.
                self._skip_one()
                continue
            del buf[:total]
            body = unstuff(frame[_HEAD_LEN:-2])
            events.append(Packet(frame[4], body[0], body[1:]))

    def _skip_one(self) -> None:
        del self._buf[:1]
        self.skipped_bytes += 1

    def reset(self) -> None:
        """Forget any partial packet (e.g. after the port was flushed)."""
        self.skipped_bytes += len(self._buf)
        self._buf.clear()
