"""The overhead tracker's datagram: the poses of the markers one camera frame showed (sans-IO).

``dh2rt tracker`` (tools/tracker.py) broadcasts one datagram per frame over UDP; each module's
:class:`firmware.tracker_feed.TrackerFeed` decodes it. Layout, big-endian, byte by byte
(docs/tracker.md draws it too)::

    0   4   magic b"DH2T"
    4   1   version (1)
    5   1   marker count n (0..MAX_MARKERS: a datagram fits one Ethernet frame)
    6   4   frame sequence number (u32, wraps)
    10  8   capture time, microseconds since the Unix epoch on the tracker's clock (u64)
    18  14n markers, ids strictly ascending, each:
            2  marker id (u16)
            4  x, tenths of a millimetre in the arena frame (i32)
            4  y, likewise (i32)
            2  heading, hundredths of a degree counter-clockwise from the arena's +x, 0..35999
            2  fit error, tenths of a millimetre (u16; 65535: that much or worse)
    ..  4   CRC-32 (zlib's) of every byte before it

Decoding is strict: a datagram has exactly one encoding, so anything else (a foreign or
truncated datagram, a count that disagrees with the length, ids out of order or repeated, a
heading of 360 degrees, a failed CRC) raises :class:`~dh2rt.errors.TrackerDatagramError`
naming the field. Encoding rounds to the wire's units and raises
:class:`~dh2rt.errors.EncodeError` for what the wire cannot carry.
"""

from __future__ import annotations

import itertools
import math
import struct
import zlib
from collections.abc import Iterable
from dataclasses import dataclass

from dh2rt.errors import EncodeError, TrackerDatagramError

MAGIC = b"DH2T"
VERSION = 1
#: The most markers one datagram carries: 22 + 14 * 100 = 1422 bytes, within one UDP datagram
#: on Ethernet (1472) with no IP fragmentation.
MAX_MARKERS = 100
#: The tracker's UDP port unless told otherwise (``dh2rt tracker --publish``, TrackerFeed's bind).
DEFAULT_PORT = 47328

_HEADER = struct.Struct(">4sBBIQ")
_MARKER = struct.Struct(">HiiHH")
_CRC = struct.Struct(">I")
HEADER_BYTES = _HEADER.size
MARKER_BYTES = _MARKER.size
MAX_DATAGRAM = HEADER_BYTES + MAX_MARKERS * MARKER_BYTES + _CRC.size

_TENTHS_PER_MM = 10
_CENTIDEGREES = 36000
_MAX_ERROR = 0xFFFF
_I32 = (-(2**31), 2**31 - 1)


@dataclass(frozen=True, slots=True)
class MarkerPose:
    """One marker on the arena's floor: where (mm), which way (degrees, CCW from +x, 0..360)
    and how well the detection fit the marker's known size (``error_mm``)."""

    marker: int
    x_mm: float
    y_mm: float
    heading_deg: float
    error_mm: float


@dataclass(frozen=True, slots=True)
class TrackerDatagram:
    """One camera frame's detections: its sequence number, when it was captured, the markers."""

    sequence: int
    captured_us: int
    markers: tuple[MarkerPose, ...]

    def marker(self, marker: int) -> MarkerPose | None:
        """The pose of ``marker`` in this frame, or None if the frame did not show it."""
        return next((m for m in self.markers if m.marker == marker), None)


def _whole(value: int, field: str, bits: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < 1 << bits:
        raise EncodeError(f"tracker datagram: {field} {value!r} is not a {bits}-bit unsigned value")
    return value


def _units(value: float, per_unit: int, field: str) -> int:
    if not math.isfinite(value):
        raise EncodeError(f"tracker datagram: {field} {value!r} is not a finite number")
    return round(value * per_unit)


def _encode_marker(pose: MarkerPose) -> bytes:
    what = f"marker {pose.marker!r}"
    _whole(pose.marker, "marker id", 16)
    x, y = (_units(v, _TENTHS_PER_MM, f"{what} {name}") for v, name in ((pose.x_mm, "x"), (pose.y_mm, "y")))
    for name, value in (("x", x), ("y", y)):
        if not _I32[0] <= value <= _I32[1]:
            raise EncodeError(f"tracker datagram: {what} {name} {value / 10:g} mm is beyond the wire's ±214 km")
    heading = _units(pose.heading_deg, 100, f"{what} heading") % _CENTIDEGREES
    error = _units(pose.error_mm, _TENTHS_PER_MM, f"{what} error")
    if error < 0:
        raise EncodeError(f"tracker datagram: {what} error {pose.error_mm!r} mm is negative")
    return _MARKER.pack(pose.marker, x, y, heading, min(error, _MAX_ERROR))


def encode(datagram: TrackerDatagram) -> bytes:
    """The datagram's bytes; markers go out in ascending id order whatever order they came in."""
    _whole(datagram.sequence, "sequence", 32)
    _whole(datagram.captured_us, "capture time", 64)
    markers = sorted(datagram.markers, key=lambda m: m.marker)
    if len(markers) > MAX_MARKERS:
        raise EncodeError(f"tracker datagram: {len(markers)} markers; at most {MAX_MARKERS} fit one datagram")
    for before, after in itertools.pairwise(markers):
        if before.marker == after.marker:
            raise EncodeError(f"tracker datagram: marker {after.marker} appears twice")
    body = _HEADER.pack(MAGIC, VERSION, len(markers), datagram.sequence, datagram.captured_us)
    body += b"".join(_encode_marker(m) for m in markers)
    return body + _CRC.pack(zlib.crc32(body))


def _fail(field: str, offset: int, message: str) -> TrackerDatagramError:
    return TrackerDatagramError(field, offset, message)


def decode(data: bytes) -> TrackerDatagram:
    """One datagram from its bytes; raises TrackerDatagramError (naming the field) otherwise."""
    data = bytes(data)
    if len(data) < HEADER_BYTES + _CRC.size:
        raise _fail("length", 0, f"{len(data)} bytes; a datagram has at least {HEADER_BYTES + _CRC.size}")
    magic, version, count, sequence, captured_us = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise _fail("magic", 0, f"{magic!r} is not {MAGIC!r}: not a tracker datagram")
    if version != VERSION:
        raise _fail("version", 4, f"version {version}; this reader knows version {VERSION}")
    if count > MAX_MARKERS:
        raise _fail("marker count", 5, f"{count} markers; at most {MAX_MARKERS}")
    expected = HEADER_BYTES + count * MARKER_BYTES + _CRC.size
    if len(data) != expected:
        raise _fail("length", 0, f"{len(data)} bytes, but a datagram of {count} markers has {expected}")
    (crc,) = _CRC.unpack_from(data, expected - _CRC.size)
    if crc != zlib.crc32(data[: expected - _CRC.size]):
        raise _fail("crc", expected - _CRC.size, "the CRC-32 does not match the bytes before it")
    markers: list[MarkerPose] = []
    for k in range(count):
        offset = HEADER_BYTES + k * MARKER_BYTES
        marker, x, y, heading, error = _MARKER.unpack_from(data, offset)
        if markers and marker <= markers[-1].marker:
            raise _fail("marker id", offset, f"marker {marker} after marker {markers[-1].marker}: ids must ascend")
        if heading >= _CENTIDEGREES:
            raise _fail("heading", offset + 10, f"marker {marker}: heading {heading / 100:g} degrees is not below 360")
        markers.append(
            MarkerPose(marker, x / _TENTHS_PER_MM, y / _TENTHS_PER_MM, heading / 100, error / _TENTHS_PER_MM)
        )
    return TrackerDatagram(sequence, captured_us, tuple(markers))


def datagram(sequence: int, captured_us: int, markers: Iterable[MarkerPose]) -> TrackerDatagram:
    """A datagram as the wire will carry it: values rounded to its units (what decoding gives)."""
    return decode(encode(TrackerDatagram(sequence, captured_us, tuple(markers))))
