"""The overhead tracker's datagram (dh2rt.wire.tracker): round trips, one encoding for each
datagram, every malformed datagram refused naming its field, garbage refused only with the
codec's own error."""

from __future__ import annotations

import struct
import zlib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dh2rt.errors import DecodeError, EncodeError, TrackerDatagramError
from dh2rt.wire.tracker import (
    HEADER_BYTES,
    MAX_DATAGRAM,
    MAX_MARKERS,
    MarkerPose,
    TrackerDatagram,
    datagram,
    decode,
    encode,
)

ONE = TrackerDatagram(7, 1_700_000_000_123_456, (MarkerPose(3, 120.5, -44.1, 271.25, 0.3),))


def resealed(body: bytes) -> bytes:
    """``body`` (a datagram without its CRC) with a CRC that matches: a field check, not the CRC's."""
    return body + struct.pack(">I", zlib.crc32(body))


def test_round_trip_keeps_every_field() -> None:
    data = encode(ONE)
    assert len(data) == HEADER_BYTES + 14 + 4
    assert decode(data) == ONE


def test_values_round_to_the_wire_units_and_markers_sort_by_id() -> None:
    sent = TrackerDatagram(0, 0, (MarkerPose(9, 1.26, -1.24, 359.996, 1e9), MarkerPose(2, 0.0, 0.0, -90.0, 0.04)))
    got = decode(encode(sent))
    assert [m.marker for m in got.markers] == [2, 9]
    assert got.markers[0] == MarkerPose(2, 0.0, 0.0, 270.0, 0.0)
    assert got.markers[1] == MarkerPose(9, 1.3, -1.2, 0.0, 6553.5)  # 359.996 rounds to 360 = 0; error saturates
    assert datagram(0, 0, sent.markers) == got


def test_largest_datagram_fits_one_ethernet_frame() -> None:
    full = TrackerDatagram(2**32 - 1, 2**64 - 1, tuple(MarkerPose(m, -1e6, 1e6, 0.0, 0.0) for m in range(MAX_MARKERS)))
    assert len(encode(full)) == MAX_DATAGRAM <= 1472
    assert decode(encode(full)) == full


@pytest.mark.parametrize(
    ("datagram_", "says"),
    [
        (TrackerDatagram(-1, 0, ()), "sequence"),
        (TrackerDatagram(2**32, 0, ()), "sequence"),
        (TrackerDatagram(0, -5, ()), "capture time"),
        (TrackerDatagram(0, 0, (MarkerPose(70000, 0, 0, 0, 0),)), "marker id"),
        (TrackerDatagram(0, 0, (MarkerPose(1, float("nan"), 0, 0, 0),)), "marker 1 x"),
        (TrackerDatagram(0, 0, (MarkerPose(1, 0, 3e9, 0, 0),)), "marker 1 y"),
        (TrackerDatagram(0, 0, (MarkerPose(1, 0, 0, float("inf"), 0),)), "marker 1 heading"),
        (TrackerDatagram(0, 0, (MarkerPose(1, 0, 0, 0, -1.0),)), "negative"),
        (TrackerDatagram(0, 0, (MarkerPose(1, 0, 0, 0, 0), MarkerPose(1, 5, 5, 0, 0))), "appears twice"),
        (TrackerDatagram(0, 0, tuple(MarkerPose(m, 0, 0, 0, 0) for m in range(MAX_MARKERS + 1))), "at most"),
    ],
)
def test_what_the_wire_cannot_carry_is_an_encode_error(datagram_: TrackerDatagram, says: str) -> None:
    with pytest.raises(EncodeError, match=says):
        encode(datagram_)


def _header(count: int = 1, magic: bytes = b"DH2T", version: int = 1) -> bytes:
    return struct.pack(">4sBBIQ", magic, version, count, 7, 99)


def _marker(marker: int = 3, heading: int = 100) -> bytes:
    return struct.pack(">HiiHH", marker, 10, -10, heading, 3)


@pytest.mark.parametrize(
    ("data", "field"),
    [
        (b"", "length"),
        (b"DH2T\x01", "length"),
        (resealed(_header(magic=b"DH2X") + _marker()), "magic"),
        (resealed(_header(version=2) + _marker()), "version"),
        (resealed(_header(count=MAX_MARKERS + 1)), "marker count"),
        (resealed(_header(count=2) + _marker()), "length"),
        (resealed(_header(count=0) + _marker()), "length"),
        (_header() + _marker() + b"\0\0\0\0", "crc"),
        (resealed(_header(count=2) + _marker(5) + _marker(4)), "marker id"),
        (resealed(_header(count=2) + _marker(5) + _marker(5)), "marker id"),
        (resealed(_header() + _marker(heading=36000)), "heading"),
    ],
)
def test_each_malformed_datagram_names_its_field(data: bytes, field: str) -> None:
    with pytest.raises(TrackerDatagramError) as caught:
        decode(data)
    assert caught.value.field == field
    assert f"tracker datagram, {field} (byte {caught.value.offset})" in str(caught.value)
    assert isinstance(caught.value, DecodeError) and isinstance(caught.value, ValueError)


def test_every_single_bit_error_is_caught() -> None:
    data = encode(TrackerDatagram(1, 2, (MarkerPose(0, 1, 2, 3, 4), MarkerPose(1, -1, -2, 300, 0))))
    for bit in range(len(data) * 8):
        flipped = bytearray(data)
        flipped[bit // 8] ^= 1 << (bit % 8)
        with pytest.raises(TrackerDatagramError):
            decode(bytes(flipped))


coordinates = st.floats(min_value=-200_000_000.0, max_value=200_000_000.0, allow_nan=False)
poses = st.builds(
    MarkerPose,
    marker=st.integers(0, 0xFFFF),
    x_mm=coordinates,
    y_mm=coordinates,
    heading_deg=st.floats(-1e6, 1e6),
    error_mm=st.floats(0.0, 1e5),
)
datagrams = st.builds(
    TrackerDatagram,
    sequence=st.integers(0, 2**32 - 1),
    captured_us=st.integers(0, 2**64 - 1),
    markers=st.lists(poses, max_size=12, unique_by=lambda m: m.marker).map(tuple),
)


@settings(max_examples=300, deadline=None)
@given(datagrams)
def test_round_trip_is_exact_on_the_wire(sent: TrackerDatagram) -> None:
    data = encode(sent)
    got = decode(data)
    assert encode(got) == data  # one encoding for each datagram
    assert got.sequence == sent.sequence and got.captured_us == sent.captured_us
    for before, after in zip(sorted(sent.markers, key=lambda m: m.marker), got.markers, strict=True):
        assert before.marker == after.marker
        assert abs(before.x_mm - after.x_mm) <= 0.05 + 1e-6 and abs(before.y_mm - after.y_mm) <= 0.05 + 1e-6
        assert abs((before.heading_deg - after.heading_deg + 180) % 360 - 180) <= 0.005 + 1e-6
        assert 0 <= after.heading_deg < 360


def _one_byte_changed(wire: bytes) -> st.SearchStrategy[bytes]:
    return st.tuples(st.integers(0, len(wire) - 1), st.integers(0, 255)).map(
        lambda at: wire[: at[0]] + bytes((at[1],)) + wire[at[0] + 1 :]
    )


@settings(max_examples=500, deadline=None)
@given(st.binary(max_size=200) | datagrams.map(encode).flatmap(_one_byte_changed))
def test_garbage_raises_only_the_codec_error(data: bytes) -> None:
    try:
        got = decode(data)
    except TrackerDatagramError:
        return
    assert encode(got) == data


@settings(max_examples=200, deadline=None)
@given(datagrams.filter(lambda d: len(d.markers) > 0), st.data())
def test_a_cut_or_lengthened_datagram_is_refused(sent: TrackerDatagram, data: st.DataObject) -> None:
    wire = encode(sent)
    cut = data.draw(st.integers(0, len(wire) - 1))
    with pytest.raises(TrackerDatagramError):
        decode(wire[:cut])
    with pytest.raises(TrackerDatagramError):
        decode(wire + data.draw(st.binary(min_size=1, max_size=20)))


def test_a_datagram_finds_its_markers() -> None:
    assert ONE.marker(3) == ONE.markers[0] and ONE.marker(4) is None
