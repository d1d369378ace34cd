"""CAN ids, segmentation and reassembly."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dh2rt.errors import CodecError
from dh2rt.hormone import Hormone, HormoneSpec, ParamSpec, Vocabulary
from dh2rt.wire.can_frames import (
    FD_DATA,
    FD_LENGTHS,
    FIRST,
    LAST,
    LINK_END_MASK,
    MAX_LINK_ID,
    MIDDLE,
    SINGLE,
    CanId,
    Reassembler,
    listen_filter,
    make_arbitration_id,
    parse_arbitration_id,
    segment,
)
from dh2rt.wire.frame import FrameCodec

CODEC = FrameCodec(Vocabulary([HormoneSpec(0, "X", (ParamSpec("a", ("A", "B")),))]), 4)


def _payload(rest: bytes) -> bytes:
    return b"\x41" + rest  # a hormone header: kind 0


def test_caterpillar_is_one_classic_frame() -> None:
    frames = segment(CODEC.encode(2, Hormone("X", ("A",))), link_id=7, side=1)
    assert len(frames) == 1 and len(frames[0].data) == 4
    assert parse_arbitration_id(frames[0].arbitration_id) == CanId(0, SINGLE, 0, 7, 1)


@given(
    st.integers(0, 3),
    st.integers(0, 3),
    st.integers(0, 63),
    st.integers(0, MAX_LINK_ID),
    st.integers(0, 1),
)
def test_id_round_trip(kind: int, seg: int, seq: int, link: int, side: int) -> None:
    can_id = make_arbitration_id(kind, seg, seq, link, side)
    assert can_id < 1 << 29
    assert parse_arbitration_id(can_id) == (kind, seg, seq, link, side)
    assert can_id & LINK_END_MASK == (link << 1) | side


def test_id_errors_name_the_field() -> None:
    with pytest.raises(ValueError, match="link_id=262144"):
        make_arbitration_id(0, 0, 0, MAX_LINK_ID + 1, 0)
    with pytest.raises(ValueError, match="side=2"):
        make_arbitration_id(0, 0, 0, 1, 2)
    with pytest.raises(CodecError, match="29-bit"):
        parse_arbitration_id(1 << 29)


def test_listen_filter_selects_the_far_side() -> None:
    f = listen_filter(5, my_side=0)
    far = make_arbitration_id(2, LAST, 9, 5, 1)
    mine = make_arbitration_id(2, LAST, 9, 5, 0)
    assert far & f["can_mask"] == f["can_id"] & f["can_mask"]
    assert mine & f["can_mask"] != f["can_id"] & f["can_mask"]


@given(st.binary(min_size=1, max_size=511), st.booleans())
@settings(max_examples=300)
def test_segment_reassemble_round_trip(body: bytes, fd: bool) -> None:
    payload = _payload(body)[:512]
    frames = segment(payload, 3, 0, FD_DATA if fd else 8)
    assert all(len(f.data) <= (64 if fd else 8) for f in frames)
    if fd:
        assert all(len(f.data) in FD_LENGTHS for f in frames)
    marks = [parse_arbitration_id(f.arbitration_id).segment for f in frames]
    if len(frames) == 1:
        assert marks == [SINGLE]
    else:
        assert marks[0] == FIRST and marks[-1] == LAST and set(marks[1:-1]) <= {MIDDLE}
    r = Reassembler()
    results = [r.feed(f.arbitration_id, f.data) for f in frames]
    assert results[-1] == payload and all(x is None for x in results[:-1])
    assert (r.dropped, r.corrupted) == (0, 0)


def test_lost_segment_drops_the_payload_only() -> None:
    frames = segment(_payload(bytes(range(1, 30))), 3, 0)
    r = Reassembler()
    for f in frames[:1] + frames[2:]:  # the second segment is lost
        assert r.feed(f.arbitration_id, f.data) is None
    assert r.dropped == 1
    ok = segment(_payload(b"\x01\x02"), 3, 0)[0]
    assert r.feed(ok.arbitration_id, ok.data) == _payload(b"\x01\x02")


def test_interleaved_link_ends_reassemble_separately() -> None:
    a = segment(_payload(bytes(20)), 1, 0)
    b = segment(_payload(bytes(range(1, 21))), 2, 1)
    r = Reassembler()
    out = [r.feed(f.arbitration_id, f.data) for pair in zip(a, b, strict=True) for f in pair]
    assert [x for x in out if x is not None] == [_payload(bytes(20)), _payload(bytes(range(1, 21)))]


@given(st.lists(st.tuples(st.integers(0, (1 << 29) - 1), st.binary(max_size=8)), max_size=50))
def test_reassembler_never_raises_on_garbage(frames: list[tuple[int, bytes]]) -> None:
    r = Reassembler()
    for can_id, data in frames:
        out = r.feed(can_id, data)
        assert out is None or isinstance(out, bytes)
