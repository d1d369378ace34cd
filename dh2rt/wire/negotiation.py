"""The messages of link negotiation (:mod:`dh2rt.negotiation`) and their codec, sans-IO.

Two media: the connector-local channel (CLC) each connector has, at most :data:`LOCAL_MAX`
bytes a message (``OFFER`` and the sealed ``PROPOSE``/``ACCEPT``/``CONFIRM``/``REJECT``), and
the bus's management frames (``CLAIM``/``RELEASE``/``HOLD``, one classic CAN frame each, id
:data:`MANAGEMENT_ID`). ``docs/link-layer.md`` ("Link negotiation") has the formats; the
state machine that speaks them is :class:`dh2rt.negotiation.LinkNegotiator`.
"""

from __future__ import annotations

import enum
import zlib
from dataclasses import dataclass

from dh2rt.errors import DecodeError, EncodeError, FrameCorrupted

# the management channel's id is CAN framing's (the transports split it off by it)
from dh2rt.wire.can_frames import MANAGEMENT_ID as MANAGEMENT_ID
from dh2rt.wire.can_frames import MANAGEMENT_KIND as MANAGEMENT_KIND
from dh2rt.wire.can_frames import MAX_LINK_ID

#: The ids links may be given: 0 is left out (the HIL world's numbering starts there) and
#: MAX_LINK_ID is the management channel's.
FIRST_LINK_ID = 1
LAST_LINK_ID = MAX_LINK_ID - 1
#: The most a CLC message may carry.
LOCAL_MAX = 8

_U32 = 0xFFFFFFFF
_U24 = 0xFFFFFF


def management_filter() -> dict[str, int | bool]:
    """A python-can filter accepting the management frames (and nothing else)."""
    return {"can_id": MANAGEMENT_ID, "can_mask": (1 << 29) - 1, "extended": True}


# ---------------------------------------------------------------------------------------------
# Connector-local channel messages


class LocalType(enum.IntEnum):
    """Byte 0 of a CLC message."""

    OFFER = 1  # nonce u32, check u24
    PROPOSE = 2  # link id u24, seal u32 (leader -> follower)
    ACCEPT = 3  # link id u24, seal u32 (follower -> leader)
    CONFIRM = 4  # link id u24, seal u32 (leader -> follower)
    REJECT = 5  # link id u24, seal u32 (follower -> leader: that id is taken)


@dataclass(frozen=True, slots=True)
class Offer:
    """``OFFER``: the sender's nonce for this negotiation."""

    nonce: int


@dataclass(frozen=True, slots=True)
class Sealed:
    """``PROPOSE``/``ACCEPT``/``CONFIRM``/``REJECT``: a link id and a seal binding it to a tag.

    ``seal = tag ^ crc32(type byte ‖ link id)``: only a receiver holding the same tag (the same
    two nonces) accepts it, and a garbled type or id (any error in those 4 bytes) or seal never
    passes. A message from an older negotiation fails the same way.
    """

    kind: LocalType
    link_id: int
    seal: int

    def opens(self, tag: int) -> bool:
        """Whether this message belongs to the negotiation whose tag is ``tag``."""
        return self.seal == _seal(self.kind, self.link_id, tag)


LocalMessage = Offer | Sealed


def _offer_check(head: bytes) -> int:
    return zlib.crc32(head) & _U24


def _seal(kind: LocalType, link_id: int, tag: int) -> int:
    return (tag ^ zlib.crc32(bytes((kind,)) + link_id.to_bytes(3, "big"))) & _U32


def _check_link_id(link_id: int) -> None:
    if isinstance(link_id, bool) or not isinstance(link_id, int) or not FIRST_LINK_ID <= link_id <= LAST_LINK_ID:
        raise EncodeError(f"link id {link_id!r} is outside {FIRST_LINK_ID}..{LAST_LINK_ID}")


def _check_u32(name: str, value: int, *, nonzero: bool = False) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or not (1 if nonzero else 0) <= value <= _U32:
        raise EncodeError(f"{name} {value!r} is not a{' non-zero' if nonzero else ''} 32-bit value")


def encode_offer(nonce: int) -> bytes:
    """``OFFER``: type, nonce (4 bytes BE), low 24 bits of the CRC-32 of those 5 bytes."""
    _check_u32("nonce", nonce)
    head = bytes((LocalType.OFFER,)) + nonce.to_bytes(4, "big")
    return head + _offer_check(head).to_bytes(3, "big")


def encode_sealed(kind: LocalType, link_id: int, tag: int) -> bytes:
    """A sealed message: type, link id (3 bytes BE), seal (4 bytes BE); 8 bytes."""
    if kind is LocalType.OFFER:
        raise EncodeError("an OFFER carries a nonce, not a link id: use encode_offer")
    _check_link_id(link_id)
    _check_u32("tag", tag, nonzero=True)
    return bytes((kind,)) + link_id.to_bytes(3, "big") + _seal(kind, link_id, tag).to_bytes(4, "big")


def decode_local(data: bytes) -> LocalMessage:
    """One CLC message; raises DecodeError (FrameCorrupted for a failed check) on garbage."""
    if len(data) != LOCAL_MAX:
        raise DecodeError(f"CLC message of {len(data)} bytes; every message is {LOCAL_MAX}")
    try:
        kind = LocalType(data[0])
    except ValueError:
        raise DecodeError(f"CLC message type {data[0]} is unknown") from None
    if kind is LocalType.OFFER:
        if int.from_bytes(data[5:8], "big") != _offer_check(bytes(data[:5])):
            raise FrameCorrupted("OFFER check does not match")
        return Offer(int.from_bytes(data[1:5], "big"))
    link_id = int.from_bytes(data[1:4], "big")
    if not FIRST_LINK_ID <= link_id <= LAST_LINK_ID:
        raise DecodeError(f"CLC {kind.name} names link id {link_id}, outside {FIRST_LINK_ID}..{LAST_LINK_ID}")
    return Sealed(kind, link_id, int.from_bytes(data[4:8], "big"))


# ---------------------------------------------------------------------------------------------
# Bus management frames


class BusOp(enum.IntEnum):
    """Byte 0 of a management frame."""

    CLAIM = 1  # a pair wants this id (sent every cycle of its claim window)
    RELEASE = 2  # a pair let go of this id
    HOLD = 3  # an established pair owns this id (re-announced; also its defence)


@dataclass(frozen=True, slots=True)
class BusMessage:
    """A management frame's data: op, link id, the claiming pair's tag."""

    op: BusOp
    link_id: int
    tag: int


def encode_bus(msg: BusMessage) -> bytes:
    """op (1 byte), link id (3 bytes BE), tag (4 bytes BE): one classic CAN frame's 8 bytes."""
    _check_link_id(msg.link_id)
    _check_u32("tag", msg.tag, nonzero=True)
    return bytes((BusOp(msg.op),)) + msg.link_id.to_bytes(3, "big") + msg.tag.to_bytes(4, "big")


def decode_bus(data: bytes) -> BusMessage:
    """A management frame's data; raises DecodeError on garbage (CAN's CRC caught the noise)."""
    if len(data) != 8:
        raise DecodeError(f"management frame of {len(data)} bytes; it must be 8")
    try:
        op = BusOp(data[0])
    except ValueError:
        raise DecodeError(f"management op {data[0]} is unknown") from None
    link_id = int.from_bytes(data[1:4], "big")
    tag = int.from_bytes(data[4:8], "big")
    if not FIRST_LINK_ID <= link_id <= LAST_LINK_ID:
        raise DecodeError(f"management frame names link id {link_id}, outside {FIRST_LINK_ID}..{LAST_LINK_ID}")
    if tag == 0:
        raise DecodeError("management frame with tag 0 (no pair has it)")
    return BusMessage(op, link_id, tag)
