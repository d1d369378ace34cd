"""Motion frames: what the modules of a docking chain say to each other while they carry a
motion out (sans-IO), control-family message types 64..127 (:mod:`dh2rt.wire.operator`
reserved them). The module whose program called ``reach_dock`` (the *asker*) runs the motion;
every other module of the chain is a *member*, reached along a route of connector hops from
the asker, as operator commands are routed from the cable.

Laid out as every control frame::

    byte 0      FF CC SSSS   family (2 bits, = 0), class (2 bits, = 2), sender connector
    byte 1      message type
    bytes 2..3  motion u16     the motion's id, the asker's choice
    bytes 4..5  seq u16        the asker's count of what it sent in this motion
    byte 6      hops u8        outward (ASK, TARGETS, END): the hops made from the asker;
                               the report (ANGLES): the hops still to go back (``left``)
    bytes 7..   route (n u8 + n hops, ``sent_through << 4 | received_at``): the member's
                path from the asker; 1..64 hops (the asker is no member of its own motion)
    then        what the message carries

Message types::

    ASK 64       tell me your joint angles: nothing more
    ANGLES 65    the member's report, answering the ASK of the same seq: its module
                 index u16 (as its config names it: the tracker's marker of it); n u8
                 (1..8), then n i16, the angles it measures of DOF1, DOF2, ... in
                 hundredths of a degree; its links: n u8 (0..15), then n bytes, for each
                 of its connectors the peer's connector linked there (its
                 ConnectorStatus, 0: none), so that the asker can route to the next
                 module of the chain
    TARGETS 66   hold these: n u8 (1..8), then n times (DOF index u8, target i16 in
                 hundredths of a degree), DOF indices strictly ascending
    END 67       the motion is over: the joints are your program's again
    SET_OFF 68   for a foot about to be released (``reach_and_dock``): come to this face
                 on your own, by the overhead tracker. The target's module index u16 (its
                 tracker marker) and connector u8 (1..15); ``body``: n u8 (1..32), then n
                 u16, the markers up the target's robot from the target (the trip's
                 polyline); ``others``: n u8 (0..32), then n u16, the markers off the path
                 (the trip keeps clear of them). No marker twice in body and others.
    69..127      reserved for later motion frames: a DecodeError

An outward frame with ``hops`` h < n is passed on by the module it reached through
``route[h][0]`` with ``hops`` h + 1; with h = n it is for that module. It must come in where
the route says (``route[h - 1] == (sender, connector)``), or the module drops it. A report
with ``left`` k > 0 is sent through ``route[k - 1][1]`` with ``left`` k - 1; with k = 0 it is
the asker's.

**Lost, late and stale frames.** ``seq`` goes up by one each frame the asker sends in a
motion (modulo 2**16, compared as RFC 1982 serial numbers: a frame is newer when it is at
most 32767 ahead): a member keeps the newest seq it took of each motion and ignores anything
not newer (a late TARGETS never undoes a later one); the asker takes an ANGLES only for an ASK
it still waits for, and sees a lost frame as an ASK unanswered (it asks again) or as a gap in
nothing (a TARGETS lost is repeated by the next cycle's). A member no frame of its motion
reaches for a while gives its joints back (:mod:`firmware.motion.member`).

Motion frames travel with class 2 (keep-alives' rank on a CAN bus): a program's hormones go
first, and a motion frame a cycle late is one cycle of the same targets. They are longer than
a CAN frame's 8 bytes and go as segment trains, as any family's do.

Every accepted byte string is the canonical encoding of what it decodes to (no trailing
bytes, DOF indices ascending, the class bits the type wants); decoding raises only
:class:`~dh2rt.errors.DecodeError`, naming the field; encoding raises
:class:`~dh2rt.errors.EncodeError` for a message that breaks a wire limit.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, replace
from enum import IntEnum
from typing import NamedTuple

from dh2rt.errors import DecodeError, EncodeError
from dh2rt.wire.fields import FieldReader, Path, check_class, check_range, encode_path, read_header
from dh2rt.wire.frame import CONTROL_FAMILY, FrameKind
from dh2rt.wire.sizes import MAX_CONNECTOR

#: Message types the motion frames own (the control family's reserved range).
MOTION_TYPES = range(64, 128)
#: The class bits motion frames travel with: keep-alives' rank, after the hormones.
MOTION_CLASS = int(FrameKind.KEEPALIVE)
#: Most joints one frame names (a CONRO module has 2).
MAX_JOINTS = 8
#: An angle's unit on the wire: hundredths of a degree, in an i16 (+-327.67 degrees).
CENTI = 100
_I16 = (-(1 << 15), (1 << 15) - 1)
_U16 = (1 << 16) - 1
_HALF = 1 << 15


class MotionType(IntEnum):
    """Byte 1 of a motion frame."""

    ASK = 64
    ANGLES = 65
    TARGETS = 66
    END = 67
    SET_OFF = 68


@dataclass(frozen=True, slots=True)
class Ask:
    """Module at ``route``, tell me your joint angles (answer with the same ``seq``)."""

    motion: int
    seq: int
    route: Path
    hops: int = 0


@dataclass(frozen=True, slots=True)
class Angles:
    """The member at ``route``, module ``module``, measures its joints at ``angles``
    (degrees, DOF1 first) and has its connectors linked to the peers' ``links`` (0: none),
    answering the ASK numbered ``seq``; ``left`` hops of the way back remain."""

    motion: int
    seq: int
    route: Path
    module: int
    angles: tuple[float, ...]
    links: tuple[int, ...] = ()
    left: int = 0


@dataclass(frozen=True, slots=True)
class Targets:
    """Member at ``route``, hold your joints at ``targets`` (degrees by DOF index: 0 is
    DOF1) in place of your program's."""

    motion: int
    seq: int
    route: Path
    targets: tuple[tuple[int, float], ...]
    hops: int = 0


@dataclass(frozen=True, slots=True)
class End:
    """Member at ``route``, the motion is over: your joints are your program's again."""

    motion: int
    seq: int
    route: Path
    hops: int = 0


@dataclass(frozen=True, slots=True)
class SetOff:
    """Member at ``route`` (a foot about to be released), come to connector ``connector`` of
    module ``target`` by your own trip, along ``body`` (the markers up the target's robot,
    the target first) and clear of ``others`` (:mod:`firmware.motion.foot`)."""

    motion: int
    seq: int
    route: Path
    target: int
    connector: int
    body: tuple[int, ...]
    others: tuple[int, ...] = ()
    hops: int = 0


Outward = Ask | Targets | End | SetOff
MotionMessage = Ask | Angles | Targets | End | SetOff

_TYPES: dict[type, MotionType] = {
    Ask: MotionType.ASK,
    Angles: MotionType.ANGLES,
    Targets: MotionType.TARGETS,
    End: MotionType.END,
    SetOff: MotionType.SET_OFF,
}
#: Most markers a SET_OFF's ``body`` or ``others`` names.
MAX_MARKERS = 32


class MotionFrame(NamedTuple):
    """A decoded motion frame and the connector its sender sent it through."""

    sender: int
    message: MotionMessage


def is_motion(payload: bytes) -> bool:
    """Whether an encoded frame is a motion frame (bytes 0 and 1 only): a control frame of a
    type in :data:`MOTION_TYPES`."""
    return len(payload) >= 2 and payload[0] >> 6 == CONTROL_FAMILY and payload[1] in MOTION_TYPES


def message_type(message: MotionMessage) -> MotionType:
    return _TYPES[type(message)]


def newer(seq: int, than: int | None) -> bool:
    """Whether ``seq`` is after ``than`` (None: nothing yet) as RFC 1982 serial numbers of
    16 bits: at most 32767 ahead, modulo 2**16."""
    return than is None or 0 < (seq - than) % (1 << 16) < _HALF


def next_seq(seq: int) -> int:
    return (seq + 1) & _U16


def onward(message: Outward) -> Outward:
    """An outward frame as a module passes it on: one hop further."""
    return replace(message, hops=message.hops + 1)


def back(message: Angles) -> Angles:
    """A report as a module sends it one hop back towards the asker."""
    return replace(message, left=message.left - 1)


def to_centi(name: str, degrees: float) -> int:
    """An angle as the wire carries it; EncodeError naming ``name`` beyond an i16."""
    value = round(degrees * CENTI)
    if not _I16[0] <= value <= _I16[1]:
        raise EncodeError(f"{name} {degrees!r} degrees is outside +-{_I16[1] / CENTI}")
    return value


# ---------------------------------------------------------------- encoding


def encode(sender: int, message: MotionMessage) -> bytes:
    """The frame carrying ``message`` sent through connector ``sender``."""
    check_range("sender connector", sender, 1, MAX_CONNECTOR)
    kind = _TYPES.get(type(message))
    if kind is None:  # a caller's mistake the type checker did not catch
        raise EncodeError(f"not a motion message: {message!r}")
    check_range("motion", message.motion, 0, _U16)
    check_range("seq", message.seq, 0, _U16)
    check_range("route length", len(message.route), 1, 255)
    at = message.left if isinstance(message, Angles) else message.hops
    check_range("hops left" if isinstance(message, Angles) else "hops", at, 0, len(message.route))
    out = bytearray((CONTROL_FAMILY << 6 | MOTION_CLASS << 4 | sender, kind))
    out += struct.pack(">HHB", message.motion, message.seq, at) + encode_path(message.route)
    if isinstance(message, Angles):
        check_range("module", message.module, 0, _U16)
        check_range("number of angles", len(message.angles), 1, MAX_JOINTS)
        out += struct.pack(">HB", message.module, len(message.angles))
        for i, a in enumerate(message.angles):
            out += struct.pack(">h", to_centi(f"angle of DOF{i + 1}", a))
        check_range("number of links", len(message.links), 0, MAX_CONNECTOR)
        out.append(len(message.links))
        for c in message.links:
            check_range("a link's connector", c, 0, MAX_CONNECTOR)
            out.append(c)
    elif isinstance(message, Targets):
        check_range("number of targets", len(message.targets), 1, MAX_JOINTS)
        dofs = [dof for dof, _ in message.targets]
        if dofs != sorted(set(dofs)):
            raise EncodeError(f"target DOF indices {dofs} are not strictly ascending")
        out.append(len(message.targets))
        for dof, target in message.targets:
            check_range("target DOF index", dof, 0, MAX_JOINTS - 1)
            out += struct.pack(">Bh", dof, to_centi(f"target of DOF{dof + 1}", target))
    elif isinstance(message, SetOff):
        check_range("target module", message.target, 0, _U16)
        check_range("target connector", message.connector, 1, MAX_CONNECTOR)
        _check_markers(message.body, message.others, EncodeError)
        out += struct.pack(">HB", message.target, message.connector)
        for markers in (message.body, message.others):
            out.append(len(markers))
            for m in markers:
                check_range("marker", m, 0, _U16)
                out += struct.pack(">H", m)
    return bytes(out)


def _check_markers(
    body: tuple[int, ...], others: tuple[int, ...], error: type[Exception], what: str = "SET_OFF"
) -> None:
    if not 1 <= len(body) <= MAX_MARKERS:
        raise error(f"{what}: {len(body)} markers in body; 1..{MAX_MARKERS}")
    if len(others) > MAX_MARKERS:
        raise error(f"{what}: {len(others)} markers in others; at most {MAX_MARKERS}")
    if len(set(body) | set(others)) != len(body) + len(others):
        raise error(f"{what}: a marker named twice in body {list(body)} and others {list(others)}")


# ---------------------------------------------------------------- decoding


def decode(data: bytes) -> MotionFrame:
    """Decode one whole motion frame; raises DecodeError for anything else."""
    data = bytes(data)
    sender, type_byte = read_header(data, CONTROL_FAMILY, "motion frame")
    if type_byte not in MOTION_TYPES:
        raise DecodeError(f"motion frame: message type {type_byte} is not a motion frame's (64..127)")
    try:
        kind = MotionType(type_byte)
    except ValueError:
        # as dh2rt.wire.operator says it of the range: one message whichever codec reads it
        reserved = f"control frame: message type {type_byte} is reserved (docking motion, not yet defined)"
        raise DecodeError(reserved) from None
    what = f"motion frame {kind.name}"
    check_class(data, what, MOTION_CLASS)
    r = FieldReader(data, what)
    motion, seq, at = r.unpack(">HHB", "motion, seq and hops")
    route = r.path("route")
    if not route:
        raise DecodeError(f"{what}: an empty route (the asker is no member of its motion)")
    if at > len(route):
        raise DecodeError(f"{what}: hops {at} beyond a {len(route)}-hop route")
    message: MotionMessage
    if kind is MotionType.ANGLES:
        module, n = r.unpack(">HB", "module and number of angles")
        _check_count(what, "angles", n)
        angles = r.unpack(f">{n}h", "angles")
        (count,) = r.take(1, "number of links")
        if count > MAX_CONNECTOR:
            raise DecodeError(f"{what}: {count} links; a module has at most {MAX_CONNECTOR} connectors")
        links = tuple(r.take(count, "links"))
        if any(c > MAX_CONNECTOR for c in links):
            raise DecodeError(f"{what}: a link names connector {max(links)}, beyond {MAX_CONNECTOR}")
        message = Angles(motion, seq, route, module, tuple(a / CENTI for a in angles), links, at)
    elif kind is MotionType.TARGETS:
        (n,) = r.take(1, "number of targets")
        _check_count(what, "targets", n)
        pairs = [r.unpack(">Bh", "targets") for _ in range(n)]
        dofs = [dof for dof, _ in pairs]
        if dofs != sorted(set(dofs)) or dofs[-1] >= MAX_JOINTS:
            raise DecodeError(f"{what}: target DOF indices {dofs} are not strictly ascending below {MAX_JOINTS}")
        message = Targets(motion, seq, route, tuple((dof, t / CENTI) for dof, t in pairs), at)
    elif kind is MotionType.SET_OFF:
        target, connector = r.unpack(">HB", "target module and connector")
        if not 1 <= connector <= MAX_CONNECTOR:
            raise DecodeError(f"{what}: target connector {connector}, not 1..{MAX_CONNECTOR}")
        body, others = _read_markers(r, "body"), _read_markers(r, "others")
        _check_markers(body, others, DecodeError, what)
        message = SetOff(motion, seq, route, target, connector, body, others, at)
    elif kind is MotionType.ASK:
        message = Ask(motion, seq, route, at)
    else:
        message = End(motion, seq, route, at)
    r.end()
    return MotionFrame(sender, message)


def _read_markers(r: FieldReader, name: str) -> tuple[int, ...]:
    (n,) = r.take(1, f"number of markers in {name}")
    return tuple(r.unpack(f">{n}H", f"markers in {name}")) if n else ()


def _check_count(what: str, name: str, n: int) -> None:
    if not 1 <= n <= MAX_JOINTS:
        raise DecodeError(f"{what}: {n} {name}; a frame carries 1..{MAX_JOINTS}")
