"""Segment trains never deliver a hormone that was not sent (issue 27).

Before wire version 3 a hormone longer than one CAN frame carried no tag and no check: with
the last frame of one train and the first of the next lost, ``N(100, 200, 300)`` and
``N(-700, 800, 900)`` arrived as ``N(100, 200, 940)``, counted nowhere. Here every pattern
of up to three lost frames over a stream of consecutive trains, and every interleaving of two
consecutive trains with up to three frames lost besides, delivers only payloads that were
sent; a hypothesis test moves and drops frames at random, classic and FD. Each fails on the
old framing (which spliced, see the reported case).
"""

from __future__ import annotations

import itertools
from collections import Counter
from collections.abc import Iterator, Sequence

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dh2rt.hormone import Hormone, HormoneSpec, ParamSpec, Vocabulary
from dh2rt.wire.can_frames import (
    CHECK_BYTES,
    FD_DATA,
    FIRST,
    LAST,
    MIDDLE,
    SINGLE,
    CanFrame,
    Reassembler,
    Segmenter,
    parse_arbitration_id,
    segment,
    train_check,
)
from dh2rt.wire.frame import FrameCodec, KeepAlive

INT = ParamSpec("n", None)
VOCAB = Vocabulary(
    [
        HormoneSpec(0, "N", (INT, INT, INT)),
        HormoneSpec(1, "X", (ParamSpec("a", ("A", "B")),)),
    ]
)
CODEC = FrameCodec(VOCAB, 4)
LINK, SIDE = 5, 0


def _n(*args: int) -> bytes:
    return CODEC.encode(2, Hormone("N", args))


#: Consecutive hormones of one link end: trains of 2 and 3 frames, and single frames between.
STREAM = (
    _n(100, 200, 300),  # 9 bytes: 2 frames
    _n(-700, 800, 900),  # 2 frames
    CODEC.encode(2, Hormone("X", ("A",))),  # 4 bytes: 1 frame
    _n(2**30, -(2**30), 2**31 - 1),  # 18 bytes: 3 frames
    _n(1, 2, 3),  # 6 bytes: 1 frame
    CODEC.encode(1, Hormone("X", ("B",), ((1, 2),) * 12)),  # 13 bytes: 3 frames
    _n(-(2**31), 5, -5),  # 10 bytes: 2 frames
)


def frames_of(payloads: Sequence[bytes], same_tag: bool = False, max_data: int = 8) -> list[list[CanFrame]]:
    """Each payload's frames as one sender makes them (consecutive tags), or all with tag 0
    (a sender that restarted between them: only the check tells the trains apart)."""
    if same_tag:
        return [segment(p, LINK, SIDE, max_data) for p in payloads]
    sender = Segmenter(max_data)
    return [sender.segment(p, LINK, SIDE) for p in payloads]


def deliver(frames: Sequence[CanFrame]) -> tuple[list[bytes], Reassembler]:
    r = Reassembler()
    out = [p for f in frames if (p := r.feed(f.arbitration_id, f.data)) is not None]
    return out, r


def is_subsequence(part: Sequence[bytes], whole: Sequence[bytes]) -> bool:
    rest = iter(whole)
    return all(any(p == w for w in rest) for p in part)


def losses(n: int, most: int = 3) -> Iterator[frozenset[int]]:
    for k in range(most + 1):
        for lost in itertools.combinations(range(n), k):
            yield frozenset(lost)


# -- the layout --------------------------------------------------------------------------


def test_a_small_hormone_is_one_frame_as_it_is() -> None:
    x = CODEC.encode(2, Hormone("X", ("A",)))
    for frames in (segment(x, LINK, SIDE), Segmenter().segment(x, LINK, SIDE)):
        assert frames == [CanFrame(frames[0].arbitration_id, x)]
        assert parse_arbitration_id(frames[0].arbitration_id).segment == SINGLE
    assert [len(f) for f in frames_of([_n(1, 2, 3), CODEC.encode(3, KeepAlive(200))])] == [1, 1]


def test_a_train_carries_its_tag_in_seq_and_ends_in_its_check() -> None:
    sender = Segmenter()
    trains = [sender.segment(p, LINK, SIDE) for p in (STREAM[0], STREAM[3], STREAM[2], STREAM[5])]
    assert [len(t) for t in trains] == [2, 3, 1, 3]
    for tag, train in zip((0, 1, None, 2), trains, strict=True):
        ids = [parse_arbitration_id(f.arbitration_id) for f in train]
        if tag is None:  # a single frame takes no tag
            continue
        assert [i.seq for i in ids] == [(tag + i) % 64 for i in range(len(train))]
        assert [i.segment for i in ids] == [FIRST, *[MIDDLE] * (len(train) - 2), LAST]
        body = b"".join(f.data for f in train)
        payload, check = body[:-CHECK_BYTES], body[-CHECK_BYTES:]
        assert check == train_check(tag, payload)
    # tags count per link end, modulo 64
    other = sender.segment(STREAM[0], LINK + 1, SIDE)
    assert parse_arbitration_id(other[0].arbitration_id).seq == 0
    for _ in range(70):
        last = sender.segment(STREAM[0], LINK, SIDE)
    assert parse_arbitration_id(last[0].arbitration_id).seq == (3 + 69) % 64


# -- the reported splice -----------------------------------------------------------------


@pytest.mark.parametrize("same_tag", [False, True])
def test_the_reported_splice_is_refused_and_counted(same_tag: bool) -> None:
    a, b = frames_of([_n(100, 200, 300), _n(-700, 800, 900)], same_tag)
    assert len(a) == len(b) == 2
    out, r = deliver([a[0], b[1]])  # the last frame of A and the first of B lost
    assert out == []
    assert r.dropped == 1 and not r.pending
    assert r.refused == (1 if same_tag else 0)  # same tags: seq matches, the check refuses it
    out, _ = deliver([*a, *b])
    assert out == [_n(100, 200, 300), _n(-700, 800, 900)]


# -- every pattern -----------------------------------------------------------------------


@pytest.mark.parametrize("same_tag", [False, True], ids=["tags", "no-tags"])
def test_up_to_three_lost_frames_deliver_only_what_was_sent(same_tag: bool) -> None:
    """Every subset of up to 3 frames lost from a stream of 7 consecutive hormones (14
    frames): what comes out is some of what was sent, in order; a frame that came in and
    went into nothing delivered is counted (or still pending)."""
    frames = [f for train in frames_of(STREAM, same_tag) for f in train]
    assert len(frames) == 14
    patterns = 0
    for lost in losses(len(frames)):
        kept = [f for i, f in enumerate(frames) if i not in lost]
        out, r = deliver(kept)
        assert is_subsequence(out, STREAM), sorted(lost)
        used = sum(len(p) + (CHECK_BYTES if len(p) > 8 else 0) for p in out)
        if used < sum(len(f.data) for f in kept):
            assert r.dropped + r.corrupted + r.pending > 0, sorted(lost)
        patterns += 1
    assert patterns == 1 + 14 + 91 + 364


@pytest.mark.parametrize("same_tag", [False, True], ids=["tags", "no-tags"])
@pytest.mark.parametrize(("first", "second"), [(0, 1), (1, 3), (3, 5), (5, 6)])
def test_two_interleaved_trains_with_frames_lost_deliver_only_what_was_sent(
    first: int, second: int, same_tag: bool
) -> None:
    """Two consecutive trains of one link end, their frames merged in every order that keeps
    each train's own (a sender sending two at once), with up to 3 frames lost besides."""
    a, b = frames_of([STREAM[first], STREAM[second]], same_tag)
    sent = Counter((STREAM[first], STREAM[second]))
    n = len(a) + len(b)
    for where_a in itertools.combinations(range(n), len(a)):
        ia, ib = iter(a), iter(b)
        merged = [next(ia) if i in where_a else next(ib) for i in range(n)]
        for lost in losses(n):
            out, _ = deliver([f for i, f in enumerate(merged) if i not in lost])
            assert not Counter(out) - sent, (where_a, sorted(lost))


# -- at random ---------------------------------------------------------------------------

ints = st.integers(-(2**31), 2**31 - 1)
payloads = st.one_of(
    st.builds(lambda a, b, c: _n(a, b, c), ints, ints, ints),
    st.builds(
        lambda a, hops: CODEC.encode(3, Hormone("X", (a,), ((2, 1),) * hops)),
        st.sampled_from("AB"),
        st.integers(0, 200),
    ),
)


@given(
    st.lists(payloads, min_size=2, max_size=8),
    st.booleans(),
    st.booleans(),
    st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 10**6)), max_size=3),
    st.lists(st.integers(0, 10**6), max_size=3),
)
@settings(max_examples=400, deadline=None)
def test_moved_and_lost_frames_never_make_a_hormone(
    sent: list[bytes], fd: bool, same_tag: bool, moves: list[tuple[int, int]], lost: list[int]
) -> None:
    """Consecutive trains (classic or FD), up to 3 frames moved elsewhere in the stream and
    up to 3 lost: every payload delivered was sent, no more often than it was sent."""
    frames = [f for train in frames_of(sent, same_tag, FD_DATA if fd else 8) for f in train]
    for src, dst in moves:
        frame = frames.pop(src % len(frames))
        frames.insert(dst % (len(frames) + 1), frame)
    for i in lost:
        if frames:
            frames.pop(i % len(frames))
    out, _ = deliver(frames)
    assert not Counter(out) - Counter(sent)
    if not moves and not lost:
        assert out == sent


# -- the transport counts what it refuses ------------------------------------------------


def test_a_can_transport_counts_a_refused_splice_as_dropped() -> None:
    can = pytest.importorskip("can")
    from dh2rt.transport.base import BusEnd
    from dh2rt.transport.can_bus import VirtualCanTransport

    channel = f"dh2rt-splice-{id(CODEC)}"
    with VirtualCanTransport(CODEC, channel=channel) as receiver, can.Bus(interface="virtual", channel=channel) as raw:
        receiver.attach(1, BusEnd(LINK, 1 - SIDE))
        a, b = frames_of([_n(100, 200, 300), _n(-700, 800, 900)], same_tag=True)
        for frame in (a[0], b[1], *b):
            raw.send(can.Message(arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=True))
        got = []
        for _ in range(50):
            got += receiver.poll(timeout=0.02)
            if got:
                break
        assert [r.frame for r in got] == [Hormone("N", (-700, 800, 900))]
        assert receiver.counters.dropped == 1 and receiver.counters.corrupted == 0
