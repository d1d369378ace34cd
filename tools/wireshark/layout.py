"""The wire layout the Wireshark dissector needs, read off dh2rt's own codec.

Nothing here restates a bit position: each field is found by probing the codec's public
functions (:func:`~dh2rt.wire.can_frames.make_arbitration_id`,
:meth:`~dh2rt.wire.frame.FrameCodec.encode`, :func:`~dh2rt.wire.frame.frame_kind`,
:func:`~dh2rt.wire.can_frames.segment`, :func:`~dh2rt.wire.negotiation.encode_bus`,
:func:`tools.serial_records.pack`, :func:`dh2rt.wire.transfer.encode`) and then checked
against a frame of every kind, so a change to the codec changes the generated dissector, or
stops the generator with :class:`LayoutError`. Transfer messages are read with dump's table
(:mod:`tools.transfer_view`), checked here against a message of each type as the codec
encodes it.
"""

from __future__ import annotations

import dataclasses
import re
import zlib
from functools import reduce
from operator import or_
from typing import Any

from dh2rt.errors import DecodeError, DissectorLayoutError
from dh2rt.hormone import Hormone, HormoneSpec, Vocabulary
from dh2rt.profile import Profile
from dh2rt.wire import can_frames, transfer
from dh2rt.wire.frame import (
    HELLO_DIGEST_BYTES,
    MAX_CONNECTORS,
    WIRE_VERSION,
    Frame,
    FrameCodec,
    FrameKind,
    Hello,
    KeepAlive,
    frame_kind,
)
from dh2rt.wire.negotiation import FIRST_LINK_ID, LAST_LINK_ID, MANAGEMENT_ID, BusMessage, BusOp, encode_bus
from dh2rt.wire.serial_framing import CRC_BYTES, DELIMITER
from tools import serial_records
from tools.decode import KINDS, REFUSED
from tools.transfer_view import SHOWS, VIEWS, WIRE_KINDS, Field, View

#: A field of an integer: its lowest bit and its width in bits.
BitField = dict[str, int]


#: The codec's layout is one the dissector cannot describe.
LayoutError = DissectorLayoutError


def bit_field(mask: int) -> BitField:
    """The shift and width of a contiguous run of set bits."""
    if mask <= 0:
        raise LayoutError(f"mask {mask:#x} has no bits")
    shift = (mask & -mask).bit_length() - 1
    width = (mask >> shift).bit_length()
    if mask >> shift != (1 << width) - 1:
        raise LayoutError(f"mask {mask:#x} is not one run of bits")
    return {"shift": shift, "width": width}


def extract(value: int, field: BitField) -> int:
    """The value of ``field`` in ``value`` (what the dissector's ``bits`` computes)."""
    return (value >> field["shift"]) & ((1 << field["width"]) - 1)


# -- the CAN arbitration id --------------------------------------------------------------

#: Each field of make_arbitration_id and its largest value.
_CAN_LIMITS = {
    "kind": max(FrameKind),
    "segment": can_frames.LAST,
    "seq": can_frames.SEQ_MODULUS - 1,
    "link_id": can_frames.MAX_LINK_ID,
    "side": 1,
}


def can_id_fields() -> dict[str, BitField]:
    """The fields of a 29-bit arbitration id, each probed with its largest value alone."""
    fields: dict[str, BitField] = {}
    for name, limit in _CAN_LIMITS.items():
        values = dict.fromkeys(_CAN_LIMITS, 0) | {name: int(limit)}
        field = bit_field(can_frames.make_arbitration_id(**values))
        if field["width"] != int(limit).bit_length():
            raise LayoutError(f"CAN id field {name}: {field['width']} bits for values up to {limit}")
        fields["link" if name == "link_id" else name] = field
    return fields


# -- the frame's first byte --------------------------------------------------------------


def _probe_codec() -> FrameCodec:
    return FrameCodec(Vocabulary((HormoneSpec(0, "P", ()),)), MAX_CONNECTORS)


def _one_of_each_kind() -> dict[FrameKind, Frame]:
    return {
        FrameKind.HORMONE: Hormone("P"),
        FrameKind.ROUTED: Hormone("P", route=()),
        FrameKind.KEEPALIVE: KeepAlive(0),
        FrameKind.HELLO: Hello(bytes(HELLO_DIGEST_BYTES)),
    }


def header_fields() -> dict[str, BitField]:
    """Version, kind and sender connector in byte 0: the kind as frame_kind reads it, the
    sender as the bits the sender changes, the version as the bits left."""
    kind_mask = reduce(or_, (1 << i for i in range(8) if frame_kind(bytes((1 << i,))) != 0))
    codec = _probe_codec()
    heads = [codec.encode(s, KeepAlive(0))[0] for s in range(1, MAX_CONNECTORS + 1)]
    sender_mask = reduce(or_, (h ^ heads[0] for h in heads))
    version_mask = 0xFF & ~(kind_mask | sender_mask)
    fields = {"version": bit_field(version_mask), "kind": bit_field(kind_mask), "sender": bit_field(sender_mask)}
    _check_header(codec, fields)
    return fields


def _check_header(codec: FrameCodec, fields: dict[str, BitField]) -> None:
    """Every kind, through every connector, reads back as encoded."""
    for kind, frame in _one_of_each_kind().items():
        for sender in (1, MAX_CONNECTORS):
            head = codec.encode(sender, frame)[0]
            got = tuple(extract(head, fields[name]) for name in ("version", "kind", "sender"))
            if got != (WIRE_VERSION, kind, sender):
                raise LayoutError(f"byte 0 of a {kind.name} frame through {sender} reads {got}")


def train_layout() -> dict[str, Any]:
    """A segment train's check, read off a train: CRC-32 of the tag byte and the payload,
    little-endian, after the payload; segment i's seq is the tag plus i."""
    payload = bytes((0xC0,)) + bytes(range(1, 12))
    tag = 61
    frames = can_frames.segment(payload, 1, 0, can_frames.CLASSIC_DATA, tag)
    body = b"".join(f.data for f in frames)
    check = body[len(payload) :]
    seq = can_id_fields()["seq"]
    seqs = [extract(f.arbitration_id, seq) for f in frames]
    if body[: len(payload)] != payload or check != zlib.crc32(bytes((tag,)) + payload).to_bytes(len(check), "little"):
        raise LayoutError("a segment train is not its payload, then CRC-32 of tag and payload, little-endian")
    if seqs != [(tag + i) % can_frames.SEQ_MODULUS for i in range(len(frames))]:
        raise LayoutError(f"a train with tag {tag} numbers its segments {seqs}")
    return {
        "check_bytes": len(check),
        "seq_modulus": can_frames.SEQ_MODULUS,
        "max_train": can_frames.MAX_TRAIN,
        "refused": REFUSED,
    }


def management_layout() -> dict[str, Any]:
    """Link negotiation's management frames: their arbitration id, and data of op (1 byte),
    link id (3 bytes, big-endian) and tag (4 bytes, big-endian), checked against encode_bus."""
    probe = BusMessage(BusOp.HOLD, 0x010203, 0x04050607)
    if encode_bus(probe) != bytes((BusOp.HOLD, 1, 2, 3, 4, 5, 6, 7)):
        raise LayoutError("a management frame is not op, big-endian link id, big-endian tag")
    return {
        "id": MANAGEMENT_ID,
        "bytes": len(encode_bus(probe)),
        "ops": {int(op): op.name for op in BusOp},
        "first_link_id": FIRST_LINK_ID,
        "last_link_id": LAST_LINK_ID,
    }


# -- the serial record -------------------------------------------------------------------


def serial_layout() -> dict[str, Any]:
    """The record header of tools.serial_records and the framing's CRC and delimiter,
    checked against a packed record: magic, version, flags, then a big-endian link id."""
    link = 0x01020304
    record = serial_records.SerialRecord(0.0, link, 1, b"", lost=True, corrupted=False)
    flags = serial_records.FLAG_SIDE | serial_records.FLAG_LOST
    expected = serial_records.MAGIC + bytes((serial_records.VERSION, flags)) + link.to_bytes(4, "big")
    if serial_records.pack(record) != expected or serial_records.HEADER.size != len(expected):
        raise LayoutError("the serial record is not magic, version, flags, big-endian link id")
    for flag in (serial_records.FLAG_SIDE, serial_records.FLAG_LOST, serial_records.FLAG_CORRUPTED):
        bit_field(flag)  # one bit each
    return {
        "magic": serial_records.MAGIC.decode("ascii"),
        "version": serial_records.VERSION,
        "header_bytes": serial_records.HEADER.size,
        "flag_side": serial_records.FLAG_SIDE,
        "flag_lost": serial_records.FLAG_LOST,
        "flag_corrupted": serial_records.FLAG_CORRUPTED,
        "crc_bytes": CRC_BYTES,
        "delimiter": DELIMITER,
    }


# -- transfer frames (flashing) ----------------------------------------------------------

_IMAGE = bytes(range(0xA1, 0xA1 + transfer.IMAGE_ID_BYTES))
#: A message of each type, every field a value of its own, so that fields laid out in
#: another order, or of another width, fail the check.
_SAMPLES: dict[type, transfer.Message] = {
    type(sample): sample
    for sample in (
        transfer.Offer(0x01020304, _IMAGE, 1000, 100, 7, True, ((1, 2), (3, 4))),
        transfer.Request(_IMAGE, 0x0506, 9, True),
        transfer.Segment(0x0708, 0x090A, b"\x0b\x0c"),
        transfer.Ack(0x0D0E, 0x0F10, 0x1112),
        transfer.Decline(_IMAGE, transfer.DeclineReason.NEWER, 0x13141516),
        transfer.Cancel(_IMAGE, "bad-signature"),
        transfer.Commit(_IMAGE, 0x1718191A, 27),
        transfer.CommitAck(_IMAGE),
        transfer.Report(0x1C1D, 0x1E1F, transfer.Outcome.REFUSED, 0x20212223, 2, ((1, 2), (2, 3)), "v", "r\u00e9ason"),
        transfer.ReportAck(0x2425),
    )
}
_INT_BYTES = {"u8": 1, "u16": 2, "u32": 4}


def hop_fields() -> dict[str, BitField]:
    """The two connectors of a path's hop byte, probed through OFFER's path (every value of
    one connector, the other held at 1)."""

    def hop_byte(sent: int, received: int) -> int:
        return transfer.encode(1, transfer.Offer(1, _IMAGE, 1, 1, 0, path=((sent, received),)))[-1]

    every = range(1, transfer.MAX_CONNECTOR + 1)
    sent = reduce(or_, (hop_byte(c, 1) ^ hop_byte(1, 1) for c in every))
    received = reduce(or_, (hop_byte(1, c) ^ hop_byte(1, 1) for c in every))
    return {"sent": bit_field(sent), "received": bit_field(received)}


def _laid_out(view: View, message: transfer.Message, hop: dict[str, BitField]) -> bytes:
    """``message``'s fields as the table lays them out (what the dissector reads)."""
    out = bytearray()
    for field in view.fields:
        value = getattr(message, field.name)
        if field.wire in _INT_BYTES:
            out += int(value).to_bytes(_INT_BYTES[field.wire], "big")
        elif field.wire == "flag":
            out.append(int(value))
        elif field.wire == "path":
            hops = [s << hop["sent"]["shift"] | r << hop["received"]["shift"] for s, r in value]
            out += bytes((len(hops), *hops))
        elif field.wire in ("ascii", "utf8"):
            out += bytes((len(value.encode()),)) + value.encode()
        else:  # image, rest
            out += value
    return bytes(out)


def _proto(field: Field) -> str:
    """The Wireshark field type a field shows as: uint, hex, bool, bytes or string."""
    if field.wire in _INT_BYTES:
        return "string" if field.show == "name" else "hex" if "x" in field.show else "uint"
    return {"flag": "bool", "image": "bytes", "rest": "bytes"}.get(field.wire, "string")


def _head_label(kind: transfer.MessageType, frame: bytes) -> str:
    """What the codec calls a message's fixed fields when the frame ends before them."""
    try:
        transfer.decode(frame[:2])
    except DecodeError as exc:
        found = re.fullmatch(rf"transfer frame {kind.name}: cut short in the (.+) at byte 2", str(exc))
        if found:
            return found.group(1)
    raise LayoutError(f"a {kind.name} cut after its type does not say which fields it lacks")


def _field_entry(field: Field) -> dict[str, Any]:
    if field.wire not in WIRE_KINDS or not (field.show in SHOWS or "%" in field.show):
        raise LayoutError(f"transfer field {field.name}: unknown wire {field.wire!r} or show {field.show!r}")
    entry: dict[str, Any] = {"name": field.name, "wire": field.wire, "show": field.show, "proto": _proto(field)}
    if field.text:
        entry["text"] = field.text
    if field.names is not None:
        entry["names"] = {int(value): value.name.lower() for value in field.names}
    if field.limit is not None:
        entry["limit"] = field.limit
    return entry


def transfer_layout() -> dict[str, Any]:
    """Transfer frames as the dissector reads them: the family in byte 0's version bits,
    and per message type its class (byte 0's kind bits), its fields in wire order as dump's
    table (:data:`tools.transfer_view.VIEWS`) has them, and what the codec calls its fixed
    fields; each checked against the codec's encoding of a sample."""
    header, hop = header_fields(), hop_fields()
    views = {view.kind: view for view in VIEWS}
    if set(views) != set(transfer.MessageType):
        raise LayoutError(f"dump's table has no line for {sorted(set(transfer.MessageType) - set(views))}")
    messages: dict[int, Any] = {}
    protos: dict[str, str] = {}
    for kind, view in views.items():
        sample = _SAMPLES[view.message]
        names = {f.name for f in dataclasses.fields(view.message)}
        if names != {f.name for f in view.fields}:
            raise LayoutError(f"dump's table lists {kind.name} as {[f.name for f in view.fields]}, not {names}")
        frame = transfer.encode(1, sample)
        if extract(frame[0], header["version"]) != transfer.TRANSFER_FAMILY or frame[1] != kind:
            raise LayoutError(
                f"a {kind.name} frame does not start with family {transfer.TRANSFER_FAMILY} and type {int(kind)}"
            )
        if frame[2:] != _laid_out(view, sample, hop):
            raise LayoutError(f"a {kind.name} frame is not its fields laid out as dump's table says")
        fields = [_field_entry(f) for f in view.fields]
        for entry in fields:
            if protos.setdefault(entry["name"], entry["proto"]) != entry["proto"]:
                raise LayoutError(f"transfer field {entry['name']} is a {entry['proto']} and a {protos[entry['name']]}")
        messages[int(kind)] = {
            "name": kind.name,
            "class": extract(frame[0], header["kind"]),
            "head": _head_label(kind, frame),
            "fields": fields,
            "line": view.line,
        }
    return {
        "family": transfer.TRANSFER_FAMILY,
        "image_bytes": transfer.IMAGE_ID_BYTES,
        "max_connector": transfer.MAX_CONNECTOR,
        "max_segment_size": transfer.MAX_SEGMENT_SIZE,
        "hop": hop,
        "messages": messages,
    }


# -- all of it ---------------------------------------------------------------------------


def wire_layout(profile: Profile) -> dict[str, Any]:
    """Everything the dissector reads, for robots of ``profile`` (its connector count sets
    the width of path and route fields)."""
    for kind in FrameKind:
        if KINDS[kind] != kind.name.lower():
            raise LayoutError(f"dump calls frame kind {kind.name} {KINDS[kind]!r}")
    codec = _probe_codec()
    segments = {
        "single": can_frames.SINGLE,
        "first": can_frames.FIRST,
        "middle": can_frames.MIDDLE,
        "last": can_frames.LAST,
    }
    return {
        "wire_version": WIRE_VERSION,
        "header": header_fields(),
        "kinds": {KINDS[k]: int(k) for k in FrameKind},
        "kind_names": {int(k): KINDS[k] for k in FrameKind},
        "keepalive_bytes": len(codec.encode(1, KeepAlive(0))),
        "hello_digest_bytes": HELLO_DIGEST_BYTES,
        "connector_bits": FrameCodec(Vocabulary(()), profile.connector_count).connector_bits,
        "can": can_id_fields(),
        "segments": segments,
        "segment_names": {value: name for name, value in segments.items()},
        "train": train_layout(),
        "management": management_layout(),
        "serial": serial_layout(),
        "transfer": transfer_layout(),
    }
