"""Control frames: the operator's commands to a running robot and the modules' answers
(sans-IO), the third frame family.

Byte 0's top two bits tell frame families apart (link frames: 3, the wire version; transfer
frames: 2, :mod:`dh2rt.wire.transfer`; 1: the old link version, refused). Control frames take
**0**, laid out as transfer frames are::

    byte 0      FF CC SSSS   family (2 bits, = 0), class (2 bits), sender connector (4 bits)
    byte 1      message type
    bytes 2..   the message's fields (big-endian), exactly as long as the type says

The class bits sit where the CAN framing reads a frame's kind into the arbitration id
(:func:`dh2rt.wire.can_frames.segment`), so they set a control frame's priority on a bus:
class 1 (urgent: INJECT, PAUSE, RESUME, whose timing the operator sees) ranks with routed
hormones, class 2 (the STATE request, the answers) with keep-alives. Frames longer than a CAN
frame's 8 bytes (every signed command) go as segment trains, as any family's do; serial
framing carries any family.

Message types (byte 1)::

    1..15     operator commands, signed (below)
    16..31    modules' answers, unsigned
    64..127   a docking chain's motion frames (:mod:`dh2rt.wire.motion`: ASK, ANGLES,
              TARGETS, END); this codec refuses them (DecodeError naming the range), the
              motion codec reads them
    others    unknown: a DecodeError

A **command** (INJECT 1, PAUSE 2, RESUME 3, STATE 4, WATCH 5)::

    byte 2      hops u8: the modules it has passed through (0: straight from the cable);
                each module that passes it on adds one, so it is outside the signature
    bytes 3..   the signed part:
                counter u64    above the last a module accepted, or the module refuses it
                key id 8       the first 8 bytes of SHA-256 of the signer's public key
                               (:func:`dh2rt.signed_image.key_id`)
                INJECT: digest 6 (the program's, as its Hello states it), route (n u8 + n
                        hops), content (len u8 + the vocabulary's encoding: hormone index,
                        then arguments, :meth:`dh2rt.hormone.Vocabulary.encode_content`)
                PAUSE, RESUME: nothing more
                STATE:  route (n u8 + n hops)
                WATCH:  cycles u16 (1..), n u8 (0: every hormone; 1: one, its index u8 follows)
    last 64     Ed25519 signature over ``SIGNING_CONTEXT ‖ type ‖ the signed part``

A *route* is the module's path from the cable, as transfer frames write paths: one byte a
hop, ``sent_through << 4 | received_at``; the empty route names the module the cable is
plugged into. INJECT and STATE travel along it (``hops`` says how far they are); PAUSE and
RESUME are flooded to every module once per counter.

An **answer** travels back to the cable along the reversed route of the command it answers::

    STATE_REPLY 16  counter u64, left u8, path (n u8 + n hops), then the module's status:
                    digest 6, type index u8, flags u8 (bit 0: paused), LocalTimer varint,
                    cycle varint, ConnectorStatus (n u8 + n bytes), sensors (n u8 + n
                    zigzag varints), variables (n u8 + n zigzag varints), receptor statuses
                    (n u8 + n bytes), all in the program's order (the console names them
                    from the program the digest names)
    REFUSED 17      counter u64, left u8, path (n u8 + n hops), reason u8
    WATCHED 18      counter u64 (the WATCH's), cycle varint, connector u8 (0: injected),
                    frame (len u8 + a link frame: a hormone the module at the cable received);
                    class 3 (bulk), sent by that module straight to the cable, never relayed

``left`` counts the hops still to go back: a module that holds an answer with ``left`` k > 0
sends it through ``path[k - 1][1]`` (where the command came in) with ``left`` k - 1; one with
``left`` 0 sends it to the cable.

Every accepted byte string is the canonical encoding of what it decodes to (varints in their
shortest form, no unknown flags, no trailing bytes); decoding raises only
:class:`~dh2rt.errors.DecodeError`, naming the field, and encoding raises
:class:`~dh2rt.errors.EncodeError` for a message that breaks a wire limit. Signing and
checking signatures are :func:`sign` and :func:`signature_holds` (libsodium through PyNaCl:
:mod:`dh2rt.ed25519`). docs/console.md has the tables and the rules a module follows.
"""

from __future__ import annotations

import hashlib
import struct
from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import IntEnum
from typing import NamedTuple

from dh2rt import ed25519
from dh2rt.errors import DecodeError, EncodeError
from dh2rt.wire.fields import FieldReader, check_class, check_range, encode_path, read_header
from dh2rt.wire.fields import Path as Path
from dh2rt.wire.frame import CONTROL_FAMILY as CONTROL_FAMILY
from dh2rt.wire.frame import HELLO_DIGEST_BYTES, FrameKind
from dh2rt.wire.serial_framing import MAX_PAYLOAD
from dh2rt.wire.sizes import MAX_CONNECTOR

#: Class bits (CAN priority): urgent commands rank with routed hormones, the rest with
#: keep-alives.
URGENT_CLASS = int(FrameKind.ROUTED)
CONTROL_CLASS = int(FrameKind.KEEPALIVE)
KEY_ID_BYTES = 8
SIGNATURE_BYTES = ed25519.SIGNATURE_BYTES
#: What a signature covers before the message type and the signed part: a command's
#: signature can never be taken for a signed image's or anything else's.
SIGNING_CONTEXT = b"dh2rt operator command 1\x00"
#: Message types reserved for issue 28's docking-motion frames.
RESERVED_TYPES = range(64, 128)
#: Largest hormone content an INJECT carries (the vocabulary's own limit is lower).
MAX_CONTENT = 255
#: Most values of one kind (connectors, sensors, variables, receptors) a status carries.
MAX_VALUES = 255
_U64 = (1 << 64) - 1
_VALUE_LIMIT = 1 << 63


class MessageType(IntEnum):
    """Byte 1 of a control frame."""

    INJECT = 1
    PAUSE = 2
    RESUME = 3
    STATE = 4
    WATCH = 5
    STATE_REPLY = 16
    REFUSED = 17
    WATCHED = 18


class RefusalReason(IntEnum):
    """Why a module did not carry out a command (REFUSED says it; the module counts it)."""

    BAD_SIGNATURE = 1  # the key is trusted, the signature does not hold: altered or forged
    UNTRUSTED_KEY = 2  # signed by a key not in the module's trust list
    REPLAYED = 3  # the counter is not above the last the module accepted
    NO_ROUTE = 4  # the route leads through a connector with nothing linked, or not here
    WRONG_PROGRAM = 5  # an INJECT for another program (digest), or content it cannot read
    NO_CONTROL = 6  # the module trusts no key: it takes no operator commands


@dataclass(frozen=True, slots=True)
class Inject:
    """Put the hormone ``content`` (the vocabulary's encoding) into the module at ``route``
    as if it had arrived there; refused unless the module runs the program ``digest`` names."""

    digest: bytes
    content: bytes
    route: Path = ()


@dataclass(frozen=True, slots=True)
class Pause:
    """Every module holds its joints and its timers (flooded)."""


@dataclass(frozen=True, slots=True)
class Resume:
    """Every module goes on where it paused (flooded)."""


@dataclass(frozen=True, slots=True)
class StateRequest:
    """Tell me your status, module at ``route``."""

    route: Path = ()


@dataclass(frozen=True, slots=True)
class Watch:
    """Module at the cable, send me every hormone you receive (or those of index ``hormone``)
    for the next ``cycles`` cycles, as WATCHED frames."""

    cycles: int
    hormone: int | None = None


Command = Inject | Pause | Resume | StateRequest | Watch


@dataclass(frozen=True, slots=True)
class Signed:
    """A command as it travels: its counter, the signer's key id, the signature over
    :meth:`signed_part`, and ``hops`` (not signed: modules passed through)."""

    command: Command
    counter: int
    key_id: bytes
    signature: bytes
    hops: int = 0

    def signed_part(self) -> bytes:
        """The bytes the signature covers (:data:`SIGNING_CONTEXT` first)."""
        return signed_part(self.command, self.counter, self.key_id)

    def onward(self) -> Signed:
        """The command as a module passes it on: one hop further."""
        return replace(self, hops=self.hops + 1)


@dataclass(frozen=True, slots=True)
class ModuleStatus:
    """One module's state as a STATE_REPLY carries it, values in the program's order."""

    digest: bytes
    type_index: int
    paused: bool
    timer: int
    cycle: int
    connectors: tuple[int, ...]
    sensors: tuple[int, ...] = ()
    variables: tuple[int, ...] = ()
    receptors: tuple[int, ...] = ()


@dataclass(frozen=True, slots=True)
class StateReply:
    """The status of the module at ``path``, answering the STATE numbered ``counter``;
    ``left`` hops of ``path`` remain on its way back."""

    counter: int
    left: int
    path: Path
    status: ModuleStatus


@dataclass(frozen=True, slots=True)
class Refused:
    """The module at ``path`` did not carry out the command numbered ``counter``."""

    counter: int
    left: int
    path: Path
    reason: RefusalReason


@dataclass(frozen=True, slots=True)
class Watched:
    """A hormone the module at the cable received in its ``cycle`` at connector ``at`` (0:
    injected there), for the WATCH numbered ``counter``: ``frame`` is it as a link frame (the
    module's program's codec encodes and decodes it)."""

    counter: int
    cycle: int
    at: int
    frame: bytes


Answer = StateReply | Refused
Message = Signed | StateReply | Refused | Watched

_COMMAND_TYPES: dict[type, MessageType] = {
    Inject: MessageType.INJECT,
    Pause: MessageType.PAUSE,
    Resume: MessageType.RESUME,
    StateRequest: MessageType.STATE,
    Watch: MessageType.WATCH,
}
_URGENT = {MessageType.INJECT, MessageType.PAUSE, MessageType.RESUME}
#: WATCHED frames rank with hellos (bulk: they must not delay the robot's own traffic).
BULK_CLASS = int(FrameKind.HELLO)
#: Longest link frame a WATCHED carries.
MAX_WATCHED_FRAME = 255


class Control(NamedTuple):
    """A decoded control frame and the connector its sender sent it through."""

    sender: int
    message: Message


# ---------------------------------------------------------------- helpers


def is_control(payload: bytes) -> bool:
    """Whether an encoded frame is a control frame (read from byte 0 only)."""
    return bool(payload) and payload[0] >> 6 == CONTROL_FAMILY


def message_type(message: Message) -> MessageType:
    if isinstance(message, Signed):
        return _COMMAND_TYPES[type(message.command)]
    if isinstance(message, Watched):
        return MessageType.WATCHED
    return MessageType.STATE_REPLY if isinstance(message, StateReply) else MessageType.REFUSED


def message_class(kind: MessageType) -> int:
    """The class bits a message type travels with (its CAN priority)."""
    if kind is MessageType.WATCHED:
        return BULK_CLASS
    return URGENT_CLASS if kind in _URGENT else CONTROL_CLASS


def route_of(command: Command) -> Path | None:
    """The route of a routed command; None for a flooded one."""
    return command.route if isinstance(command, Inject | StateRequest) else None


def key_id(public_key: bytes) -> bytes:
    """The 8-byte id of a raw public key: the first bytes of its SHA-256 (as
    :func:`dh2rt.signed_image.key_id` names a signer)."""
    return hashlib.sha256(public_key).digest()[:KEY_ID_BYTES]


def signed_part(command: Command, counter: int, key_id: bytes) -> bytes:
    """What a signature over ``command`` numbered ``counter`` covers."""
    check_range("counter", counter, 0, _U64)
    if len(key_id) != KEY_ID_BYTES:
        raise EncodeError(f"key id of {len(key_id)} bytes; it must be {KEY_ID_BYTES}")
    kind = _COMMAND_TYPES.get(type(command))
    if kind is None:
        raise EncodeError(f"not an operator command: {command!r}")
    return SIGNING_CONTEXT + bytes((kind,)) + struct.pack(">Q", counter) + bytes(key_id) + _command_body(command)


def sign(command: Command, counter: int, private_key: bytes) -> Signed:
    """``command`` numbered ``counter``, signed with the raw 32-byte Ed25519 ``private_key``
    (libsodium through PyNaCl, imported here)."""
    from nacl.signing import SigningKey

    if len(private_key) != 32:
        raise EncodeError(f"an Ed25519 private key is 32 bytes, not {len(private_key)}")
    signer = SigningKey(bytes(private_key))
    kid = key_id(bytes(signer.verify_key))
    signature = signer.sign(signed_part(command, counter, kid)).signature
    return Signed(command, counter, kid, bytes(signature))


def signature_holds(message: Signed, public_key: bytes) -> bool:
    """Whether ``message``'s signature is ``public_key``'s (libsodium's strict check)."""
    try:
        part = message.signed_part()
    except EncodeError:
        return False
    return ed25519.verify(public_key, message.signature, part)


# ---------------------------------------------------------------- encoding


def encode(sender: int, message: Message) -> bytes:
    """The frame carrying ``message`` sent through connector ``sender``."""
    check_range("sender connector", sender, 1, MAX_CONNECTOR)
    kind = message_type(message)
    head = (CONTROL_FAMILY << 6) | (message_class(kind) << 4) | sender
    match message:
        case Signed():
            check_range("hops", message.hops, 0, 255)
            if len(message.signature) != SIGNATURE_BYTES:
                raise EncodeError(f"signature of {len(message.signature)} bytes; it must be {SIGNATURE_BYTES}")
            part = message.signed_part()[len(SIGNING_CONTEXT) + 1 :]
            body = bytes((message.hops,)) + part + bytes(message.signature)
        case StateReply():
            body = _answer_head(message) + _status(message.status)
        case Refused():
            body = _answer_head(message) + bytes((RefusalReason(message.reason),))
        case Watched():
            check_range("counter", message.counter, 0, _U64)
            check_range("cycle", message.cycle, 0, _U64)
            check_range("connector", message.at, 0, MAX_CONNECTOR)
            check_range("watched frame bytes", len(message.frame), 1, MAX_WATCHED_FRAME)
            out = bytearray(struct.pack(">Q", message.counter))
            _put_varint(out, message.cycle)
            body = bytes(out) + bytes((message.at, len(message.frame))) + message.frame
    frame = bytes((head, kind)) + body
    if len(frame) > MAX_PAYLOAD:
        raise EncodeError(f"control frame of {len(frame)} bytes exceeds a link's {MAX_PAYLOAD}")
    return frame


def _command_body(command: Command) -> bytes:
    match command:
        case Inject():
            if len(command.digest) != HELLO_DIGEST_BYTES:
                raise EncodeError(f"program digest of {len(command.digest)} bytes; it must be {HELLO_DIGEST_BYTES}")
            check_range("hormone content bytes", len(command.content), 1, MAX_CONTENT)
            return bytes(command.digest) + encode_path(command.route) + bytes((len(command.content),)) + command.content
        case StateRequest():
            return encode_path(command.route)
        case Watch():
            check_range("watch cycles", command.cycles, 1, 0xFFFF)
            if command.hormone is None:
                return struct.pack(">HB", command.cycles, 0)
            check_range("hormone index", command.hormone, 0, 255)
            return struct.pack(">HBB", command.cycles, 1, command.hormone)
    return b""


def _answer_head(m: Answer) -> bytes:
    check_range("counter", m.counter, 0, _U64)
    check_range("hops left", m.left, 0, len(m.path))
    return struct.pack(">QB", m.counter, m.left) + encode_path(m.path)


def _status(s: ModuleStatus) -> bytes:
    if len(s.digest) != HELLO_DIGEST_BYTES:
        raise EncodeError(f"program digest of {len(s.digest)} bytes; it must be {HELLO_DIGEST_BYTES}")
    check_range("type index", s.type_index, 0, 255)
    out = bytearray(s.digest)
    out += bytes((s.type_index, int(s.paused)))
    for name, value in (("LocalTimer", s.timer), ("cycle", s.cycle)):
        check_range(name, value, 0, _U64)
        _put_varint(out, value)
    out += _bytes_list("ConnectorStatus", s.connectors)
    for name, values in (("sensors", s.sensors), ("variables", s.variables)):
        check_range(f"number of {name}", len(values), 0, MAX_VALUES)
        out.append(len(values))
        for v in values:
            check_range(f"a value of {name}", v, -_VALUE_LIMIT, _VALUE_LIMIT - 1)
            _put_varint(out, (v << 1) ^ (v >> 63))
    out += _bytes_list("receptor statuses", s.receptors)
    return bytes(out)


def _bytes_list(name: str, values: tuple[int, ...]) -> bytes:
    check_range(f"number of {name}", len(values), 0, MAX_VALUES)
    for v in values:
        check_range(f"a value of {name}", v, 0, 255)
    return bytes((len(values), *values))


def _put_varint(out: bytearray, n: int) -> None:
    while n >= 0x80:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)


# ---------------------------------------------------------------- decoding


class _Reader(FieldReader):
    """The shared reader, and the numbers control frames carry."""

    __slots__ = ()

    def byte(self, name: str) -> int:
        return self.take(1, name)[0]

    def varint(self, name: str) -> int:
        result = shift = 0
        while True:
            b = self.byte(name)
            if shift >= 64 or (shift == 63 and b > 1):
                raise DecodeError(f"{self.what}: {name} does not fit 64 bits")
            result |= (b & 0x7F) << shift
            if not b & 0x80:
                if b == 0 and shift:
                    raise DecodeError(f"{self.what}: {name} is not in its shortest form")
                return result
            shift += 7

    def signed_values(self, name: str) -> tuple[int, ...]:
        n = self.byte(f"number of {name}")
        values = []
        for _ in range(n):
            raw = self.varint(f"a value of {name}")
            values.append((raw >> 1) ^ -(raw & 1))
        return tuple(values)


def decode(data: bytes) -> Control:
    """Decode one whole control frame; raises DecodeError for anything else."""
    data = bytes(data)
    sender, type_byte = read_header(data, CONTROL_FAMILY, "control frame")
    if type_byte in RESERVED_TYPES:
        raise DecodeError(f"control frame: message type {type_byte} is reserved (docking motion, not yet defined)")
    try:
        kind = MessageType(type_byte)
    except ValueError:
        raise DecodeError(f"control frame: unknown message type {type_byte}") from None
    check_class(data, f"control frame {kind.name}", message_class(kind))
    reader = _Reader(data, f"control frame {kind.name}")
    message = _DECODERS[kind](reader)
    reader.end()
    return Control(sender, message)


def _decode_signed(r: _Reader, kind: MessageType) -> Signed:
    hops = r.byte("hops")
    counter, kid = struct.unpack(">Q8s", r.take(16, "counter and key id"))
    command: Command
    if kind is MessageType.INJECT:
        digest = r.take(HELLO_DIGEST_BYTES, "program digest")
        route = r.path("route")
        n = r.byte("content length")
        if n == 0:
            raise DecodeError(f"{r.what}: empty hormone content")
        command = Inject(digest, r.take(n, "content"), route)
    elif kind is MessageType.STATE:
        command = StateRequest(r.path("route"))
    elif kind is MessageType.WATCH:
        cycles, n = struct.unpack(">HB", r.take(3, "watch cycles and hormones"))
        if cycles == 0 or n > 1:
            raise DecodeError(f"{r.what}: {cycles} cycles of {n} hormone(s): not a watch")
        command = Watch(cycles, r.byte("hormone index") if n else None)
    else:
        command = Pause() if kind is MessageType.PAUSE else Resume()
    return Signed(command, counter, kid, r.take(SIGNATURE_BYTES, "signature"), hops)


def _decode_answer_head(r: _Reader) -> tuple[int, int, Path]:
    counter, left = struct.unpack(">QB", r.take(9, "counter and hops left"))
    path = r.path("path")
    if left > len(path):
        raise DecodeError(f"{r.what}: {left} hops left of a {len(path)}-hop path")
    return counter, left, path


def _decode_state_reply(r: _Reader) -> StateReply:
    counter, left, path = _decode_answer_head(r)
    digest = r.take(HELLO_DIGEST_BYTES, "program digest")
    type_index = r.byte("type index")
    flags = r.byte("flags")
    if flags & ~1:
        raise DecodeError(f"{r.what}: unknown flags {flags:#04x}")
    timer = r.varint("LocalTimer")
    cycle = r.varint("cycle")
    connectors = tuple(r.take(r.byte("number of connectors"), "ConnectorStatus"))
    sensors = r.signed_values("sensors")
    variables = r.signed_values("variables")
    receptors = tuple(r.take(r.byte("number of receptors"), "receptor statuses"))
    status = ModuleStatus(digest, type_index, bool(flags), timer, cycle, connectors, sensors, variables, receptors)
    return StateReply(counter, left, path, status)


def _decode_watched(r: _Reader) -> Watched:
    (counter,) = struct.unpack(">Q", r.take(8, "counter"))
    cycle = r.varint("cycle")
    at = r.byte("connector")
    if at > MAX_CONNECTOR:
        raise DecodeError(f"{r.what}: connector {at} is outside 0..{MAX_CONNECTOR}")
    n = r.byte("frame length")
    if n == 0:
        raise DecodeError(f"{r.what}: an empty frame")
    return Watched(counter, cycle, at, r.take(n, "frame"))


def _decode_refused(r: _Reader) -> Refused:
    counter, left, path = _decode_answer_head(r)
    reason = r.byte("reason")
    try:
        return Refused(counter, left, path, RefusalReason(reason))
    except ValueError:
        raise DecodeError(f"{r.what}: unknown reason {reason}") from None


_DECODERS: dict[MessageType, Callable[[_Reader], Message]] = {
    MessageType.INJECT: lambda r: _decode_signed(r, MessageType.INJECT),
    MessageType.PAUSE: lambda r: _decode_signed(r, MessageType.PAUSE),
    MessageType.RESUME: lambda r: _decode_signed(r, MessageType.RESUME),
    MessageType.STATE: lambda r: _decode_signed(r, MessageType.STATE),
    MessageType.STATE_REPLY: _decode_state_reply,
    MessageType.REFUSED: _decode_refused,
    MessageType.WATCH: lambda r: _decode_signed(r, MessageType.WATCH),
    MessageType.WATCHED: lambda r: _decode_watched(r),
}
