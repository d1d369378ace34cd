"""Protocol 2.0 codec: known vectors from the e-Manual, agreement with dynamixel-sdk, and
property tests (round trip, whole vs byte-by-byte, garbage)."""

from __future__ import annotations

import contextlib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dh2rt.errors import CodecError, DxlCrcError, DxlProtocolError, FrameCorrupted
from hil.dxl_protocol import (
    BROADCAST_ID,
    CorruptPacket,
    Event,
    Instruction,
    Packet,
    PacketParser,
    crc16,
    decode_packet,
    encode_instruction,
    encode_packet,
    encode_status,
    stuff,
    unstuff,
)

# Bytes biased towards the header and stuffing pattern, where the bugs live.
tricky_bytes = st.lists(st.sampled_from([0xFF, 0xFD, 0x00, 0x55, 0x01, 0xFE]), max_size=64).map(bytes)
any_bytes = st.one_of(tricky_bytes, st.binary(max_size=64))
packets = st.builds(
    Packet,
    id=st.integers(0, 0xFE),
    instruction=st.one_of(st.sampled_from(list(Instruction)), st.integers(0, 0xFF)),
    params=st.one_of(tricky_bytes, st.binary(max_size=200)),
)


def feed_bytewise(parser: PacketParser, data: bytes) -> list[Event]:
    events: list[Event] = []
    for i in range(len(data)):
        events += parser.feed(data[i : i + 1])
    return events


def test_crc_check_value() -> None:
    assert crc16(b"123456789") == 0xFEE8  # CRC-16/BUYPASS check value


def test_ping_instruction_matches_the_e_manual() -> None:
    assert encode_instruction(1, Instruction.PING) == bytes.fromhex("FF FF FD 00 01 03 00 01 19 4E")


def test_ping_status_matches_the_e_manual() -> None:
    # The e-Manual's ping reply: model 1030 (0x0406), firmware 0x26.
    wire = bytes.fromhex("FF FF FD 00 01 07 00 55 00 06 04 26 65 5D")
    assert encode_status(1, 0, bytes((0x06, 0x04, 0x26))) == wire
    packet = decode_packet(wire)
    assert packet.is_status and packet.error == 0 and packet.data == b"\x06\x04\x26"


def test_stuffing_grows_the_length_field() -> None:
    wire = encode_instruction(1, Instruction.WRITE, b"\x74\x00\xff\xff\xfd\x00")
    assert b"\xff\xff\xfd\xfd" in wire[7:]
    assert wire[5] == 6 + 3 + 1  # params + INST/CRC + one stuffed byte
    assert decode_packet(wire).params == b"\x74\x00\xff\xff\xfd\x00"


@given(tricky_bytes)
def test_unstuff_inverts_stuff(body: bytes) -> None:
    stuffed = stuff(body)
    assert unstuff(stuffed) == body
    assert b"\xff\xff\xfd\x00" not in stuffed


@given(any_bytes)
def test_crc_and_stuffing_agree_with_dynamixel_sdk(params: bytes) -> None:
    from dynamixel_sdk import PacketHandler

    handler = PacketHandler(2.0)
    assert handler.updateCRC(0, list(params), len(params)) == crc16(params)
    tx = [0] * (12 + len(params))
    tx[4], tx[5], tx[6], tx[7] = 1, (len(params) + 3) & 0xFF, (len(params) + 3) >> 8, 3
    tx[8 : 8 + len(params)] = list(params)
    out = handler.addStuffing(tx)
    length = out[5] | (out[6] << 8)
    assert bytes(out[7 : 7 + length - 2]) == stuff(b"\x03" + params)


@given(packets)
def test_round_trip(packet: Packet) -> None:
    wire = encode_packet(packet)
    assert decode_packet(wire) == packet
    assert PacketParser().feed(wire) == [packet]


@settings(max_examples=200)
@given(st.lists(st.tuples(any_bytes, packets), max_size=6), any_bytes)
def test_whole_and_bytewise_give_the_same_events(chunks: list[tuple[bytes, Packet]], tail: bytes) -> None:
    stream = b"".join(garbage + encode_packet(p) for garbage, p in chunks) + tail
    whole = PacketParser()
    bytewise = PacketParser()
    assert whole.feed(stream) == feed_bytewise(bytewise, stream)
    assert whole.pending == bytewise.pending


@settings(max_examples=200)
@given(any_bytes, packets)
def test_garbage_is_skipped_and_the_next_packet_found(garbage: bytes, packet: Packet) -> None:
    parser = PacketParser()
    # A corrupted length field in the garbage may claim up to 1 KiB: padding flushes it.
    events = parser.feed(garbage + encode_packet(packet) + bytes(1024))
    assert packet in events
    assert all(isinstance(e, Packet | CorruptPacket) for e in events)


@given(st.binary(max_size=300))
def test_random_bytes_never_raise_in_the_parser(data: bytes) -> None:
    parser = PacketParser()
    parser.feed(data)
    feed_bytewise(PacketParser(), data)


@given(st.binary(max_size=40))
def test_strict_decode_raises_only_its_own_error(data: bytes) -> None:
    with contextlib.suppress(DxlProtocolError):  # anything else fails the test
        decode_packet(data)


def test_bad_crc_is_an_event_and_the_parser_resynchronises() -> None:
    good = encode_instruction(2, Instruction.READ, b"\x84\x00\x04\x00")
    bad = bytearray(encode_instruction(1, Instruction.PING))
    bad[-1] ^= 0xFF
    parser = PacketParser()
    events = parser.feed(b"\x00\x13" + bytes(bad) + good)
    assert events == [CorruptPacket(1, bytes(bad)), Packet(2, Instruction.READ, good[8:12])]
    assert parser.corrupt_packets == 1
    with pytest.raises(DxlCrcError, match="CRC mismatch from id 1") as info:
        decode_packet(bytes(bad))
    assert isinstance(info.value, FrameCorrupted) and isinstance(info.value, CodecError)


def test_a_corrupted_length_does_not_lose_the_next_packet() -> None:
    first = bytearray(encode_instruction(1, Instruction.PING))
    first[5] = 40  # the length now swallows the next packet
    second = encode_instruction(2, Instruction.PING)
    events = PacketParser().feed(bytes(first) + second + bytes(40))
    assert events[-1] == Packet(2, Instruction.PING)


def test_status_accessors_reject_instruction_packets() -> None:
    with pytest.raises(DxlProtocolError, match="not a status packet"):
        _ = Packet(1, Instruction.PING).error


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"dxl_id": 300, "instruction": 1}, "id must be an integer in 0..255, got 300"),
        ({"dxl_id": 1, "instruction": -1}, "instruction must be"),
        ({"dxl_id": 1, "instruction": 3, "params": bytes(1100)}, "packet too long"),
    ],
)
def test_encoder_rejects_bad_values(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(DxlProtocolError, match=message):
        encode_instruction(**kwargs)  # type: ignore[arg-type]


def test_broadcast_id_is_accepted() -> None:
    wire = encode_instruction(BROADCAST_ID, Instruction.PING)
    assert decode_packet(wire).id == 0xFE
