"""Transfer frames: the messages that carry a signed program image over the robot's own links
(sans-IO), and the Hello that carries the program version.

The frame kinds of :mod:`dh2rt.wire.frame` fill their two bits, so transfer frames are a
second *frame family*, told apart by the top two bits of byte 0, where link frames carry the
wire version (1)::

    byte 0      FF CC SSSS   family (2 bits, = 2), class (2 bits), sender connector (4 bits)
    byte 1      message type
    bytes 2..   the message's fields (big-endian), exactly as long as the type says

A decoder that knows only link frames reads family 2 as "wire version 2" and raises
DecodeError before it looks at anything else: a transfer frame is never misread as a hormone,
a keep-alive or a hello. The class bits sit where link frames keep their kind, which is what
the CAN framing puts in the arbitration id (:func:`dh2rt.wire.can_frames.segment`), so they
set a transfer frame's priority on a bus: class 1 (urgent: COMMIT, COMMIT_ACK, whose timing
matters) ranks with routed hormones, class 2 (control: the other messages but SEGMENT) with
keep-alives, class 3 (bulk: SEGMENT) with hellos, all below flooded hormones (kind 0).
Transfer frames name no program vocabulary, so modules running different programs read
each other's.

Messages (``id`` is an image id: the first 8 bytes of blake2b of the signed image's bytes;
``tag`` its first two bytes as an integer, for the frames sent many times)::

    OFFER       version u32, id 8, length u32, segment size u16, held u16, flags u8,
                path n u8 + n hops
    REQUEST     id 8, next segment u16, window u8, flags u8 (bit 0: a probe)
    SEGMENT     tag u16, index u16, data (1.. segment size bytes)
    ACK         tag u16, next u16 (every segment below is held), sack u16 (bit i: next+1+i held)
    DECLINE     id 8, reason u8, version u32 (the decliner runs)
    CANCEL      id 8, verdict (len u8 + ASCII): the sender withdraws the image (it refused it)
    COMMIT      id 8, remaining µs u32 (0: at once), hops u8
    COMMIT_ACK  id 8
    REPORT      tag u16, seq u16, outcome u8, version u32, left u8, path n u8 + n hops,
                verdict (len u8 + ASCII), reason (len u8 + UTF-8)
    REPORT_ACK  seq u16

A *hop* is one byte, ``sent_through << 4 | received_at`` (connectors 1..15), as a hormone's
path records hops. ``docs/flashing.md`` ("Delivery over the links") has the tables, the
sequence and the rules; :mod:`dh2rt.flash` holds the state machines that speak this.

The Hello that states the program version is a link frame (:func:`dh2rt.wire.frame.encode_hello`),
and the wire limits and link costs every module needs are in :mod:`dh2rt.wire.sizes`; both
are re-exported here, and neither loads this module's messages.

Decoding raises only :class:`~dh2rt.errors.DecodeError`; encoding raises
:class:`~dh2rt.errors.EncodeError` for a message that breaks a wire limit.
"""

from __future__ import annotations

import hashlib
import struct
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import NamedTuple

from dh2rt.errors import DecodeError, EncodeError
from dh2rt.wire.fields import FieldReader, check_class, check_range, encode_path, read_header
from dh2rt.wire.fields import Path as Path
from dh2rt.wire.frame import TRANSFER_FAMILY as TRANSFER_FAMILY
from dh2rt.wire.frame import FrameKind
from dh2rt.wire.frame import VersionedHello as VersionedHello
from dh2rt.wire.frame import decode_hello as decode_hello
from dh2rt.wire.frame import encode_hello as encode_hello
from dh2rt.wire.sizes import MAX_CONNECTOR as MAX_CONNECTOR
from dh2rt.wire.sizes import MAX_PATH as MAX_PATH
from dh2rt.wire.sizes import MAX_REASON as MAX_REASON
from dh2rt.wire.sizes import MAX_VERDICT as MAX_VERDICT
from dh2rt.wire.sizes import SERIAL_OVERHEAD as SERIAL_OVERHEAD
from dh2rt.wire.sizes import can_cost as can_cost
from dh2rt.wire.sizes import can_frame_bits as can_frame_bits
from dh2rt.wire.sizes import serial_cost as serial_cost

#: Class bits (the CAN priority) of COMMIT and COMMIT_ACK (that of routed hormones), of the
#: other control messages (keep-alives') and of SEGMENT (hellos').
URGENT_CLASS = int(FrameKind.ROUTED)
CONTROL_CLASS = int(FrameKind.KEEPALIVE)
BULK_CLASS = int(FrameKind.HELLO)
IMAGE_ID_BYTES = 8
#: Largest segment: a SEGMENT frame (6 bytes of header) then fills a serial frame's 512-byte
#: payload and the 64 classic CAN segments a payload may take.
MAX_SEGMENT_SIZE = 506
MAX_WINDOW = 64
#: Segments the ACK's selective bitmap covers beyond ``next``.
SACK_BITS = 16
_U16 = 0xFFFF
_U32 = 0xFFFFFFFF


class MessageType(IntEnum):
    """Byte 1 of a transfer frame."""

    OFFER = 1
    REQUEST = 2
    SEGMENT = 3
    ACK = 4
    DECLINE = 5
    CANCEL = 6
    COMMIT = 7
    COMMIT_ACK = 8
    REPORT = 9
    REPORT_ACK = 10


class DeclineReason(IntEnum):
    """Why a module does not take an offered image."""

    HAVE = 1  # it holds (or is receiving) this image from another neighbour
    CURRENT = 2  # it runs this image already
    NEWER = 3  # it runs or holds a higher version: the image would be a rollback
    REFUSED = 4  # its flash refused this image before
    REVERTED = 5  # this image was reverted here (a fault on trial)
    BUSY = 6  # another program runs on trial here


class Outcome(IntEnum):
    """What a REPORT says of a module."""

    WITHHELD = 1  # not offered, or withdrawn: a module on its path refused the image
    SILENT = 2  # offered, and never answered (reported by the neighbour that offered it)
    STAGED = 3  # the image is in its flash, waiting for the commit
    COMMITTED = 4  # it switched to the image
    CURRENT = 5  # it ran the image already
    CONFIRMED = 6  # its trial of the image ended well
    REFUSED = 7  # its flash refused the image (verdict and reason say why)
    REVERTED = 8  # it switched, faulted on trial and went back


@dataclass(frozen=True, slots=True)
class Offer:
    """I have (or am receiving) this image; segments follow. ``held``: the segments I hold
    from the first on (all of them, or fewer while I am still receiving it). ``running``: I
    run it (a module that stages it may switch at once). ``path``: the hops from the entry
    point to me."""

    version: int
    image: bytes
    length: int
    segment_size: int
    held: int
    running: bool = False
    path: Path = ()


@dataclass(frozen=True, slots=True)
class Request:
    """Send me ``image`` from segment ``next`` on (I hold every one below), ``window`` at a
    time: you are my source. A ``probe`` asks instead: I have lost my source (a restart, a
    link drop); OFFER me what you hold, and I choose."""

    image: bytes
    next: int
    window: int
    probe: bool = False


@dataclass(frozen=True, slots=True)
class Segment:
    """Segment ``index`` of the image whose tag is ``tag``."""

    tag: int
    index: int
    data: bytes


@dataclass(frozen=True, slots=True)
class Ack:
    """I hold every segment below ``next``, and segment ``next + 1 + i`` where bit i of ``sack`` is set."""

    tag: int
    next: int
    sack: int = 0


@dataclass(frozen=True, slots=True)
class Decline:
    """I do not take ``image`` (``reason``); I run ``version``."""

    image: bytes
    reason: DeclineReason
    version: int


@dataclass(frozen=True, slots=True)
class Cancel:
    """I withdraw ``image``: my flash refused it (``verdict``). Drop what you received."""

    image: bytes
    verdict: str


@dataclass(frozen=True, slots=True)
class Commit:
    """Switch to ``image`` ``remaining_us`` microseconds from when this frame was sent (0: at
    once). ``hops``: the modules the commit has passed through (0 from the entry point)."""

    image: bytes
    remaining_us: int
    hops: int


@dataclass(frozen=True, slots=True)
class CommitAck:
    """I have the commit of ``image``: stop sending it."""

    image: bytes


@dataclass(frozen=True, slots=True)
class Report:
    """The outcome of the module named ``path`` (from the entry point) for the image whose
    tag is ``tag``, travelling back to the entry point: ``left`` hops of ``path`` remain
    (the next goes out through ``path[left - 1][1]``). ``seq`` numbers it on one hop."""

    tag: int
    seq: int
    outcome: Outcome
    version: int
    left: int
    path: Path
    verdict: str = ""
    reason: str = ""


@dataclass(frozen=True, slots=True)
class ReportAck:
    """The report numbered ``seq`` arrived (on this hop)."""

    seq: int


Message = Offer | Request | Segment | Ack | Decline | Cancel | Commit | CommitAck | Report | ReportAck

_TYPES: dict[type, MessageType] = {
    Offer: MessageType.OFFER,
    Request: MessageType.REQUEST,
    Segment: MessageType.SEGMENT,
    Ack: MessageType.ACK,
    Decline: MessageType.DECLINE,
    Cancel: MessageType.CANCEL,
    Commit: MessageType.COMMIT,
    CommitAck: MessageType.COMMIT_ACK,
    Report: MessageType.REPORT,
    ReportAck: MessageType.REPORT_ACK,
}
_CLASSES = {MessageType.SEGMENT: BULK_CLASS, MessageType.COMMIT: URGENT_CLASS, MessageType.COMMIT_ACK: URGENT_CLASS}


class Transfer(NamedTuple):
    """A decoded transfer frame and the connector its sender sent it through."""

    sender: int
    message: Message


# ---------------------------------------------------------------- helpers


def image_id(data: bytes) -> bytes:
    """The id an image travels under: the first 8 bytes of blake2b of its bytes."""
    return hashlib.blake2b(data, digest_size=IMAGE_ID_BYTES).digest()


def tag_of(image: bytes) -> int:
    """The two-byte tag of an image id (SEGMENT, ACK and REPORT carry it)."""
    return int.from_bytes(image[:2], "big")


def is_transfer(payload: bytes) -> bool:
    """Whether an encoded frame is a transfer frame (read from byte 0 only)."""
    return bool(payload) and payload[0] >> 6 == TRANSFER_FAMILY


def cut_reason(text: str, limit: int = MAX_REASON) -> str:
    """``text`` cut to at most ``limit`` UTF-8 bytes at a character boundary ("…" marks a cut)."""
    raw = text.encode()
    if len(raw) <= limit:
        return text
    return raw[: limit - 3].decode(errors="ignore") + "…"


def message_class(message: Message) -> int:
    """The class bits a message travels with (its CAN priority)."""
    return _CLASSES.get(_TYPES[type(message)], CONTROL_CLASS)


# ---------------------------------------------------------------- encoding


def encode(sender: int, message: Message) -> bytes:
    """The frame carrying ``message`` sent through connector ``sender``."""
    check_range("sender connector", sender, 1, MAX_CONNECTOR)
    kind, body = _body(message)
    head = (TRANSFER_FAMILY << 6) | (message_class(message) << 4) | sender
    return bytes((head, kind)) + body


def _body(m: Message) -> tuple[int, bytes]:
    match m:
        case Offer():
            _check_image(m.image)
            check_range("version", m.version, 0, _U32)
            check_range("image length", m.length, 1, _U32)
            check_range("segment size", m.segment_size, 1, MAX_SEGMENT_SIZE)
            count = _segments(m.length, m.segment_size)
            if count > _U16:
                raise EncodeError(f"{m.length} bytes in segments of {m.segment_size} need more than {_U16} segments")
            check_range("segments held", m.held, 0, count)
            head = struct.pack(">I8sIHHB", m.version, m.image, m.length, m.segment_size, m.held, int(m.running))
            return MessageType.OFFER, head + encode_path(m.path)
        case Request():
            _check_image(m.image)
            check_range("next segment", m.next, 0, _U16)
            check_range("window", m.window, 1, MAX_WINDOW)
            return MessageType.REQUEST, struct.pack(">8sHBB", m.image, m.next, m.window, int(m.probe))
        case Segment():
            check_range("tag", m.tag, 0, _U16)
            check_range("segment index", m.index, 0, _U16)
            check_range("segment bytes", len(m.data), 1, MAX_SEGMENT_SIZE)
            return MessageType.SEGMENT, struct.pack(">HH", m.tag, m.index) + bytes(m.data)
        case Ack():
            check_range("tag", m.tag, 0, _U16)
            check_range("next segment", m.next, 0, _U16)
            check_range("sack", m.sack, 0, _U16)
            return MessageType.ACK, struct.pack(">HHH", m.tag, m.next, m.sack)
        case Decline():
            _check_image(m.image)
            check_range("version", m.version, 0, _U32)
            return MessageType.DECLINE, struct.pack(">8sBI", m.image, DeclineReason(m.reason), m.version)
        case Cancel():
            _check_image(m.image)
            return MessageType.CANCEL, bytes(m.image) + _ascii(m.verdict)
        case Commit():
            _check_image(m.image)
            check_range("remaining µs", m.remaining_us, 0, _U32)
            check_range("hops", m.hops, 0, 255)
            return MessageType.COMMIT, struct.pack(">8sIB", m.image, m.remaining_us, m.hops)
        case CommitAck():
            _check_image(m.image)
            return MessageType.COMMIT_ACK, bytes(m.image)
        case Report():
            return MessageType.REPORT, _report(m)
        case ReportAck():
            check_range("report seq", m.seq, 0, _U16)
            return MessageType.REPORT_ACK, struct.pack(">H", m.seq)
    raise EncodeError(f"not a transfer message: {m!r}")


def _report(m: Report) -> bytes:
    check_range("tag", m.tag, 0, _U16)
    check_range("report seq", m.seq, 0, _U16)
    check_range("version", m.version, 0, _U32)
    check_range("hops left", m.left, 1, len(m.path))
    head = struct.pack(">HHBIB", m.tag, m.seq, Outcome(m.outcome), m.version, m.left)
    reason = m.reason.encode()
    if len(reason) > MAX_REASON:
        raise EncodeError(f"report reason of {len(reason)} bytes exceeds {MAX_REASON} (cut_reason cuts it)")
    return head + encode_path(m.path) + _ascii(m.verdict) + bytes((len(reason),)) + reason


def _ascii(text: str) -> bytes:
    if not text.isascii() or len(text) > MAX_VERDICT:
        raise EncodeError(f"verdict {text!r} is not ASCII of at most {MAX_VERDICT} characters")
    return bytes((len(text),)) + text.encode()


def _check_image(image: bytes) -> None:
    if len(image) != IMAGE_ID_BYTES:
        raise EncodeError(f"image id of {len(image)} bytes; it must be {IMAGE_ID_BYTES}")


def _segments(length: int, size: int) -> int:
    return -(-length // size)


# ---------------------------------------------------------------- decoding


class _Reader(FieldReader):
    """The shared reader, and the texts transfer frames carry."""

    __slots__ = ()

    def text(self, field: str, limit: int, *, ascii_only: bool) -> str:
        (n,) = self.take(1, f"{field} length")
        if n > limit:
            raise DecodeError(f"{self.what}: {field} of {n} bytes exceeds {limit}")
        raw = self.take(n, field)
        if ascii_only and not raw.isascii():
            raise DecodeError(f"{self.what}: {field} is not ASCII")
        try:
            return raw.decode()
        except UnicodeDecodeError:
            raise DecodeError(f"{self.what}: {field} is not UTF-8") from None

    def rest(self) -> bytes:
        out = self.data[self.pos :]
        self.pos = len(self.data)
        return out


def decode(data: bytes) -> Transfer:
    """Decode one whole transfer frame; raises DecodeError for anything else."""
    data = bytes(data)
    sender, type_byte = read_header(data, TRANSFER_FAMILY, "transfer frame")
    try:
        kind = MessageType(type_byte)
    except ValueError:
        raise DecodeError(f"transfer frame: unknown message type {type_byte}") from None
    check_class(data, f"transfer frame {kind.name}", _CLASSES.get(kind, CONTROL_CLASS))
    reader = _Reader(data, f"transfer frame {kind.name}")
    message = _DECODERS[kind](reader)
    reader.end()
    return Transfer(sender, message)


def restamp_commit(frame: bytes, left_s: float) -> bytes:
    """``frame``, a COMMIT, stating ``left_s`` seconds to the switch instant instead (none
    left: 0): what a host sends as the frame leaves (:meth:`dh2rt.flash.values.Send.frame`)."""
    sender, message = decode(frame)
    if not isinstance(message, Commit):
        raise ValueError(f"restamp_commit: a {type(message).__name__}, not a COMMIT")
    return encode(sender, Commit(message.image, max(0, round(left_s * 1e6)), message.hops))


def _decode_offer(r: _Reader) -> Offer:
    version, image, length, size, held, flags = struct.unpack(">I8sIHHB", r.take(21, "offer fields"))
    if length == 0 or not 1 <= size <= MAX_SEGMENT_SIZE or _segments(length, size) > _U16:
        raise DecodeError(f"{r.what}: {length} bytes in segments of {size} is no image")
    if held > _segments(length, size):
        raise DecodeError(f"{r.what}: {held} segments held of {_segments(length, size)}")
    if flags & ~1:
        raise DecodeError(f"{r.what}: unknown flags {flags:#04x}")
    return Offer(version, image, length, size, held, bool(flags & 1), r.path())


def _decode_request(r: _Reader) -> Request:
    image, nxt, window, flags = struct.unpack(">8sHBB", r.take(12, "request fields"))
    if not 1 <= window <= MAX_WINDOW:
        raise DecodeError(f"{r.what}: window {window} is outside 1..{MAX_WINDOW}")
    if flags & ~1:
        raise DecodeError(f"{r.what}: unknown flags {flags:#04x}")
    return Request(image, nxt, window, bool(flags))


def _decode_segment(r: _Reader) -> Segment:
    tag, index = r.unpack(">HH", "segment header")
    data = r.rest()
    if not 1 <= len(data) <= MAX_SEGMENT_SIZE:
        raise DecodeError(f"{r.what}: {len(data)} data bytes, outside 1..{MAX_SEGMENT_SIZE}")
    return Segment(tag, index, data)


def _decode_ack(r: _Reader) -> Ack:
    tag, nxt, sack = r.unpack(">HHH", "ack fields")
    return Ack(tag, nxt, sack)


def _decode_decline(r: _Reader) -> Decline:
    image, reason, version = struct.unpack(">8sBI", r.take(13, "decline fields"))
    try:
        return Decline(image, DeclineReason(reason), version)
    except ValueError:
        raise DecodeError(f"{r.what}: unknown reason {reason}") from None


def _decode_cancel(r: _Reader) -> Cancel:
    image = r.take(IMAGE_ID_BYTES, "image id")
    return Cancel(image, r.text("verdict", MAX_VERDICT, ascii_only=True))


def _decode_commit(r: _Reader) -> Commit:
    image, remaining, hops = struct.unpack(">8sIB", r.take(13, "commit fields"))
    return Commit(image, remaining, hops)


def _decode_commit_ack(r: _Reader) -> CommitAck:
    return CommitAck(r.take(IMAGE_ID_BYTES, "image id"))


def _decode_report(r: _Reader) -> Report:
    tag, seq, outcome, version, left = r.unpack(">HHBIB", "report fields")
    try:
        kind = Outcome(outcome)
    except ValueError:
        raise DecodeError(f"{r.what}: unknown outcome {outcome}") from None
    path = r.path()
    if not 1 <= left <= len(path):
        raise DecodeError(f"{r.what}: {left} hops left of a {len(path)}-hop path")
    verdict = r.text("verdict", MAX_VERDICT, ascii_only=True)
    reason = r.text("reason", MAX_REASON, ascii_only=False)
    return Report(tag, seq, kind, version, left, path, verdict, reason)


def _decode_report_ack(r: _Reader) -> ReportAck:
    (seq,) = r.unpack(">H", "report seq")
    return ReportAck(seq)


_DECODERS: dict[MessageType, Callable[[_Reader], Message]] = {
    MessageType.OFFER: _decode_offer,
    MessageType.REQUEST: _decode_request,
    MessageType.SEGMENT: _decode_segment,
    MessageType.ACK: _decode_ack,
    MessageType.DECLINE: _decode_decline,
    MessageType.CANCEL: _decode_cancel,
    MessageType.COMMIT: _decode_commit,
    MessageType.COMMIT_ACK: _decode_commit_ack,
    MessageType.REPORT: _decode_report,
    MessageType.REPORT_ACK: _decode_report_ack,
}
