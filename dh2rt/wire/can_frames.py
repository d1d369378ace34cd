"""CAN framing for a shared bus, sans-IO: arbitration ids, segmentation, reassembly.

Modules share one bus, so adjacency is not visible on the wire. Each docked connector pair is
a *link* with a link id assigned by the world (never a module id, never seen by a program);
its two ends are *side* 0 and side 1. Every frame uses a 29-bit extended identifier::

    bits 28..27  kind      frame kind (0 hormone, 1 routed, 2 keep-alive, 3 hello);
                           lower ids win arbitration, so hormones go before beacons
    bits 26..25  segment   0 single, 1 first, 2 middle, 3 last
    bits 24..19  seq       a segment train's tag plus the segment's index, mod 64 (single: 0)
    bits 18..1   link id   0..262143
    bit  0       side      the end that SENT the frame

A module at side ``s`` of link ``L`` sends with ``(L, s)`` and listens for ``(L, 1 - s)``:
an acceptance filter on the low 19 bits (:func:`listen_filter`). Its own frames (which
``udp_multicast`` echoes back) carry its own side and are filtered out by the same rule.

Payloads of up to 8 bytes (a caterpillar hormone is 4) go in one classic frame, as they are:
CAN's own CRC guards them. Longer ones are segmented here: the segment marker and number ride
in the arbitration id, and the payload is followed by a CRC-32 of the train's *tag* and the
payload, so a receiver refuses a payload spliced from two trains or missing a piece
(``Reassembler.refused``). The tag is a per-link-end count of the sender's segment trains
(:class:`Segmenter`); segment ``i`` of a train with tag ``t`` carries seq ``(t + i) % 64``,
so segments of two consecutive trains never continue each other at the same position. No
flow control is needed: a receiver only reassembles, and CAN keeps one sender's frames in
order (docs/link-layer.md explains why this beats ISO-TP for hormones). With CAN FD,
segments carry up to 64 bytes and are cut to lengths FD can carry unpadded (``FD_LENGTHS``).
"""

from __future__ import annotations

from binascii import crc32
from dataclasses import dataclass, field
from typing import NamedTuple

from dh2rt.errors import DecodeError, EncodeError
from dh2rt.wire.frame import frame_kind
from dh2rt.wire.serial_framing import MAX_PAYLOAD

SINGLE, FIRST, MIDDLE, LAST = 0, 1, 2, 3
MAX_LINK_ID = (1 << 18) - 1
#: Values of the seq field: tags and segment numbers count modulo this.
SEQ_MODULUS = 64
CLASSIC_DATA = 8
FD_DATA = 64
#: Low 19 bits of the id: link id and side, what a receiver filters on.
LINK_END_MASK = (1 << 19) - 1
#: Bytes of the check that ends a segment train: CRC-32/ISO-HDLC of the tag byte and the
#: payload, little-endian (serial framing's FCS).
CHECK_BYTES = 4
#: The longest segment train: the longest payload a link carries (serial framing's limit,
#: a transfer frame's largest) and its check; 65 classic frames.
MAX_TRAIN = MAX_PAYLOAD + CHECK_BYTES


class CanId(NamedTuple):
    """The fields of a dh2rt arbitration id."""

    kind: int
    segment: int
    seq: int
    link_id: int
    side: int


class CanFrame(NamedTuple):
    """One CAN frame as dh2rt sends it: a 29-bit extended id and its data."""

    arbitration_id: int
    data: bytes


def make_arbitration_id(kind: int, segment: int, seq: int, link_id: int, side: int) -> int:
    """Pack the fields into a 29-bit id; raises EncodeError naming a field out of range."""
    for name, value, limit in (
        ("kind", kind, 3),
        ("segment", segment, 3),
        ("seq", seq, SEQ_MODULUS - 1),
        ("link_id", link_id, MAX_LINK_ID),
        ("side", side, 1),
    ):
        if not 0 <= value <= limit:
            raise EncodeError(f"CAN id field {name}={value} is outside 0..{limit}")
    return (kind << 27) | (segment << 25) | (seq << 19) | (link_id << 1) | side


#: The frame kind management frames use (kind 3, "hello": they lose arbitration to hormones).
MANAGEMENT_KIND = 3
#: The arbitration id of every management frame (link negotiation, :mod:`dh2rt.negotiation`):
#: link id MAX_LINK_ID, side 0, single segment. No negotiated link ever uses MAX_LINK_ID, so
#: no link's listen filter matches it; a CAN transport hands these to its management handler.
MANAGEMENT_ID = make_arbitration_id(MANAGEMENT_KIND, SINGLE, 0, MAX_LINK_ID, 0)

_ID_LIMIT = 1 << 29


def parse_arbitration_id(can_id: int) -> CanId:
    """Split a 29-bit id into its fields."""
    if not 0 <= can_id < _ID_LIMIT:
        raise DecodeError(f"CAN id {can_id:#x} is not a 29-bit identifier")
    return CanId(
        (can_id >> 27) & 3,
        (can_id >> 25) & 3,
        (can_id >> 19) & 63,
        (can_id >> 1) & MAX_LINK_ID,
        can_id & 1,
    )


def listen_filter(link_id: int, my_side: int) -> dict[str, int | bool]:
    """A python-can filter accepting what the far end of ``link_id`` sends to ``my_side``."""
    return {
        "can_id": make_arbitration_id(0, 0, 0, link_id, 1 - my_side),
        "can_mask": LINK_END_MASK,
        "extended": True,
    }


def segment(payload: bytes, link_id: int, side: int, max_data: int = CLASSIC_DATA, tag: int = 0) -> list[CanFrame]:
    """Split one frame's bytes into CAN frames sent by ``side`` of ``link_id``: one frame as it
    is when it fits, else a train numbered by ``tag`` (0..63) ending in its check.
    :class:`Segmenter` chooses the tags; a lone call may keep the default."""
    if not payload:
        raise EncodeError("cannot send an empty payload")
    if not 0 <= tag < SEQ_MODULUS:
        raise EncodeError(f"segment tag {tag} is outside 0..{SEQ_MODULUS - 1}")
    if len(payload) > MAX_PAYLOAD:
        raise EncodeError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    kind = int(frame_kind(payload))
    if len(_chunk_sizes(len(payload), max_data)) == 1:
        return [CanFrame(make_arbitration_id(kind, SINGLE, 0, link_id, side), bytes(payload))]
    body = bytes(payload) + train_check(tag, payload)
    sizes = _chunk_sizes(len(body), max_data)
    if len(sizes) == 1:  # FD: the payload fits no frame unpadded, payload and check one
        first = max(s for s in FD_LENGTHS if s < len(body))
        sizes = [first, *_chunk_sizes(len(body) - first, max_data)]
    frames = []
    pos = 0
    for i, size in enumerate(sizes):
        mark = FIRST if i == 0 else LAST if i == len(sizes) - 1 else MIDDLE
        can_id = make_arbitration_id(kind, mark, (tag + i) % SEQ_MODULUS, link_id, side)
        frames.append(CanFrame(can_id, body[pos : pos + size]))
        pos += size
    return frames


def train_check(tag: int, payload: bytes) -> bytes:
    """The check a segment train with ``tag`` ends in: CRC-32 of the tag byte and the payload."""
    return crc32(payload, crc32(bytes((tag,)))).to_bytes(CHECK_BYTES, "little")


class Segmenter:
    """Cuts payloads into CAN frames for one module, numbering each link end's segment
    trains with consecutive tags (mod 64): what lets a receiver tell two trains apart."""

    __slots__ = ("_next_tag", "max_data")

    def __init__(self, max_data: int = CLASSIC_DATA) -> None:
        _chunk_sizes(1, max_data)  # validates max_data
        self.max_data = max_data
        self._next_tag: dict[tuple[int, int], int] = {}

    def segment(self, payload: bytes, link_id: int, side: int) -> list[CanFrame]:
        """The frames of ``payload`` sent by ``side`` of ``link_id``."""
        key = (link_id, side)
        tag = self._next_tag.get(key, 0)
        frames = segment(payload, link_id, side, self.max_data, tag)
        if len(frames) > 1:
            self._next_tag[key] = (tag + 1) % SEQ_MODULUS
        return frames


#: Data lengths a CAN FD frame can have; others would be padded, and the frame codec rejects
#: trailing bytes, so FD segments are cut to these sizes instead of padded.
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)


def _chunk_sizes(n: int, max_data: int) -> list[int]:
    if max_data == CLASSIC_DATA:
        return [min(CLASSIC_DATA, n - i) for i in range(0, n, CLASSIC_DATA)]
    if max_data != FD_DATA:
        raise EncodeError(f"max_data must be {CLASSIC_DATA} (classic) or {FD_DATA} (FD), got {max_data}")
    sizes: list[int] = []
    while n > 0:
        size = max(s for s in FD_LENGTHS if s <= n)
        sizes.append(size)
        n -= size
    return sizes


@dataclass(slots=True)
class _Partial:
    kind: int
    tag: int
    next_seq: int
    data: bytearray = field(default_factory=bytearray)
    stamp: float = 0.0  # when its first segment arrived


class Reassembler:
    """Rebuilds payloads from segments, per sending link end.

    ``feed`` returns a whole payload or None. A segment out of sequence abandons the payload
    being rebuilt (``dropped``); a segment that cannot start or continue one is ``corrupted``;
    a train whose check fails (spliced from two trains, or a piece missing) is ``refused``,
    and counted in ``dropped`` too. Only payloads that were sent come out.

    ``started``: the ``stamp`` given with the first segment of the payload ``feed`` returned
    last (its own, for a single frame): when it began to arrive, which is when its sender
    sent it, whatever held the sender up between its segments.
    """

    __slots__ = ("_partial", "corrupted", "dropped", "refused", "started")

    def __init__(self) -> None:
        self._partial: dict[tuple[int, int], _Partial] = {}
        self.dropped = 0
        self.corrupted = 0
        self.refused = 0
        self.started = 0.0

    @property
    def pending(self) -> bool:
        """Whether a payload is being rebuilt (at any link end)."""
        return bool(self._partial)

    def feed(self, can_id: int, data: bytes, stamp: float = 0.0) -> bytes | None:
        """Consume one received frame (already known to be for one of our link ends) that
        arrived at ``stamp`` (any clock: see ``started``)."""
        # The fields of parse_arbitration_id, read in place: this runs for every frame.
        if not 0 <= can_id < _ID_LIMIT:
            self.corrupted += 1
            return None
        mark = (can_id >> 25) & 3
        key = ((can_id >> 1) & MAX_LINK_ID, can_id & 1)
        if mark == SINGLE:
            if self._partial:
                self._abandon(key)
            self.started = stamp
            return bytes(data)
        kind, seq = can_id >> 27, (can_id >> 19) & 63
        if mark == FIRST:
            self._abandon(key)
            if not data:
                self.corrupted += 1
                return None
            self._partial[key] = _Partial(kind, seq, (seq + 1) % SEQ_MODULUS, bytearray(data), stamp)
            return None
        part = self._partial.get(key)
        if part is None or seq != part.next_seq or kind != part.kind or not data:
            # A lost first segment or a gap: whatever was being rebuilt is lost too.
            if part is not None:
                self._abandon(key)
            else:
                self.corrupted += 1
            return None
        part.data += data
        part.next_seq = (seq + 1) % SEQ_MODULUS
        if mark == LAST:
            del self._partial[key]
            body = part.data
            payload = bytes(body[:-CHECK_BYTES])
            if len(body) <= CHECK_BYTES or train_check(part.tag, payload) != body[-CHECK_BYTES:]:
                self.refused += 1
                self.dropped += 1
                return None
            self.started = part.stamp
            return payload
        if len(part.data) >= MAX_TRAIN:  # a last segment would make it too long
            self._abandon(key)
        return None

    def forget(self, link_id: int, side: int) -> None:
        """Drop a partial payload silently (the link was detached)."""
        self._partial.pop((link_id, side), None)

    def _abandon(self, key: tuple[int, int]) -> None:
        if self._partial.pop(key, None) is not None:
            self.dropped += 1
