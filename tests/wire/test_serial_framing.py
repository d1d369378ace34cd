"""COBS + CRC-32 serial framing: vectors, round trips, chunking independence, resync, and a
link layer that no single-bit error, inserted or deleted byte fools (fixed frames and random
streams)."""

from __future__ import annotations

import binascii

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dh2rt.errors import FrameCorrupted
from dh2rt.hormone import Hormone, HormoneSpec, ParamSpec, Vocabulary
from dh2rt.wire.frame import FrameCodec
from dh2rt.wire.serial_framing import (
    FRAMING_VERSION,
    MAX_PAYLOAD,
    SerialDecoder,
    cobs_decode,
    cobs_encode,
    decode_serial,
    encode_serial,
    fcs32,
)

payloads = st.binary(min_size=1, max_size=MAX_PAYLOAD)


@pytest.mark.parametrize(
    ("raw", "encoded"),
    [
        (b"", b"\x01"),
        (b"\x00", b"\x01\x01"),
        (b"\x00\x00", b"\x01\x01\x01"),
        (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
        (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
        (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
        (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255)) + b"\x01"),
    ],
)
def test_cobs_vectors(raw: bytes, encoded: bytes) -> None:
    assert cobs_encode(raw) == encoded
    assert cobs_decode(encoded) == raw


def test_fcs_is_crc32() -> None:
    assert FRAMING_VERSION == 2  # version 1 was CRC-16/CCITT-FALSE: a new FCS is a new version
    assert fcs32(b"123456789") == 0xCBF43926  # the CRC-32/ISO-HDLC check value
    assert fcs32(b"abc") == binascii.crc32(b"abc")


def test_caterpillar_hop_is_at_most_12_bytes() -> None:
    codec = FrameCodec(Vocabulary([HormoneSpec(0, "X", (ParamSpec("a", ("A", "B")),))]), 4)
    wire = encode_serial(codec.encode(2, Hormone("X", ("A",))))
    assert len(wire) == 10 <= 12  # code byte, 4 payload bytes, 4 FCS bytes, delimiter
    assert wire.count(0) == 1 and wire.endswith(b"\x00")


@given(st.binary(max_size=1200))
@settings(max_examples=300)
def test_cobs_round_trip_has_no_zero(data: bytes) -> None:
    enc = cobs_encode(data)
    assert 0 not in enc
    assert len(enc) <= len(data) + 1 + len(data) // 254
    assert cobs_decode(enc) == data


@given(st.lists(payloads, max_size=8))
@settings(max_examples=200)
def test_whole_equals_byte_by_byte(frames: list[bytes]) -> None:
    stream = b"".join(encode_serial(p) for p in frames)
    whole = SerialDecoder()
    assert whole.feed(stream) == frames
    one = SerialDecoder()
    got: list[bytes] = []
    for i in range(len(stream)):
        got += one.feed(stream[i : i + 1])
    assert got == frames
    assert (one.frames, one.corrupted, one.dropped) == (whole.frames, 0, 0)


@given(st.binary(max_size=2000), st.lists(st.integers(1, 64), min_size=1, max_size=50))
@settings(max_examples=300)
def test_garbage_is_counted_and_chunking_never_matters(noise: bytes, cuts: list[int]) -> None:
    stream = noise + b"\x00" + encode_serial(b"hello")
    whole = SerialDecoder()
    expect = whole.feed(stream)
    assert expect[-1] == b"hello"  # resynchronised at the delimiter after the noise
    chunked = SerialDecoder()
    got: list[bytes] = []
    pos = 0
    i = 0
    while pos < len(stream):
        step = cuts[i % len(cuts)]
        got += chunked.feed(stream[pos : pos + step])
        pos += step
        i += 1
    assert got == expect
    assert (chunked.corrupted, chunked.dropped) == (whole.corrupted, whole.dropped)


def test_bad_frames_are_counted() -> None:
    dec = SerialDecoder()
    good = encode_serial(b"\x42\x00\x00\x00")
    flipped = bytearray(good)
    flipped[2] ^= 0x10
    assert dec.feed(bytes(flipped) + b"\x05\x01\x00" + b"\x00\x00" + good) == [b"\x42\x00\x00\x00"]
    assert (dec.frames, dec.corrupted, dec.dropped) == (1, 2, 0)


def test_oversize_frames_are_dropped_then_resync() -> None:
    dec = SerialDecoder(max_encoded=16)
    assert dec.feed(b"\x01" * 40) == []
    assert dec.pending == 0
    assert dec.feed(b"\x01\x00" + encode_serial(b"ok")) == [b"ok"]
    assert dec.dropped == 1


def test_decode_serial_errors() -> None:
    with pytest.raises(FrameCorrupted, match="too short"):
        decode_serial(cobs_encode(b"\x01"))
    with pytest.raises(FrameCorrupted, match="runs past"):
        decode_serial(b"\x09\x01")
    with pytest.raises(FrameCorrupted, match="CRC"):
        decode_serial(cobs_encode(b"abc\x00\x00"))
    with pytest.raises(ValueError, match="exceeds"):
        encode_serial(bytes(MAX_PAYLOAD + 1))


# ---------------------------------------------------------------- errors that must never pass

#: Payloads like the robot's: a caterpillar hop, a Hello, a keep-alive, a routed reply, and
#: payloads with zeros and 0xFF runs that exercise COBS's corner cases.
ERROR_PAYLOADS = [
    bytes.fromhex("42000000"),
    bytes.fromhex("43" + "a1" * 8),
    bytes.fromhex("4405"),
    bytes(range(1, 19)),
    b"\x00" * 6,
    b"\xff" * 20 + b"\x00" + b"\x01",
    bytes(range(256))[:60],
]


def _decode_line(line: bytes) -> list[bytes]:
    return SerialDecoder().feed(line)


def _line(payload: bytes) -> tuple[bytes, int, int]:
    """Idle line, the frame, idle line: the bytes, and where the frame (with its delimiter)
    starts and ends."""
    frame = encode_serial(payload)
    before, after = b"\x00\x00", b"\x00\x00"
    return before + frame + after, len(before), len(before) + len(frame)


@pytest.mark.parametrize("payload", ERROR_PAYLOADS, ids=lambda p: p.hex()[:12])
def test_no_single_bit_error_passes(payload: bytes) -> None:
    """Flip every bit of the frame and of the idle bytes around it: a flip inside the frame
    or its delimiter loses the frame; no flip ever yields a payload that was not sent. The
    delimiter flipped to 01 followed by idle 00 is the case CRC-16/CCITT-FALSE let through."""
    line, start, end = _line(payload)
    assert _decode_line(line) == [payload]
    for i in range(len(line)):
        for bit in range(8):
            bad = bytearray(line)
            bad[i] ^= 1 << bit
            got = _decode_line(bytes(bad))
            if start <= i < end:
                assert got == [], (i, bit, got)
            else:
                assert got in ([], [payload]), (i, bit, got)


@pytest.mark.parametrize("payload", ERROR_PAYLOADS, ids=lambda p: p.hex()[:12])
def test_no_inserted_or_deleted_byte_passes(payload: bytes) -> None:
    """Insert every byte value at every position from the delimiter before the frame to the
    delimiter after it, and delete every byte there: never a payload that was not sent."""
    line, start, end = _line(payload)
    for i in range(start - 1, end + 1):
        deleted = line[:i] + line[i + 1 :]
        assert _decode_line(deleted) in ([], [payload]), ("delete", i)
        for value in range(256):
            inserted = line[:i] + bytes([value]) + line[i:]
            got = _decode_line(inserted)
            assert all(p == payload for p in got), ("insert", i, value, got)


def test_random_noise_never_passes() -> None:
    """A residual-error estimate: 200,000 frames hit by 1 to 8 random byte errors each; the
    FCS must catch every one (a 32-bit FCS lets about one in 4.3e9 through)."""
    import random

    rng = random.Random(7)
    frames = [encode_serial(p) for p in ERROR_PAYLOADS]
    passed = 0
    for n in range(200_000):
        frame = bytearray(frames[n % len(frames)])
        for _ in range(rng.randint(1, 8)):
            frame[rng.randrange(len(frame) - 1)] = rng.randrange(1, 256)
        got = SerialDecoder().feed(bytes(frame))
        passed += bool(got) and got != [ERROR_PAYLOADS[n % len(frames)]]
    assert passed == 0


def _is_subsequence(got: list[bytes], sent: list[bytes]) -> bool:
    rest = iter(sent)
    return all(any(p == s for s in rest) for p in got)


@given(st.lists(st.binary(min_size=1, max_size=40), min_size=1, max_size=2))
@settings(max_examples=60, deadline=None)
def test_no_bit_error_or_byte_slip_fools_a_stream(sent: list[bytes]) -> None:
    """Random frames back to back on an idle line: after any single-bit error, any deleted
    byte or any inserted byte (a sample of values) anywhere, what comes out is some of what
    was sent, in order, and nothing else."""
    line = b"\x00" + b"".join(encode_serial(p) for p in sent) + b"\x00\x00"
    assert _decode_line(line) == sent
    for i in range(len(line)):
        for bit in range(8):
            bad = bytearray(line)
            bad[i] ^= 1 << bit
            assert _is_subsequence(_decode_line(bytes(bad)), sent), ("flip", i, bit)
        assert _is_subsequence(_decode_line(line[:i] + line[i + 1 :]), sent), ("delete", i)
        for value in (0x00, 0x01, 0x02, 0xFF, line[i], line[i] ^ 0x80):
            got = _decode_line(line[:i] + bytes([value]) + line[i:])
            assert _is_subsequence(got, sent), ("insert", i, value)
