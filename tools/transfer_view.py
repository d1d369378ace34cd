"""How flashing's transfer messages read, field by field: one table that ``dh2rt dump``
(:func:`transfer_text`) and the Wireshark dissector (its generated block,
:func:`tools.wireshark.layout.transfer_layout`) both read, so the two show a message alike.

Each message lists its fields in wire order (:mod:`dh2rt.wire.transfer` documents the wire),
each with how it is on the wire and how dump shows it, and a line that puts the shown
fields together. The table names no offset: the dissector reads the fields one after the
other, and the layout checks the table against the codec (a message of each type encoded
by the codec must be its fields laid out as the table says).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum

from dh2rt.wire.transfer import (
    MAX_PATH,
    MAX_REASON,
    MAX_SEGMENT_SIZE,
    MAX_VERDICT,
    MAX_WINDOW,
    Ack,
    Cancel,
    Commit,
    CommitAck,
    Decline,
    DeclineReason,
    Message,
    MessageType,
    Offer,
    Outcome,
    Path,
    Report,
    ReportAck,
    Request,
    Segment,
)

#: How a field is on the wire: an unsigned big-endian integer of 1, 2 or 4 bytes, an image
#: id, a flag byte (bit 0), a path (hop count, then a byte a hop), text (length byte, then
#: ASCII or UTF-8), or the bytes that are left.
WIRE_KINDS = ("u8", "u16", "u32", "image", "flag", "path", "ascii", "utf8", "rest")

#: How dump shows a field: a printf format of an integer (``%d``, ``0x%04x``), or
#: ``hex`` (an image id's bytes), ``name`` (an enum's name, lower case), ``count`` (how
#: many bytes), ``path`` (named hops, or ``(entry point)``), ``ms`` (microseconds as
#: ``in 105.9 ms``, 0 as ``at once``), ``flag`` (``text`` when set, else nothing),
#: ``suffix`` (``, TEXT`` when there is text, else nothing).
SHOWS = ("hex", "name", "count", "path", "ms", "flag", "suffix")


@dataclass(frozen=True, slots=True)
class Field:
    """One field of a message: ``name`` is the message's attribute (and the dissector's
    ``dh2rt.transfer.NAME``)."""

    name: str
    wire: str
    show: str = "%d"
    text: str = ""  # a flag's text when set
    names: type[IntEnum] | None = None  # an enum field's values
    #: The most the decoder takes: of a path, hops; of text or the bytes left, bytes; of an
    #: integer, its value (its least is then 1).
    limit: int | None = None


@dataclass(frozen=True, slots=True)
class View:
    """A message type: its dataclass, its fields in wire order, and dump's line, each
    ``{name}`` the field shown."""

    kind: MessageType
    message: type
    fields: tuple[Field, ...]
    line: str


_IMAGE = Field("image", "image", "hex")
_PATH = Field("path", "path", "path", limit=MAX_PATH)

VIEWS: tuple[View, ...] = (
    View(
        MessageType.OFFER,
        Offer,
        (
            Field("version", "u32"),
            _IMAGE,
            Field("length", "u32"),
            Field("segment_size", "u16"),
            Field("held", "u16"),
            Field("running", "flag", "flag", ", running"),
            _PATH,
        ),
        "OFFER v{version} {image} {length} bytes, segments of {segment_size}, held {held}{running}, path {path}",
    ),
    View(
        MessageType.REQUEST,
        Request,
        (
            _IMAGE,
            Field("next", "u16"),
            Field("window", "u8", limit=MAX_WINDOW),
            Field("probe", "flag", "flag", ", probe"),
        ),
        "REQUEST {image} from #{next}, window {window}{probe}",
    ),
    View(
        MessageType.SEGMENT,
        Segment,
        (Field("tag", "u16"), Field("index", "u16"), Field("data", "rest", "count", limit=MAX_SEGMENT_SIZE)),
        "SEGMENT tag {tag} #{index} ({data} bytes)",
    ),
    View(
        MessageType.ACK,
        Ack,
        (Field("tag", "u16"), Field("next", "u16"), Field("sack", "u16", "0x%04x")),
        "ACK tag {tag} next #{next} sack {sack}",
    ),
    View(
        MessageType.DECLINE,
        Decline,
        (_IMAGE, Field("reason", "u8", "name", names=DeclineReason), Field("version", "u32")),
        "DECLINE {image} {reason} (runs v{version})",
    ),
    View(
        MessageType.CANCEL,
        Cancel,
        (_IMAGE, Field("verdict", "ascii", "%s", limit=MAX_VERDICT)),
        "CANCEL {image}: {verdict}",
    ),
    View(
        MessageType.COMMIT,
        Commit,
        (_IMAGE, Field("remaining_us", "u32", "ms"), Field("hops", "u8")),
        "COMMIT {image} {remaining_us} (hops {hops})",
    ),
    View(MessageType.COMMIT_ACK, CommitAck, (_IMAGE,), "COMMIT_ACK {image}"),
    View(
        MessageType.REPORT,
        Report,
        (
            Field("tag", "u16"),
            Field("seq", "u16"),
            Field("outcome", "u8", "name", names=Outcome),
            Field("version", "u32"),
            Field("left", "u8"),
            _PATH,
            Field("verdict", "ascii", "suffix", limit=MAX_VERDICT),
            Field("reason", "utf8", "suffix", limit=MAX_REASON),
        ),
        "REPORT {outcome} v{version} tag {tag} #{seq}, path {path}, left {left}{verdict}{reason}",
    ),
    View(MessageType.REPORT_ACK, ReportAck, (Field("seq", "u16"),), "REPORT_ACK #{seq}"),
)

_BY_CLASS = {view.message: view for view in VIEWS}


def view_of(message: Message) -> View:
    """The table's entry for ``message``."""
    return _BY_CLASS[type(message)]


def show(field: Field, value: object, name: Callable[[int], str]) -> str:
    """``value`` of ``field`` as dump shows it, connectors named by ``name``."""
    match field.show:
        case "hex":
            assert isinstance(value, bytes)
            return value.hex()
        case "name":
            assert isinstance(value, IntEnum)
            return value.name.lower()
        case "count":
            assert isinstance(value, bytes)
            return str(len(value))
        case "path":
            return path_text(value, name)  # type: ignore[arg-type]
        case "ms":
            assert isinstance(value, int)
            return f"in {value / 1000:.1f} ms" if value else "at once"
        case "flag":
            return field.text if value else ""
        case "suffix":
            return f", {value}" if value else ""
    return field.show % value


def path_text(hops: Path, name: Callable[[int], str]) -> str:
    """A path's hops as ``sent>received``, named by ``name``; an empty one is the entry point."""
    return " ".join(f"{name(s)}>{name(r)}" for s, r in hops) or "(entry point)"


def transfer_text(message: Message, name: Callable[[int], str]) -> str:
    """A transfer message in one short line, as dump prints it (and the dissector shows it):
    its image id in hex and its connectors named by ``name`` (a profile's
    :meth:`~dh2rt.profile.Profile.connector_name`)."""
    view = view_of(message)
    return view.line.format_map({f.name: show(f, getattr(message, f.name), name) for f in view.fields})
