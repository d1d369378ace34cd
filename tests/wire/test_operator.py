"""Control frames (dh2rt.wire.operator): the layout, round trips, strict and canonical
decoding, the reserved docking range, signatures, and what the other codecs and the CAN and
serial framings make of them."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dh2rt.errors import DecodeError, EncodeError
from dh2rt.hormone import HormoneSpec, ParamSpec, Vocabulary
from dh2rt.wire import operator as op
from dh2rt.wire import transfer as tw
from dh2rt.wire.can_frames import Reassembler, parse_arbitration_id, segment
from dh2rt.wire.frame import FrameCodec
from dh2rt.wire.serial_framing import SerialDecoder, encode_serial

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
DIGEST = bytes.fromhex("0102030405ff")

connector = st.integers(1, 15)
hops = st.lists(st.tuples(connector, connector), max_size=8).map(tuple)
u64 = st.integers(0, (1 << 64) - 1)
i64 = st.integers(-(1 << 63), (1 << 63) - 1)
byte_values = st.lists(st.integers(0, 255), max_size=20).map(tuple)

commands = st.one_of(
    st.builds(op.Inject, st.just(DIGEST), st.binary(min_size=1, max_size=40), hops),
    st.just(op.Pause()),
    st.just(op.Resume()),
    st.builds(op.StateRequest, hops),
    st.builds(op.Watch, st.integers(1, 0xFFFF), st.one_of(st.none(), st.integers(0, 255))),
)


@st.composite
def answers(draw: st.DrawFn) -> op.Answer | op.Watched:
    if draw(st.integers(0, 3)) == 0:
        return op.Watched(draw(u64), draw(u64), draw(st.integers(0, 15)), draw(st.binary(min_size=1, max_size=255)))
    path = draw(hops)
    left = draw(st.integers(0, len(path)))
    if draw(st.booleans()):
        return op.Refused(draw(u64), left, path, draw(st.sampled_from(list(op.RefusalReason))))
    status = op.ModuleStatus(
        draw(st.binary(min_size=6, max_size=6)),
        draw(st.integers(0, 255)),
        draw(st.booleans()),
        draw(u64),
        draw(u64),
        draw(byte_values),
        tuple(draw(st.lists(i64, max_size=10))),
        tuple(draw(st.lists(i64, max_size=10))),
        draw(byte_values),
    )
    return op.StateReply(draw(u64), left, path, status)


@st.composite
def signed(draw: st.DrawFn) -> op.Signed:
    command = draw(commands)
    counter = draw(u64)
    sig = draw(st.binary(min_size=64, max_size=64))
    return op.Signed(command, counter, draw(st.binary(min_size=8, max_size=8)), sig, draw(st.integers(0, 255)))


@given(connector, st.one_of(signed(), answers()))
def test_round_trip(sender: int, message: op.Message) -> None:
    frame = op.encode(sender, message)
    assert frame[0] >> 6 == op.CONTROL_FAMILY and frame[0] & 0x0F == sender
    assert op.decode(frame) == op.Control(sender, message)
    assert op.is_control(frame) and not tw.is_transfer(frame)


@settings(max_examples=400, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(signed(), answers()), st.integers(0, 10_000), st.integers(0, 255), st.sampled_from("sid"))
def test_every_accepted_byte_string_is_canonical(message: op.Message, at: int, value: int, edit: str) -> None:
    """A valid frame with one byte set, inserted or deleted: whatever still decodes re-encodes
    to the very same bytes; the rest is a DecodeError."""
    frame = bytearray(op.encode(2, message))
    at %= len(frame)
    if edit == "s":
        frame[at] = value
    elif edit == "i":
        frame.insert(at, value)
    else:
        del frame[at]
    try:
        sender, decoded = op.decode(bytes(frame))
    except DecodeError:
        return
    assert op.encode(sender, decoded) == bytes(frame)


def test_layout_of_a_pause() -> None:
    message = op.Signed(op.Pause(), 0x0102, bytes(8), bytes(64), hops=3)
    frame = op.encode(2, message)
    assert frame[:3] == bytes((0x12, 2, 3))  # family 0, class 1 (urgent), sender 2; PAUSE; 3 hops
    assert frame[3:11] == (0x0102).to_bytes(8, "big") and len(frame) == 3 + 8 + 8 + 64


def test_layout_of_an_inject() -> None:
    message = op.Signed(op.Inject(DIGEST, b"\x05", ((2, 1), (3, 1))), 7, bytes(8), bytes(64))
    frame = op.encode(1, message)
    assert frame[:3] == bytes((0x11, 1, 0))
    assert frame[19:25] == DIGEST and frame[25:28] == bytes((2, 0x21, 0x31)) and frame[28:30] == bytes((1, 5))


@pytest.mark.parametrize(
    ("data", "says"),
    [
        (b"\x11", "too short"),
        (bytes((0x80 | 0x11, 1)), "family 2"),
        (bytes((0x10, 1)), "sender connector 0"),
        (bytes((0x21, 64)), "reserved (docking motion"),
        (bytes((0x21, 127)), "reserved"),
        (bytes((0x21, 6)), "unknown message type 6"),
        (bytes((0x21, 2, 0)), "PAUSE: class 2, expected 1"),
        (bytes((0x11, 2, 0)) + bytes(10), "cut short in the counter and key id"),
        (bytes((0x11, 2, 0)) + bytes(16 + 63), "cut short in the signature"),
        (bytes((0x11, 2, 0)) + bytes(16 + 65), "1 trailing byte"),
        (bytes((0x11, 1, 0)) + bytes(16 + 6) + b"\x00\x00", "empty hormone content"),
        (bytes((0x11, 1, 0)) + bytes(16 + 6) + b"\x01\x10", "route hop names connector 0"),
        (bytes((0x21, 17)) + bytes(8) + b"\x01\x00\x01", "1 hops left of a 0-hop path"),
        (bytes((0x21, 17)) + bytes(8) + b"\x00\x00\x09", "unknown reason 9"),
        (bytes((0x21, 5, 0)) + bytes(16) + b"\x00\x00\x00", "0 cycles of 0 hormone"),
        (bytes((0x31, 18)) + bytes(8) + b"\x00\x10\x01\x00", "connector 16 is outside 0..15"),
        (bytes((0x31, 18)) + bytes(8) + b"\x00\x01\x00", "an empty frame"),
        (bytes((0x21, 16)) + bytes(8) + b"\x00\x00" + bytes(7) + b"\x02", "unknown flags"),
        (bytes((0x21, 16)) + bytes(8) + b"\x00\x00" + bytes(8) + b"\x80\x00", "LocalTimer is not in its shortest"),
        (bytes((0x21, 16)) + bytes(8) + b"\x00\x00" + bytes(8) + b"\xff" * 10 + b"\x01", "does not fit 64 bits"),
    ],
)
def test_strict_decoding_names_the_field(data: bytes, says: str) -> None:
    with pytest.raises(DecodeError, match=says.replace("(", r"\(")):
        op.decode(data)


@pytest.mark.parametrize(
    ("message", "says"),
    [
        (op.Signed(op.Pause(), -1, bytes(8), bytes(64)), "counter"),
        (op.Signed(op.Pause(), 1, bytes(7), bytes(64)), "key id"),
        (op.Signed(op.Pause(), 1, bytes(8), bytes(63)), "signature"),
        (op.Signed(op.Inject(bytes(5), b"\x00"), 1, bytes(8), bytes(64)), "program digest"),
        (op.Signed(op.Inject(DIGEST, b""), 1, bytes(8), bytes(64)), "hormone content bytes"),
        (op.Signed(op.StateRequest(((0, 1),)), 1, bytes(8), bytes(64)), "path connector"),
        (op.Refused(1, 2, ((1, 1),), op.RefusalReason.REPLAYED), "hops left"),
    ],
)
def test_encoding_refuses_what_the_wire_cannot_carry(message: op.Message, says: str) -> None:
    with pytest.raises(EncodeError, match=says):
        op.encode(1, message)


def test_a_status_too_large_for_a_link_is_refused() -> None:
    status = op.ModuleStatus(DIGEST, 0, False, 0, 0, (0,) * 4, variables=((1 << 62),) * 60)
    with pytest.raises(EncodeError, match="exceeds a link's 512"):
        op.encode(1, op.StateReply(1, 0, (), status))


def test_signatures_hold_for_the_key_only_and_cover_every_signed_field() -> None:
    from nacl.signing import SigningKey

    public = bytes(SigningKey(KEY).verify_key)
    other = bytes(SigningKey(OTHER_KEY).verify_key)
    message = op.sign(op.Inject(DIGEST, b"\x03", ((2, 1),)), 42, KEY)
    assert message.key_id == op.key_id(public) and message.hops == 0
    assert op.signature_holds(message, public) and not op.signature_holds(message, other)
    assert op.signature_holds(message.onward().onward(), public)  # hops are outside the signature
    sent = op.decode(op.encode(3, message)).message
    assert isinstance(sent, op.Signed) and op.signature_holds(sent, public)
    for changed in (
        op.Signed(op.Inject(DIGEST, b"\x04", ((2, 1),)), 42, message.key_id, message.signature),
        op.Signed(op.Inject(DIGEST, b"\x03", ((2, 2),)), 42, message.key_id, message.signature),
        op.Signed(op.Inject(DIGEST, b"\x03", ((2, 1),)), 43, message.key_id, message.signature),
        op.Signed(op.StateRequest(((2, 1),)), 42, message.key_id, message.signature),
    ):
        assert not op.signature_holds(changed, public), changed
    pause = op.sign(op.Pause(), 42, KEY)
    assert not op.signature_holds(op.Signed(op.Resume(), 42, pause.key_id, pause.signature), public)


def test_link_and_transfer_decoders_refuse_control_frames() -> None:
    vocab = Vocabulary([HormoneSpec(i, f"H{i}", (ParamSpec("a", None),)) for i in range(256)])
    frame = op.encode(2, op.sign(op.Pause(), 1, KEY))
    with pytest.raises(DecodeError, match="wire version 0"):
        FrameCodec(vocab, 15).decode(frame)
    with pytest.raises(DecodeError, match="family 0, expected 2"):
        tw.decode(frame)


def test_a_command_crosses_can_as_a_segment_train_and_serial_as_one_frame() -> None:
    frame = op.encode(2, op.sign(op.Inject(DIGEST, b"\x01", ((2, 1), (2, 1))), 9, KEY))
    cans = segment(frame, link_id=5, side=1)
    assert len(cans) > 1 and {parse_arbitration_id(c.arbitration_id).kind for c in cans} == {op.URGENT_CLASS}
    reassembler = Reassembler()
    got = [reassembler.feed(c.arbitration_id, c.data) for c in cans]
    assert got[-1] == frame and got[:-1] == [None] * (len(cans) - 1)
    assert SerialDecoder().feed(encode_serial(frame)) == [frame]
