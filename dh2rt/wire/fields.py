"""What the transfer and control families share (:mod:`dh2rt.wire.transfer`,
:mod:`dh2rt.wire.operator`): the two-byte header, range checks, paths written a byte a hop,
and a reader that names the field it runs short in. Kept apart so that a module loading one
family's messages does not load the other's.
"""

from __future__ import annotations

import struct

from dh2rt.errors import DecodeError, EncodeError
from dh2rt.wire.sizes import MAX_CONNECTOR, MAX_PATH

#: A path: hops ``(sent_through, received_at)``, from the entry point outwards.
Path = tuple[tuple[int, int], ...]


def check_range(name: str, value: int, low: int, high: int) -> None:
    """EncodeError naming ``name`` unless ``value`` is an int in ``low..high``."""
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise EncodeError(f"{name} {value!r} is outside {low}..{high}")


def encode_path(path: Path) -> bytes:
    """A path as both families write it: n u8, then a byte a hop, ``sent << 4 | received``."""
    if len(path) > MAX_PATH:
        raise EncodeError(f"path of {len(path)} hops exceeds {MAX_PATH}")
    out = bytearray((len(path),))
    for sent, received in path:
        check_range("path connector", sent, 1, MAX_CONNECTOR)
        check_range("path connector", received, 1, MAX_CONNECTOR)
        out.append(sent << 4 | received)
    return bytes(out)


def read_header(data: bytes, family: int, name: str) -> tuple[int, int]:
    """``(sender connector, message type byte)`` of a frame of ``family`` (byte 0's top two
    bits), called ``name`` in errors; DecodeError for a frame too short or of another family."""
    if len(data) < 2:
        raise DecodeError(f"{name}: {len(data)} bytes, too short for a header and a type")
    head = data[0]
    if head >> 6 != family:
        raise DecodeError(f"{name}: family {head >> 6}, expected {family}")
    if head & 0x0F == 0:
        raise DecodeError(f"{name}: sender connector 0")
    return head & 0x0F, data[1]


def check_class(data: bytes, what: str, expected: int) -> None:
    """DecodeError unless byte 0's class bits are ``expected``."""
    if (data[0] >> 4) & 3 != expected:
        raise DecodeError(f"{what}: class {(data[0] >> 4) & 3}, expected {expected}")


class FieldReader:
    """Reads fields from a frame in order, from byte 2; every shortfall is a DecodeError
    naming the field."""

    __slots__ = ("data", "pos", "what")

    def __init__(self, data: bytes, what: str) -> None:
        self.data = data
        self.pos = 2
        self.what = what

    def take(self, n: int, field: str) -> bytes:
        if self.pos + n > len(self.data):
            raise DecodeError(f"{self.what}: cut short in the {field} at byte {self.pos}")
        out = self.data[self.pos : self.pos + n]
        self.pos += n
        return out

    def unpack(self, fmt: str, field: str) -> tuple[int, ...]:
        return struct.unpack(fmt, self.take(struct.calcsize(fmt), field))

    def path(self, field: str = "path") -> Path:
        (n,) = self.take(1, f"{field} length")
        if n > MAX_PATH:
            raise DecodeError(f"{self.what}: {field} of {n} hops exceeds {MAX_PATH}")
        hops = tuple((b >> 4, b & 0x0F) for b in self.take(n, field))
        if any(not (s and r) for s, r in hops):
            raise DecodeError(f"{self.what}: a {field} hop names connector 0")
        return hops

    def end(self) -> None:
        if self.pos != len(self.data):
            raise DecodeError(f"{self.what}: {len(self.data) - self.pos} trailing byte(s)")
