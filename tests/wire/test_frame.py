"""The frame codec: sizes, round trips, and garbage that only ever raises CodecError."""

from __future__ import annotations

import contextlib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dh2rt.errors import CodecError, DecodeError, FrameEncodeError, HormoneError
from dh2rt.hormone import Hormone, HormoneSpec, ParamSpec, Vocabulary
from dh2rt.wire.frame import (
    FrameCodec,
    FrameKind,
    Hello,
    KeepAlive,
    frame_kind,
    program_digest,
)

VOCAB = Vocabulary(
    [
        HormoneSpec(0, "X", (ParamSpec("a", ("A", "B", "C")),)),
        HormoneSpec(1, "Go", ()),
        HormoneSpec(2, "Q", (ParamSpec("n", None), ParamSpec("d", ("up", "down")), ParamSpec("m", None))),
    ]
)
CODEC = FrameCodec(VOCAB, 4)

connector = st.integers(1, 4)
path = st.lists(st.tuples(connector, connector), max_size=255).map(tuple)
route = st.none() | st.lists(connector, max_size=255).map(tuple)
i32 = st.integers(-(2**31), 2**31 - 1)
hormones = st.one_of(
    st.builds(lambda a, p, r: Hormone("X", (a,), p, r), st.sampled_from(["A", "B", "C"]), path, route),
    st.builds(lambda p, r: Hormone("Go", (), p, r), path, route),
    st.builds(
        lambda n, d, m, p, r: Hormone("Q", (n, d, m), p, r),
        i32,
        st.sampled_from(["up", "down"]),
        i32,
        path,
        route,
    ),
)
frames = st.one_of(
    hormones,
    st.builds(KeepAlive, st.integers(0, 255)),
    st.builds(Hello, st.binary(min_size=6, max_size=6)),
)


def test_caterpillar_frame_is_four_bytes() -> None:
    data = CODEC.encode(2, Hormone("X", ("A",)))
    assert data == bytes([0xC2, 0x00, 0x00, 0x00])  # v3, hormone, sender 2 | 0 hops | X | A
    assert len(data) <= 8  # one classic CAN frame


def test_header_and_path_layout() -> None:
    h = Hormone("X", ("B",), ((1, 2), (3, 4)), (2, 1))
    data = CODEC.encode(3, h)
    assert data[0] == 0xC0 | (FrameKind.ROUTED << 4) | 3
    assert data[1] == 2  # hops
    assert data[2:4] == b"\x00\x01"  # content: X, B
    # 3-bit fields 1,2,3,4 = 001 010 011 100 -> 0010 1001 1100 (+ 4 zero bits)
    assert data[4:6] == bytes([0b00101001, 0b11000000])
    assert data[6] == 2 and data[7] == 0b01000100  # route 2, 1 -> 010 001 + 00
    assert CODEC.decode(data) == (3, h)
    assert frame_kind(data) is FrameKind.ROUTED


def test_keepalive_and_hello() -> None:
    assert CODEC.encode(1, KeepAlive(9)) == bytes([0xE1, 9])
    digest = program_digest(b"some program")
    assert len(digest) == 6 and CODEC.decode(CODEC.encode(4, Hello(digest))) == (4, Hello(digest))


@given(frames, connector)
@settings(max_examples=400)
def test_round_trip(frame: Hormone | KeepAlive | Hello, sender: int) -> None:
    assert CODEC.decode(CODEC.encode(sender, frame)) == (sender, frame)


@given(st.binary(max_size=300))
@settings(max_examples=1000)
def test_garbage_raises_only_codec_error(data: bytes) -> None:
    try:
        sender, frame = CODEC.decode(data)
    except CodecError:
        return
    # Whatever does decode is a valid frame that re-encodes to the very same bytes.
    assert CODEC.encode(sender, frame) == data


def test_an_over_long_varint_is_refused() -> None:
    """Issue 27: ``c1 00 02 8a 00 00 00`` read as Q(5, up, 0) although 5 is ``0a``: an
    argument had two encodings. Only the shortest is accepted, so every accepted frame is
    canonical and re-encodes to itself."""
    assert CODEC.encode(1, Hormone("Q", (5, "up", 0))) == bytes.fromhex("c100020a0000")
    for padded in ("8a00", "8a8000", "8a808000", "8a80808000", "ff80808000"):
        with pytest.raises(DecodeError, match="shortest form"):
            CODEC.decode(bytes.fromhex("c10002" + padded + "0000"))


@given(i32, i32)
def test_integers_round_trip_in_their_shortest_form(n: int, m: int) -> None:
    data = CODEC.encode(1, Hormone("Q", (n, "down", m)))
    assert CODEC.decode(data) == (1, Hormone("Q", (n, "down", m)))
    assert len(data) == 3 + _shortest(n) + 1 + _shortest(m)


def _shortest(n: int) -> int:
    """Bytes of the shortest LEB128 of ``n`` zig-zagged: 7 bits a byte."""
    zigzag = 2 * n if n >= 0 else -2 * n - 1
    return max(1, -(-zigzag.bit_length() // 7))


#: Bytes that make varints end, continue, or end in a zero: what an over-long one is made of.
_tricky = st.lists(st.sampled_from([0x00, 0x01, 0x0A, 0x7F, 0x80, 0x8A, 0xFF]), min_size=1, max_size=12).map(bytes)


@given(st.binary(min_size=1, max_size=12) | _tricky)
@settings(max_examples=2000)
def test_every_accepted_content_re_encodes_to_itself(content: bytes) -> None:
    """Random bytes where Q's two integers and its atom go: whatever decodes is canonical."""
    data = b"\xc1\x00\x02" + content
    try:
        sender, frame = CODEC.decode(data)
    except CodecError:
        return
    assert CODEC.encode(sender, frame) == data


@given(hormones, connector, st.data())
def test_corrupted_frames_raise_only_codec_error(h: Hormone, sender: int, data: st.DataObject) -> None:
    raw = bytearray(CODEC.encode(sender, h))
    cut = data.draw(st.integers(0, len(raw) - 1))
    for broken in (bytes(raw[:cut]), bytes(raw) + b"\x00"):
        with pytest.raises(CodecError):
            CODEC.decode(broken)
    raw[cut] ^= 1 << data.draw(st.integers(0, 7))
    with contextlib.suppress(CodecError):
        CODEC.decode(bytes(raw))


@pytest.mark.parametrize(
    ("sender", "frame", "message"),
    [
        (0, Hormone("Go"), "sender connector 0"),
        (5, Hormone("Go"), "sender connector 5"),
        (1, Hormone("Go", (), ((1, 9),)), "path connector 9"),
        (1, Hormone("Go", (), (), (0,)), "route connector 0"),
        (1, Hormone("Go", (), (), (1,) * 256), "route of 256 hops"),
        (1, KeepAlive(256), "seq 256"),
        (1, Hello(b"abc"), "digest is 3 bytes"),
    ],
)
def test_encode_errors_name_the_field(sender: int, frame: Hormone | KeepAlive | Hello, message: str) -> None:
    with pytest.raises(FrameEncodeError, match=message):
        CODEC.encode(sender, frame)


def test_bad_hormones_raise_hormone_error() -> None:
    with pytest.raises(HormoneError, match="unknown hormone"):
        CODEC.encode(1, Hormone("Nope"))
    with pytest.raises(HormoneError, match="exceeds 255"):
        CODEC.encode(1, Hormone("Go", (), ((1, 2),) * 256))


def test_decode_errors_are_specific() -> None:
    with pytest.raises(CodecError, match="wire version 0"):
        CODEC.decode(b"\x02\x00\x01")
    with pytest.raises(CodecError, match="sender connector 7"):
        CODEC.decode(b"\xc7\x00\x01")
    with pytest.raises(CodecError, match="trailing"):
        CODEC.decode(b"\xc1\x00\x01\x00")
    with pytest.raises(CodecError, match="padding"):
        CODEC.decode(b"\xc1\x01\x01\x49\x01")  # hop (2, 2) = 010 010 then nonzero pad bits
    with pytest.raises(CodecError, match="wire version 1, expected 3"):
        CODEC.decode(b"\x41\x00\x01")  # version 1: segment trains without a check


def test_connector_width_follows_the_profile() -> None:
    wide = FrameCodec(VOCAB, 15)
    h = Hormone("Go", (), ((15, 1), (7, 12)))
    assert wide.connector_bits == 4
    assert wide.decode(wide.encode(15, h)) == (15, h)
    with pytest.raises(ValueError, match="connector_count 16"):
        FrameCodec(VOCAB, 16)
