"""Motion frames (dh2rt.wire.motion): the layout, round trips, every malformed case named,
canonical decoding, sequence numbers, and what the CAN and serial framings make of them."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dh2rt.errors import DecodeError, EncodeError
from dh2rt.wire import motion as mw
from dh2rt.wire import operator as op
from dh2rt.wire.can_frames import Reassembler, segment
from dh2rt.wire.serial_framing import SerialDecoder, encode_serial

connector = st.integers(1, 15)
routes = st.lists(st.tuples(connector, connector), min_size=1, max_size=8).map(tuple)
u16 = st.integers(0, 0xFFFF)
centi = st.integers(-32768, 32767).map(lambda c: c / 100)


@st.composite
def messages(draw: st.DrawFn) -> mw.MotionMessage:
    route = draw(routes)
    at = draw(st.integers(0, len(route)))
    motion, seq = draw(u16), draw(u16)
    kind = draw(st.integers(0, 4))
    if kind == 0:
        return mw.Ask(motion, seq, route, at)
    if kind == 1:
        angles = tuple(draw(st.lists(centi, min_size=1, max_size=8)))
        links = tuple(draw(st.lists(st.integers(0, 15), max_size=15)))
        return mw.Angles(motion, seq, route, draw(u16), angles, links, at)
    if kind == 2:
        dofs = sorted(draw(st.sets(st.integers(0, 7), min_size=1)))
        return mw.Targets(motion, seq, route, tuple((d, draw(centi)) for d in dofs), at)
    if kind == 3:
        return mw.End(motion, seq, route, at)
    markers = draw(st.lists(u16, min_size=1, max_size=2 * mw.MAX_MARKERS, unique=True))
    split = draw(st.integers(max(1, len(markers) - mw.MAX_MARKERS), min(len(markers), mw.MAX_MARKERS)))
    body, others = tuple(markers[:split]), tuple(markers[split:])
    return mw.SetOff(motion, seq, route, draw(u16), draw(connector), body, others, at)


@given(connector, messages())
def test_every_message_round_trips_and_is_a_motion_frame(sender: int, message: mw.MotionMessage) -> None:
    frame = mw.encode(sender, message)
    assert mw.is_motion(frame)
    assert frame[0] >> 6 == op.CONTROL_FAMILY and (frame[0] >> 4) & 3 == mw.MOTION_CLASS
    assert mw.decode(frame) == mw.MotionFrame(sender, message)
    assert mw.encode(sender, mw.decode(frame).message) == frame


def test_the_layout_byte_by_byte() -> None:
    frame = mw.encode(2, mw.Targets(0x1234, 7, ((2, 1), (2, 1)), ((0, 45.5), (1, -30.0)), 1))
    assert frame.hex(" ") == "22 42 12 34 00 07 01 02 21 21 02 00 11 c6 01 f4 48"
    assert mw.encode(1, mw.Ask(1, 2, ((2, 1),))).hex(" ") == "21 40 00 01 00 02 00 01 21"
    angles = mw.encode(1, mw.Angles(1, 2, ((2, 1),), 3, (0.0, 90.0), (2, 0, 0, 0), 1))
    assert angles.hex(" ") == "21 41 00 01 00 02 01 01 21 00 03 02 00 00 23 28 04 02 00 00 00"
    assert mw.encode(1, mw.End(1, 3, ((2, 1),))).hex(" ") == "21 43 00 01 00 03 00 01 21"
    set_off = mw.encode(1, mw.SetOff(1, 4, ((2, 1),), 0x0102, 4, (0x0102, 7), (9,), 1))
    assert set_off.hex(" ") == "21 44 00 01 00 04 01 01 21 01 02 04 02 01 02 00 07 01 00 09"


def test_the_operator_codec_and_the_motion_codec_split_the_family() -> None:
    ask = mw.encode(1, mw.Ask(1, 2, ((2, 1),)))
    with pytest.raises(DecodeError, match="reserved"):
        op.decode(ask)
    assert op.is_control(ask) and mw.is_motion(ask)
    pause = op.encode(1, op.Signed(op.Pause(), 8, bytes(8), bytes(64)))
    assert not mw.is_motion(pause)
    with pytest.raises(DecodeError, match="message type 2 is not a motion frame's"):
        mw.decode(pause)


ANGLES = mw.encode(1, mw.Angles(1, 2, ((2, 1),), 7, (1.0,), (2, 0, 0, 0)))
NOT_ASCENDING = "motion frame TARGETS: target DOF indices {} are not strictly ascending below 8"
RESERVED = "control frame: message type 69 is reserved (docking motion, not yet defined)"
SET_OFF = mw.encode(1, mw.SetOff(1, 2, ((2, 1),), 5, 4, (5, 6), (7,)))
TWICE = "motion frame SET_OFF: a marker named twice in body [5, 6] and others [6]"
GOOD = mw.encode(2, mw.Targets(5, 7, ((2, 1), (2, 1)), ((0, 45.5), (1, -30.0)), 1))


@pytest.mark.parametrize(
    ("data", "error"),
    [
        (b"\x22", "motion frame: 1 bytes, too short for a header and a type"),
        (bytes((0xA2, 0x42)) + GOOD[2:], "motion frame: family 2, expected 0"),
        (bytes((0x20,)) + GOOD[1:], "motion frame: sender connector 0"),
        (bytes((0x22, 0x45)) + GOOD[2:], RESERVED),
        (bytes((0x12,)) + GOOD[1:], "motion frame TARGETS: class 1, expected 2"),
        (GOOD[:5], "motion frame TARGETS: cut short in the motion, seq and hops at byte 2"),
        (GOOD[:7], "motion frame TARGETS: cut short in the route length at byte 7"),
        (GOOD[:9], "motion frame TARGETS: cut short in the route at byte 8"),
        (GOOD[:7] + b"\x00", "motion frame TARGETS: an empty route (the asker is no member of its motion)"),
        (GOOD[:7] + b"\x41" + bytes(65), "motion frame TARGETS: route of 65 hops exceeds 64"),
        (GOOD[:7] + b"\x01\x20", "motion frame TARGETS: a route hop names connector 0"),
        (GOOD[:6] + b"\x03" + GOOD[7:], "motion frame TARGETS: hops 3 beyond a 2-hop route"),
        (GOOD[:10], "motion frame TARGETS: cut short in the number of targets at byte 10"),
        (GOOD[:10] + b"\x00", "motion frame TARGETS: 0 targets; a frame carries 1..8"),
        (GOOD[:10] + b"\x09" + bytes(27), "motion frame TARGETS: 9 targets; a frame carries 1..8"),
        (GOOD[:-1], "motion frame TARGETS: cut short in the targets at byte 14"),
        (GOOD[:11] + GOOD[14:] + GOOD[11:14], NOT_ASCENDING.format("[1, 0]")),
        (GOOD[:11] + b"\x00\x00\x00" + GOOD[11:14], NOT_ASCENDING.format("[0, 0]")),
        (GOOD[:10] + b"\x01\x08\x00\x00", NOT_ASCENDING.format("[8]")),
        (GOOD + b"\x00", "motion frame TARGETS: 1 trailing byte(s)"),
        (ANGLES[:10], "motion frame ANGLES: cut short in the module and number of angles at byte 9"),
        (ANGLES[:13], "motion frame ANGLES: cut short in the angles at byte 12"),
        (ANGLES[:11] + b"\x00", "motion frame ANGLES: 0 angles; a frame carries 1..8"),
        (ANGLES[:14], "motion frame ANGLES: cut short in the number of links at byte 14"),
        (ANGLES[:14] + b"\x10", "motion frame ANGLES: 16 links; a module has at most 15 connectors"),
        (ANGLES[:-1] + b"\x10", "motion frame ANGLES: a link names connector 16, beyond 15"),
        (ANGLES[:-1], "motion frame ANGLES: cut short in the links at byte 15"),
        (SET_OFF[:11], "motion frame SET_OFF: cut short in the target module and connector at byte 9"),
        (SET_OFF[:11] + b"\x00" + SET_OFF[12:], "motion frame SET_OFF: target connector 0, not 1..15"),
        (SET_OFF[:11] + b"\x10" + SET_OFF[12:], "motion frame SET_OFF: target connector 16, not 1..15"),
        (SET_OFF[:12], "motion frame SET_OFF: cut short in the number of markers in body at byte 12"),
        (SET_OFF[:15], "motion frame SET_OFF: cut short in the markers in body at byte 13"),
        (SET_OFF[:17], "motion frame SET_OFF: cut short in the number of markers in others at byte 17"),
        (SET_OFF[:-1], "motion frame SET_OFF: cut short in the markers in others at byte 18"),
        (SET_OFF[:12] + b"\x00\x00", "motion frame SET_OFF: 0 markers in body; 1..32"),
        (SET_OFF[:12] + b"\x21" + bytes(66) + b"\x00", "motion frame SET_OFF: 33 markers in body; 1..32"),
        (SET_OFF[:17] + b"\x21" + bytes(66), "motion frame SET_OFF: 33 markers in others; at most 32"),
        (SET_OFF[:17] + b"\x01\x00\x06", TWICE),
        (SET_OFF + b"\x00", "motion frame SET_OFF: 1 trailing byte(s)"),
        (mw.encode(1, mw.Ask(1, 2, ((2, 1),))) + b"\x05", "motion frame ASK: 1 trailing byte(s)"),
        (mw.encode(1, mw.End(1, 2, ((2, 1),))) + b"\x05", "motion frame END: 1 trailing byte(s)"),
    ],
)
def test_every_malformed_frame_is_a_decode_error_naming_the_field(data: bytes, error: str) -> None:
    with pytest.raises(DecodeError) as caught:
        mw.decode(data)
    assert str(caught.value) == error


@pytest.mark.parametrize(
    ("sender", "message", "error"),
    [
        (0, mw.Ask(1, 2, ((2, 1),)), "sender connector 0 is outside 1..15"),
        (1, mw.Ask(1 << 16, 2, ((2, 1),)), "motion 65536 is outside 0..65535"),
        (1, mw.Ask(1, -1, ((2, 1),)), "seq -1 is outside 0..65535"),
        (1, mw.Ask(1, 2, ()), "route length 0 is outside 1..255"),
        (1, mw.Ask(1, 2, ((2, 1),), 2), "hops 2 is outside 0..1"),
        (1, mw.Angles(1, 2, ((2, 1),), 0, (1.0,), (), 2), "hops left 2 is outside 0..1"),
        (1, mw.Ask(1, 2, ((16, 1),)), "path connector 16 is outside 1..15"),
        (1, mw.Angles(1, 2, ((2, 1),), 1 << 16, (1.0,)), "module 65536 is outside 0..65535"),
        (1, mw.Angles(1, 2, ((2, 1),), 0, (1.0,), (0,) * 16), "number of links 16 is outside 0..15"),
        (1, mw.Angles(1, 2, ((2, 1),), 0, (1.0,), (16,)), "a link's connector 16 is outside 0..15"),
        (1, mw.Angles(1, 2, ((2, 1),), 0, ()), "number of angles 0 is outside 1..8"),
        (1, mw.Angles(1, 2, ((2, 1),), 0, (400.0,)), "angle of DOF1 400.0 degrees is outside +-327.67"),
        (1, mw.Targets(1, 2, ((2, 1),), ((1, 0.0), (0, 0.0))), "target DOF indices [1, 0] are not strictly ascending"),
        (1, mw.Targets(1, 2, ((2, 1),), ((8, 0.0),)), "target DOF index 8 is outside 0..7"),
        (1, mw.Targets(1, 2, ((2, 1),), ((0, -400.0),)), "target of DOF1 -400.0 degrees is outside +-327.67"),
        (1, mw.SetOff(1, 2, ((2, 1),), 1 << 16, 1, (1,)), "target module 65536 is outside 0..65535"),
        (1, mw.SetOff(1, 2, ((2, 1),), 1, 0, (1,)), "target connector 0 is outside 1..15"),
        (1, mw.SetOff(1, 2, ((2, 1),), 1, 1, ()), "SET_OFF: 0 markers in body; 1..32"),
        (1, mw.SetOff(1, 2, ((2, 1),), 1, 1, (1,), tuple(range(2, 35))), "SET_OFF: 33 markers in others; at most 32"),
        (
            1,
            mw.SetOff(1, 2, ((2, 1),), 1, 1, (1, 2), (2,)),
            "SET_OFF: a marker named twice in body [1, 2] and others [2]",
        ),
        (1, mw.SetOff(1, 2, ((2, 1),), 1, 1, (1 << 16,)), "marker 65536 is outside 0..65535"),
    ],
)
def test_what_breaks_a_wire_limit_is_an_encode_error(sender: int, message: mw.MotionMessage, error: str) -> None:
    with pytest.raises(EncodeError) as caught:
        mw.encode(sender, message)
    assert str(caught.value) == error


def test_sequence_numbers_compare_across_the_wrap() -> None:
    assert mw.newer(0, None) and mw.newer(1, 0) and mw.newer(0, 0xFFFF) and mw.newer(5, 0xFFF0)
    assert not mw.newer(3, 3) and not mw.newer(2, 3) and not mw.newer(0xFFFF, 0)
    assert mw.newer(0x7FFF, 0) and not mw.newer(0x8000, 0)
    assert mw.next_seq(0xFFFF) == 0


def test_relaying_moves_one_hop() -> None:
    ask = mw.Ask(1, 2, ((2, 1), (2, 1)))
    assert mw.onward(ask).hops == 1
    assert mw.back(mw.Angles(1, 2, ask.route, 0, (0.0, 0.0), (), 2)).left == 1


@given(messages())
def test_can_trains_and_serial_framing_carry_them_whole(message: mw.MotionMessage) -> None:
    frame = mw.encode(1, message)
    cans = segment(frame, 3, 1)
    reassembler = Reassembler()
    got = [reassembler.feed(c.arbitration_id, c.data) for c in cans]
    assert got[-1] == frame and got[:-1] == [None] * (len(cans) - 1)
    assert SerialDecoder().feed(encode_serial(frame)) == [frame]
