"""Transfer frames (dh2rt.wire.transfer): the layout, round trips, strict decoding, what a
link-frame decoder makes of them (an error, never a hormone), the Hello with a version, and
what a frame costs a serial line or a CAN bus."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dh2rt.errors import DecodeError, EncodeError
from dh2rt.hormone import Hormone, HormoneSpec, ParamSpec, Vocabulary
from dh2rt.wire import transfer as tw
from dh2rt.wire.can_frames import CHECK_BYTES, CLASSIC_DATA, MAX_TRAIN, Reassembler, parse_arbitration_id, segment
from dh2rt.wire.frame import WIRE_VERSION, FrameCodec, FrameKind, Hello, frame_kind, program_digest
from dh2rt.wire.serial_framing import MAX_PAYLOAD, SerialDecoder, encode_serial
from dh2rt.wire.transfer import (
    Ack,
    Cancel,
    Commit,
    CommitAck,
    Decline,
    DeclineReason,
    Offer,
    Outcome,
    Report,
    ReportAck,
    Request,
    Segment,
)

#: Every hormone index 0..255 declared, so that no frame fails on an unknown index alone:
#: a link-frame decoder that accepted a transfer frame would have to return a hormone.
VOCAB = Vocabulary([HormoneSpec(i, f"H{i}", (ParamSpec("a", None),)) for i in range(256)])
CODEC = FrameCodec(VOCAB, 15)

IMAGE = bytes(range(8))
connector = st.integers(1, 15)
image = st.binary(min_size=8, max_size=8)
u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFFFFFF)
hops = st.lists(st.tuples(connector, connector), max_size=tw.MAX_PATH).map(tuple)
verdict = st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=tw.MAX_VERDICT)
reason = st.text(max_size=20).filter(lambda t: len(t.encode()) <= tw.MAX_REASON)


@st.composite
def offers(draw: st.DrawFn) -> Offer:
    size = draw(st.integers(1, tw.MAX_SEGMENT_SIZE))
    length = draw(st.integers(1, min(0xFFFFFFFF, size * 0xFFFF)))
    held = draw(st.integers(0, -(-length // size)))
    return Offer(draw(u32), draw(image), length, size, held, draw(st.booleans()), draw(hops))


@st.composite
def reports(draw: st.DrawFn) -> Report:
    path = draw(hops.filter(bool))
    left = draw(st.integers(1, len(path)))
    outcome = draw(st.sampled_from(list(Outcome)))
    return Report(draw(u16), draw(u16), outcome, draw(u32), left, path, draw(verdict), draw(reason))


messages = st.one_of(
    offers(),
    st.builds(Request, image, u16, st.integers(1, tw.MAX_WINDOW), st.booleans()),
    st.builds(Segment, u16, u16, st.binary(min_size=1, max_size=200)),
    st.builds(Ack, u16, u16, u16),
    st.builds(Decline, image, st.sampled_from(list(DeclineReason)), u32),
    st.builds(Cancel, image, verdict),
    st.builds(Commit, image, u32, st.integers(0, 255)),
    st.builds(CommitAck, image),
    reports(),
    st.builds(ReportAck, u16),
)


# ---------------------------------------------------------------- layout


def test_the_layout_byte_by_byte() -> None:
    offer = Offer(7, IMAGE, 343, 80, 5, False, ((1, 3), (2, 1)))
    assert tw.encode(2, offer).hex(" ") == (
        "a2 01 00 00 00 07 00 01 02 03 04 05 06 07 00 00 01 57 00 50 00 05 00 02 13 21"
    )
    #         family 2, class 2 (control), sender 2 | OFFER | version | id | length | size | held | flags | path
    assert tw.encode(3, Segment(0x0001, 4, b"\xaa\xbb")).hex(" ") == "b3 03 00 01 00 04 aa bb"
    #         class 3 (bulk) | SEGMENT | tag | index | data
    assert tw.encode(1, Ack(1, 5, 0b101)).hex(" ") == "a1 04 00 01 00 05 00 05"
    assert tw.encode(1, Commit(IMAGE, 1500, 0)).hex(" ") == "91 07 00 01 02 03 04 05 06 07 00 00 05 dc 00"
    #         class 1 (urgent) | COMMIT | id | remaining µs | hops


def test_sizes_of_the_frames_sent_most() -> None:
    """ACK fills one classic CAN frame; a SEGMENT costs 6 bytes of header."""
    assert len(tw.encode(1, Ack(1, 2, 3))) == CLASSIC_DATA
    assert len(tw.encode(1, Segment(1, 2, bytes(80)))) == 86
    assert len(tw.encode(1, Request(IMAGE, 0, 8))) == 14
    assert len(tw.encode(1, CommitAck(IMAGE))) == 10
    assert len(tw.encode(1, ReportAck(9))) == 4


@given(messages, connector)
@settings(max_examples=400, suppress_health_check=[HealthCheck.too_slow], deadline=None)
def test_round_trip(message: tw.Message, sender: int) -> None:
    data = tw.encode(sender, message)
    assert tw.is_transfer(data)
    assert tw.decode(data) == tw.Transfer(sender, message)
    assert (data[0] >> 4) & 3 == tw.message_class(message)


@given(messages, connector)
@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow], deadline=None)
def test_every_cut_and_every_trailing_byte_is_refused(message: tw.Message, sender: int) -> None:
    data = tw.encode(sender, message)
    for end in range(len(data)):
        if isinstance(message, Segment) and end >= 7:
            continue  # a shorter segment is another valid segment
        with pytest.raises(DecodeError):
            tw.decode(data[:end])
    if not isinstance(message, Segment):
        with pytest.raises(DecodeError):
            tw.decode(data + b"\x00")


@pytest.mark.parametrize(
    ("data", "why"),
    [
        (bytes((0x61, 1)) + bytes(21), "family 1"),  # a link frame's first byte
        (bytes((0xA0, 10, 0, 1)), "sender connector 0"),
        (bytes((0xA1, 11, 0, 1)), "unknown message type 11"),
        (bytes((0xB1, 10, 0, 1)), "class 3, expected 2"),  # a control message in the bulk class
        (bytes((0xA1, 8)) + IMAGE, "class 2, expected 1"),  # a COMMIT_ACK in the control class
        (bytes((0xA1, 3, 0, 1, 0, 0, 9)), "class 2, expected 3"),  # a segment in the control class
        (bytes((0xA1, 2)) + IMAGE + bytes((0, 0, 0, 0)), "window 0"),
        (bytes((0xA1, 2)) + IMAGE + bytes((0, 0, 1, 2)), "unknown flags"),
        (bytes((0xA1, 5)) + IMAGE + bytes((9, 0, 0, 0, 1)), "unknown reason 9"),
        (bytes((0xA1, 6)) + IMAGE + bytes((1, 0xC3)), "not ASCII"),
        (bytes((0xB1, 3, 0, 1, 0, 0)), "0 data bytes"),
    ],
)
def test_garbage_is_named(data: bytes, why: str) -> None:
    with pytest.raises(DecodeError, match=why):
        tw.decode(data)


def test_paths_and_reports_are_checked() -> None:
    report = Report(1, 2, Outcome.STAGED, 3, 2, ((1, 1), (2, 1)))
    data = bytearray(tw.encode(1, report))
    data[11] = 3  # left 3 of a 2-hop path
    with pytest.raises(DecodeError, match="3 hops left of a 2-hop path"):
        tw.decode(bytes(data))
    data = bytearray(tw.encode(1, report))
    data[13] = 0x20  # a hop naming connector 0
    with pytest.raises(DecodeError, match="connector 0"):
        tw.decode(bytes(data))
    with pytest.raises(EncodeError, match="hops left"):
        tw.encode(1, Report(1, 2, Outcome.STAGED, 3, 0, ((1, 1),)))
    with pytest.raises(EncodeError, match="exceeds 64"):
        tw.encode(1, Offer(1, IMAGE, 10, 10, 0, False, ((1, 1),) * 65))


@pytest.mark.parametrize(
    "message",
    [
        Offer(1, IMAGE, 10, 0, 0),
        Offer(1, IMAGE, 10, 5, 3),  # holds 3 of 2 segments
        Offer(1, IMAGE, 0xFFFFFFFF, 1, 0),  # too many segments
        Offer(1, b"short", 10, 5, 0),
        Request(IMAGE, 0, 0),
        Segment(0, 0, b""),
        Ack(0x10000, 0, 0),
        Cancel(IMAGE, "wrong kéy"),
        Report(1, 1, Outcome.STAGED, 1, 1, ((1, 1),), "", "x" * 49),
        Offer(1, IMAGE, 10, 5, 0, False, ((16, 1),)),
    ],
)
def test_encoding_refuses_what_the_wire_cannot_carry(message: tw.Message) -> None:
    with pytest.raises(EncodeError):
        tw.encode(1, message)


def test_reasons_are_cut_at_a_character_boundary() -> None:
    cut = tw.cut_reason("é" * 40)
    assert len(cut.encode()) <= tw.MAX_REASON
    assert cut.endswith("…") and cut.startswith("é" * 20)
    assert tw.cut_reason("short") == "short"


@given(st.binary(max_size=80))
@settings(max_examples=500, suppress_health_check=[HealthCheck.too_slow], deadline=None)
def test_garbage_only_ever_raises_decode_error(data: bytes) -> None:
    try:
        sender, message = tw.decode(data)
    except DecodeError:
        return
    assert tw.encode(sender, message) == data  # whatever decodes is canonical


# ---------------------------------------------------------------- next to link frames


@given(messages, connector)
@settings(max_examples=400, suppress_health_check=[HealthCheck.too_slow], deadline=None)
def test_a_link_frame_decoder_rejects_every_transfer_frame(message: tw.Message, sender: int) -> None:
    """Today's FrameCodec (every hormone index declared) raises DecodeError on a transfer
    frame: the family sits where it reads the wire version. Never a hormone."""
    data = tw.encode(sender, message)
    with pytest.raises(DecodeError, match="wire version 2"):
        CODEC.decode(data)


def test_link_frames_are_not_transfer_frames() -> None:
    for frame in (Hormone("H0", (1,), ((1, 2),)), Hello(b"abcdef")):
        data = CODEC.encode(3, frame)
        assert not tw.is_transfer(data)
        with pytest.raises(DecodeError, match=f"family {WIRE_VERSION}"):
            tw.decode(data)
    assert not tw.is_transfer(b"")


def test_can_priority_and_segmentation() -> None:
    """The class bits become the CAN kind: commits rank with routed hormones, other control
    frames with keep-alives, segments with hellos, all after hormones; segmented frames
    reassemble."""
    urgent = tw.encode(2, Commit(IMAGE, 5, 1))
    control = tw.encode(2, Offer(1, IMAGE, 343, 56, 0, False, ((1, 1),) * 10))
    bulk = tw.encode(2, Segment(1, 0, bytes(range(56))))
    assert frame_kind(urgent) is FrameKind.ROUTED
    assert frame_kind(control) is FrameKind.KEEPALIVE and frame_kind(bulk) is FrameKind.HELLO
    reassembler = Reassembler()
    for data in (urgent, control, bulk):
        frames = segment(data, 5, 1)
        assert {parse_arbitration_id(f.arbitration_id).kind for f in frames} == {frame_kind(data)}
        assert [reassembler.feed(f.arbitration_id, f.data) for f in frames][-1] == data


def test_the_largest_frames_fit_a_serial_frame() -> None:
    longest = Report(1, 1, Outcome.REFUSED, 1, 64, ((15, 15),) * 64, "w" * 16, "é" * 24)
    for message in (longest, Segment(1, 1, bytes(tw.MAX_SEGMENT_SIZE))):
        data = tw.encode(15, message)
        assert len(data) <= MAX_PAYLOAD
        wire = encode_serial(data)
        assert SerialDecoder().feed(wire) == [data]
        assert tw.serial_cost(len(data)) >= len(wire)
        frames = segment(data, 1, 0)  # a train of the frame and its check, within MAX_TRAIN
        assert len(frames) == -(-(len(data) + CHECK_BYTES) // CLASSIC_DATA) <= 65
        assert sum(len(f.data) for f in frames) <= MAX_TRAIN


@pytest.mark.parametrize("n", [1, 4, 13, 86, 253, 254, 300, 512])
def test_serial_cost_is_the_framed_length_at_worst(n: int) -> None:
    worst = bytes(n)  # zeros: COBS at its worst
    assert tw.serial_cost(n) >= len(encode_serial(worst))
    assert tw.serial_cost(n) <= len(encode_serial(bytes([1]) * n)) + 2


def test_can_cost_counts_worst_case_stuffing() -> None:
    assert tw.can_frame_bits(8) == 160  # 67 + 64 + floor(117 / 4)
    assert tw.can_frame_bits(0) == 80
    assert tw.can_cost(8) == 160  # one frame, no check
    # longer: a segment train, the payload and its 4-byte check
    assert tw.can_cost(13) == 2 * 160 + tw.can_frame_bits(1)
    assert tw.can_cost(86) == 11 * 160 + tw.can_frame_bits(2)
    for n in (9, 12, 13, 56 + 6, 143, 512):
        frames = segment(bytes((0xC0,)) + bytes(n - 1), 1, 0)
        assert tw.can_cost(n) == sum(tw.can_frame_bits(len(f.data)) for f in frames)


# ---------------------------------------------------------------- the Hello with a version


@pytest.mark.parametrize(("version", "size"), [(0, 8), (127, 8), (128, 9), (2**14, 10), (2**32 - 1, 12)])
def test_hello_with_a_version(version: int, size: int) -> None:
    digest = program_digest(b"program")
    data = tw.encode_hello(4, digest, version)
    assert len(data) == size
    assert tw.decode_hello(data) == tw.VersionedHello(4, digest, version)
    assert frame_kind(data) is FrameKind.HELLO
    # the link codec reads it too (the release that sends it decodes it), and writes it back
    assert CODEC.decode(data) == (4, Hello(digest, version))
    assert CODEC.encode(4, Hello(digest, version)) == data
    with pytest.raises(DecodeError, match="hello frame"):
        CODEC.decode(data + bytes(13 - size))  # longer than any varint: refused


def test_a_hello_without_a_version_reads_as_none() -> None:
    digest = program_digest(b"program")
    assert tw.decode_hello(CODEC.encode(2, Hello(digest))) == tw.VersionedHello(2, digest, None)


@pytest.mark.parametrize(
    ("tail", "why"),
    [
        (b"\x80", "cut short"),
        (b"\x81\x00", "shortest form"),
        (b"\x05\x00", "trailing"),
        (b"\xff\xff\xff\xff\x7f", "exceeds 32 bits"),
    ],
)
def test_a_bad_version_is_refused(tail: bytes, why: str) -> None:
    head = CODEC.encode(1, Hello(b"abcdef"))
    with pytest.raises(DecodeError, match=why):
        tw.decode_hello(head + tail)


def test_a_hello_must_be_a_hello() -> None:
    with pytest.raises(DecodeError, match="not a hello"):
        tw.decode_hello(CODEC.encode(1, Hormone("H1", (5,))) + bytes(6))
    with pytest.raises(DecodeError, match="at least 7"):
        tw.decode_hello(b"\x71abc")
    with pytest.raises(EncodeError):
        tw.encode_hello(1, b"abc", 1)


def test_a_commit_restamped_states_the_time_left_and_keeps_the_rest() -> None:
    frame = tw.encode(3, tw.Commit(bytes(range(8)), 50_000, 4))
    sender, message = tw.decode(tw.restamp_commit(frame, 0.0123456))
    assert (sender, message) == (3, tw.Commit(bytes(range(8)), 12_346, 4))
    assert tw.decode(tw.restamp_commit(frame, -1.0)).message == tw.Commit(bytes(range(8)), 0, 4)  # past: at once
    with pytest.raises(ValueError, match="not a COMMIT"):
        tw.restamp_commit(tw.encode(3, tw.CommitAck(bytes(range(8)))), 0.01)
