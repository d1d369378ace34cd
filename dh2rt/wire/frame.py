"""The hormone frame: the versioned, compact binary unit every link carries (sans-IO).

A frame is what one module sends through one connector: a hormone, a keep-alive beacon or a
hello. Its bytes are the same on every medium (CAN segments them, serial wraps them in COBS
and a CRC). Layout, byte by byte (``w`` = connector width in bits, 3 for CONRO)::

    byte 0      VV KK SSSS   version (2 bits, = 3), kind (2 bits), sender connector (4 bits)
    HORMONE (kind 0) and ROUTED (kind 1):
    byte 1      hop count H (0..255)
    content     Vocabulary.encode_content: hormone index, then one byte per atom / varint
    path        H hops, each (sent_through, received_at) as two w-bit fields, MSB first,
                zero-padded to a whole byte
    ROUTED only:
    route len   R (0..255), then R w-bit connector fields, zero-padded to a whole byte
    KEEPALIVE (kind 2):
    byte 1      sequence number (0..255, wraps)
    HELLO (kind 3):
    bytes 1..6  the program digest (blake2b, 6 bytes): mismatched programs are detected

The sender connector is the ``remote`` of the :class:`~dh2rt.hormone.Arrival` the receiver
builds. Nothing here names a module. A caterpillar hormone ``X(A)`` with an empty path is
4 bytes: header, hop count 0, hormone index, atom index.

Decoding raises only :class:`~dh2rt.errors.DecodeError` (or a subclass); encoding raises
:class:`FrameEncodeError` for a frame that breaks a wire limit, or ``HormoneError`` for a
hormone that breaks its declaration.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import NamedTuple

from dh2rt.errors import CodecError, DecodeError, FrameEncodeError
from dh2rt.hormone import MAX_HOPS_LIMIT, Hormone, Vocabulary

#: The wire format version carried in every frame's first byte. 3 since CAN segment trains
#: carry a tag and a CRC-32 and integer arguments must be in their shortest form (1 before;
#: 2 is the transfer family's; docs/link-layer.md).
WIRE_VERSION = 3
#: The same two bits of a transfer frame (:mod:`dh2rt.wire.transfer`): a second frame family.
TRANSFER_FAMILY = 2
#: The same two bits of a control frame (:mod:`dh2rt.wire.operator`): the operator's family.
CONTROL_FAMILY = 0
#: Bytes of program digest a hello carries.
HELLO_DIGEST_BYTES = 6
#: The digest of a peer that runs no program: a programming cable's Hello (dh2rt flash). A
#: module neither links to it nor refuses it (docs/flashing.md).
NO_PROGRAM = bytes(HELLO_DIGEST_BYTES)
#: Largest connector index the 4-bit sender field can carry.
MAX_CONNECTORS = 15


class FrameKind(IntEnum):
    """The two-bit frame kind in byte 0 (also the top bits of a CAN arbitration id)."""

    HORMONE = 0
    ROUTED = 1
    KEEPALIVE = 2
    HELLO = 3


@dataclass(frozen=True, slots=True)
class KeepAlive:
    """A liveness beacon; ``seq`` (0..255) lets a receiver estimate loss."""

    seq: int = 0


@dataclass(frozen=True, slots=True)
class Hello:
    """Announces the sender's program digest (see :func:`program_digest`) and, from a module
    that runs a versioned program, its version (``dh2rt.wire.transfer.encode_hello``: a LEB128
    varint after the digest; None: the 7-byte Hello without one)."""

    digest: bytes
    version: int | None = None


#: Anything a link carries. A hormone is sent as-is (its path as sent).
Frame = Hormone | KeepAlive | Hello


class Decoded(NamedTuple):
    """A decoded frame and the connector its sender sent it through."""

    sender: int
    frame: Frame


def program_digest(program: bytes) -> bytes:
    """The 6-byte digest a hello carries for a program image or source text."""
    return hashlib.blake2b(program, digest_size=HELLO_DIGEST_BYTES).digest()


def frame_kind(payload: bytes) -> FrameKind:
    """The kind of an encoded frame, read from its first byte without decoding the rest."""
    if not payload:
        raise DecodeError("frame: no bytes")
    return FrameKind((payload[0] >> 4) & 0x3)


class FrameCodec:
    """Encodes and decodes frames for one program (vocabulary) and one connector count.

    Both ends of a link run the same program and profile, so both build equal codecs.
    """

    __slots__ = ("connector_bits", "connector_count", "vocabulary")

    def __init__(self, vocabulary: Vocabulary, connector_count: int = 4) -> None:
        if not 1 <= connector_count <= MAX_CONNECTORS:
            raise FrameEncodeError(f"connector_count {connector_count} is outside 1..{MAX_CONNECTORS}")
        self.vocabulary = vocabulary
        self.connector_count = connector_count
        #: Bits per connector index in paths and routes (3 for CONRO's 4 connectors).
        self.connector_bits = connector_count.bit_length()

    # -- encoding ---------------------------------------------------------------------------

    def encode(self, sender: int, frame: Frame) -> bytes:
        """Encode ``frame`` as sent through connector ``sender``."""
        self._check_connector("sender connector", sender)
        if isinstance(frame, Hormone):
            kind = FrameKind.HORMONE if frame.route is None else FrameKind.ROUTED
            content = self.vocabulary.encode_content(frame)  # checks declaration and hop limit
            out = bytearray((_header(kind, sender), len(frame.path)))
            out += content
            flat: list[int] = []
            for sent, received in frame.path:
                flat.append(sent)
                flat.append(received)
            for value in flat:
                self._check_connector("path connector", value)
            out += _pack(flat, self.connector_bits)
            if frame.route is not None:
                if len(frame.route) > MAX_HOPS_LIMIT:
                    raise FrameEncodeError(
                        f"hormone {frame.name}: route of {len(frame.route)} hops exceeds {MAX_HOPS_LIMIT}"
                    )
                for value in frame.route:
                    self._check_connector("route connector", value)
                out.append(len(frame.route))
                out += _pack(frame.route, self.connector_bits)
            return bytes(out)
        if isinstance(frame, KeepAlive):
            if not 0 <= frame.seq <= 0xFF:
                raise FrameEncodeError(f"keep-alive seq {frame.seq} is outside 0..255")
            return bytes((_header(FrameKind.KEEPALIVE, sender), frame.seq))
        if isinstance(frame, Hello):
            if len(frame.digest) != HELLO_DIGEST_BYTES:
                raise FrameEncodeError(f"hello digest is {len(frame.digest)} bytes; it must be {HELLO_DIGEST_BYTES}")
            if frame.version is not None:
                return encode_hello(sender, frame.digest, frame.version)
            return bytes((_header(FrameKind.HELLO, sender),)) + bytes(frame.digest)
        raise FrameEncodeError(f"not a frame: {frame!r}")

    def _check_connector(self, what: str, value: int) -> None:
        if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= self.connector_count:
            raise FrameEncodeError(f"{what} {value!r} is outside 1..{self.connector_count}")

    # -- decoding ---------------------------------------------------------------------------

    def decode(self, data: bytes) -> Decoded:
        """Decode one whole frame; raises CodecError for anything but exactly one valid frame."""
        try:
            return self._decode(bytes(data))
        except CodecError:
            raise
        except (IndexError, ValueError) as exc:  # defensive: garbage must only raise CodecError
            raise DecodeError(f"frame: malformed ({exc})") from None

    def _decode(self, data: bytes) -> Decoded:
        if not data:
            raise DecodeError("frame: no bytes")
        head = data[0]
        version = head >> 6
        if version != WIRE_VERSION:
            raise DecodeError(f"frame: wire version {version}, expected {WIRE_VERSION}")
        kind = (head >> 4) & 0x3  # a FrameKind, compared as an int (the enum's call is slow)
        sender = head & 0x0F
        if not 1 <= sender <= self.connector_count:
            raise DecodeError(f"frame: sender connector {sender} is outside 1..{self.connector_count}")
        if kind == FrameKind.KEEPALIVE:
            if len(data) != 2:
                raise DecodeError(f"keep-alive frame: {len(data)} bytes, expected 2")
            return Decoded(sender, KeepAlive(data[1]))
        if kind == FrameKind.HELLO:
            if len(data) == 1 + HELLO_DIGEST_BYTES:
                return Decoded(sender, Hello(data[1:]))
            if not 1 + HELLO_DIGEST_BYTES < len(data) <= 1 + HELLO_DIGEST_BYTES + 5:
                raise DecodeError(f"hello frame: {len(data)} bytes, expected 7 (or 8..12 with a version)")
            hello = decode_hello(data)
            return Decoded(sender, Hello(hello.digest, hello.version))
        if len(data) < 2:
            raise DecodeError("hormone frame: truncated before the hop count")
        hops = data[1]
        name, args, pos = self.vocabulary.decode_content(data, 2)
        flat, pos = self._unpack(data, pos, 2 * hops, "path")
        path = tuple(zip(flat[::2], flat[1::2], strict=True)) if flat else ()
        route: tuple[int, ...] | None = None
        if kind == FrameKind.ROUTED:
            if pos >= len(data):
                raise DecodeError(f"hormone frame {name}: truncated before the route length")
            count = data[pos]
            route, pos = self._unpack(data, pos + 1, count, "route")
        if pos != len(data):
            raise DecodeError(f"hormone frame {name}: {len(data) - pos} trailing byte(s)")
        return Decoded(sender, Hormone(name, args, path, route))

    def _unpack(self, data: bytes, pos: int, count: int, what: str) -> tuple[tuple[int, ...], int]:
        if not count:
            return (), pos
        bits = self.connector_bits
        nbytes = (count * bits + 7) // 8
        if pos + nbytes > len(data):
            raise DecodeError(f"frame: {what} truncated ({count} connectors need {nbytes} bytes)")
        acc = int.from_bytes(data[pos : pos + nbytes], "big")
        pad = nbytes * 8 - count * bits
        if acc & ((1 << pad) - 1):
            raise DecodeError(f"frame: {what} padding bits are not zero")
        acc >>= pad
        mask = (1 << bits) - 1
        values = tuple((acc >> (bits * (count - 1 - i))) & mask for i in range(count))
        for v in values:
            if not 1 <= v <= self.connector_count:
                raise DecodeError(f"frame: {what} connector {v} is outside 1..{self.connector_count}")
        return values, pos + nbytes


def _header(kind: FrameKind, sender: int) -> int:
    return (WIRE_VERSION << 6) | (int(kind) << 4) | sender


def _pack(values: Sequence[int], bits: int) -> bytes:
    """Pack ``values`` as ``bits``-wide fields, MSB first, zero-padded to whole bytes."""
    if not values:
        return b""
    acc = 0
    for v in values:
        acc = (acc << bits) | v
    nbytes = (len(values) * bits + 7) // 8
    acc <<= nbytes * 8 - len(values) * bits
    return acc.to_bytes(nbytes, "big")


# ---------------------------------------------------------------- the Hello with a version

#: Largest program version a Hello states.
_U32 = 0xFFFFFFFF


class VersionedHello(NamedTuple):
    """A decoded Hello: sender connector, program digest, program version (None: a 7-byte
    Hello, which states none)."""

    sender: int
    digest: bytes
    version: int | None


def encode_hello(sender: int, digest: bytes, version: int) -> bytes:
    """A Hello (link frame kind 3) that also states the program version: the 7-byte hello
    and the version as an unsigned LEB128 varint (8 bytes for versions below 128)."""
    _check_range("sender connector", sender, 1, MAX_CONNECTORS)
    _check_range("version", version, 0, _U32)
    if len(digest) != HELLO_DIGEST_BYTES:
        raise FrameEncodeError(f"hello digest is {len(digest)} bytes; it must be {HELLO_DIGEST_BYTES}")
    head = (WIRE_VERSION << 6) | (int(FrameKind.HELLO) << 4) | sender
    return bytes((head,)) + bytes(digest) + _varint(version)


def decode_hello(data: bytes) -> VersionedHello:
    """Decode a Hello of 7 bytes (no version) or 8..12 (with one); DecodeError otherwise."""
    data = bytes(data)
    if len(data) < 1 + HELLO_DIGEST_BYTES:
        raise DecodeError(f"hello frame: {len(data)} bytes, at least {1 + HELLO_DIGEST_BYTES} expected")
    head = data[0]
    if head >> 6 != WIRE_VERSION or (head >> 4) & 3 != FrameKind.HELLO or not head & 0x0F:
        raise DecodeError(f"hello frame: header {head:#04x} is not a hello")
    digest = data[1 : 1 + HELLO_DIGEST_BYTES]
    if len(data) == 1 + HELLO_DIGEST_BYTES:
        return VersionedHello(head & 0x0F, digest, None)
    return VersionedHello(head & 0x0F, digest, _read_varint(data[1 + HELLO_DIGEST_BYTES :]))


def _check_range(name: str, value: int, low: int, high: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise FrameEncodeError(f"{name} {value!r} is outside {low}..{high}")


def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        low, value = value & 0x7F, value >> 7
        out.append(low | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _read_varint(data: bytes) -> int:
    """A canonical unsigned LEB128 u32 filling ``data`` exactly."""
    value = 0
    for i, byte in enumerate(data):
        value |= (byte & 0x7F) << (7 * i)
        if not byte & 0x80:
            if i != len(data) - 1:
                raise DecodeError(f"hello frame: {len(data) - i - 1} trailing byte(s) after the version")
            if byte == 0 and i > 0:
                raise DecodeError("hello frame: the version is not in its shortest form")
            if value > _U32:
                raise DecodeError(f"hello frame: version {value} exceeds 32 bits")
            return value
    raise DecodeError("hello frame: the version is cut short")
