"""The messages of link negotiation (dh2rt.wire.negotiation): the connector-local channel's
and the bus's management frames, their checks and their refusals."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from dh2rt.errors import DecodeError, EncodeError, FrameCorrupted
from dh2rt.wire.can_frames import MAX_LINK_ID, SINGLE, parse_arbitration_id
from dh2rt.wire.negotiation import (
    LAST_LINK_ID,
    MANAGEMENT_ID,
    BusMessage,
    BusOp,
    LocalType,
    Offer,
    Sealed,
    decode_bus,
    decode_local,
    encode_bus,
    encode_offer,
    encode_sealed,
    management_filter,
)


def test_offer_round_trip() -> None:
    data = encode_offer(0xDEADBEEF)
    assert len(data) == 8 and data[0] == LocalType.OFFER
    assert decode_local(data) == Offer(0xDEADBEEF)


@pytest.mark.parametrize("kind", [LocalType.PROPOSE, LocalType.ACCEPT, LocalType.CONFIRM, LocalType.REJECT])
def test_sealed_message_opens_only_under_its_tag(kind: LocalType) -> None:
    data = encode_sealed(kind, 0x2ABCD, 0x1234_5678)
    assert len(data) == 8
    msg = decode_local(data)
    assert isinstance(msg, Sealed) and msg.kind is kind and msg.link_id == 0x2ABCD
    assert msg.opens(0x1234_5678)
    assert not msg.opens(0x1234_5679)


@pytest.mark.parametrize("kind", list(LocalType))
def test_every_single_bit_error_is_caught(kind: LocalType) -> None:
    """A flipped bit anywhere in a CLC message fails decoding (OFFER's check, the type, the id
    range) or the seal: never a different message that is accepted."""
    tag = 0x0BAD_F00D
    data = encode_offer(0x600DCAFE) if kind is LocalType.OFFER else encode_sealed(kind, 12345, tag)
    for bit in range(64):
        flipped = bytearray(data)
        flipped[bit // 8] ^= 1 << (bit % 8)
        try:
            msg = decode_local(bytes(flipped))
        except DecodeError:
            continue
        assert isinstance(msg, Sealed) and not msg.opens(tag), f"bit {bit}: {msg}"


def test_bus_round_trip_and_management_id() -> None:
    for op in BusOp:
        msg = BusMessage(op, LAST_LINK_ID, 0xFFFF_FFFF)
        data = encode_bus(msg)
        assert len(data) == 8 and decode_bus(data) == msg
    f = parse_arbitration_id(MANAGEMENT_ID)
    assert (f.kind, f.segment, f.seq, f.link_id, f.side) == (3, SINGLE, 0, MAX_LINK_ID, 0)
    assert management_filter() == {"can_id": MANAGEMENT_ID, "can_mask": (1 << 29) - 1, "extended": True}


@pytest.mark.parametrize(
    "encode",
    [
        lambda: encode_offer(1 << 32),
        lambda: encode_offer(-1),
        lambda: encode_sealed(LocalType.PROPOSE, 0, 1),
        lambda: encode_sealed(LocalType.PROPOSE, MAX_LINK_ID, 1),
        lambda: encode_sealed(LocalType.PROPOSE, 5, 0),
        lambda: encode_sealed(LocalType.OFFER, 5, 1),
        lambda: encode_bus(BusMessage(BusOp.CLAIM, 0, 1)),
        lambda: encode_bus(BusMessage(BusOp.HOLD, 5, 0)),
        lambda: encode_bus(BusMessage(BusOp.HOLD, 5, 1 << 32)),
    ],
)
def test_encoders_refuse_values_out_of_range(encode: Callable[[], bytes]) -> None:
    with pytest.raises(EncodeError):
        encode()


@pytest.mark.parametrize(
    "data",
    [
        b"",
        encode_offer(7)[:7],
        encode_offer(7) + b"\x00",
        bytes([9]) + bytes(7),
        bytes([0]) + bytes(7),
        bytes([LocalType.ACCEPT]) + bytes(3) + bytes([1, 2, 3, 4]),  # link id 0
        bytes([LocalType.ACCEPT]) + MAX_LINK_ID.to_bytes(3, "big") + bytes([1, 2, 3, 4]),
    ],
)
def test_local_decoder_refuses_garbage(data: bytes) -> None:
    with pytest.raises(DecodeError):
        decode_local(data)


def test_offer_with_a_bad_check_is_corrupted() -> None:
    data = bytearray(encode_offer(42))
    data[7] ^= 1
    with pytest.raises(FrameCorrupted):
        decode_local(bytes(data))


@pytest.mark.parametrize(
    "data",
    [
        b"",
        bytes(7),
        bytes(9),
        bytes([0, 0, 0, 5, 0, 0, 0, 1]),  # op 0
        bytes([4, 0, 0, 5, 0, 0, 0, 1]),  # op 4
        bytes([1, 0, 0, 0, 0, 0, 0, 1]),  # link id 0
        bytes([1, 3, 0xFF, 0xFF, 0, 0, 0, 1]),  # link id MAX_LINK_ID
        bytes([1, 0, 0, 5, 0, 0, 0, 0]),  # tag 0
    ],
)
def test_bus_decoder_refuses_garbage(data: bytes) -> None:
    with pytest.raises(DecodeError):
        decode_bus(data)
