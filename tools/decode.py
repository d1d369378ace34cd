"""A capture's frames in DH2 terms: which link and side, what kind of frame, the hormone as
text with its path. CAN frames: segments of a long hormone reassembled per link end, as a
module's transport does (:class:`~dh2rt.wire.can_frames.Reassembler`): a train whose check
fails (spliced from two hormones, or a piece lost) is marked refused. Serial link frames:
COBS and CRC-32 undone, lost frames (sent, never delivered) marked. Frames that do not decode
are kept, marked with the reason, so that a capture shows the robot's errors too.
Flashing's transfer frames (:mod:`dh2rt.wire.transfer`, the second frame family) show as kind
``transfer``, one line per message in DH2 flash terms (:func:`tools.transfer_view.transfer_text`);
the operator's control frames (:mod:`dh2rt.wire.operator`, the third) as kind ``control``
(:func:`tools.control_view.control_text`), the docking chain's motion frames among them
(:mod:`dh2rt.wire.motion`, types 64..127: :func:`tools.control_view.motion_text`).

Each link end is decoded with the program its sender announced in its last Hello (matched by
digest among the capture's programs); before any Hello, with the first program."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from typing import Any, NamedTuple

from dh2rt.errors import DecodeError
from dh2rt.hormone import Hormone
from dh2rt.profile import CONRO, Profile
from dh2rt.program import CompiledProgram
from dh2rt.wire.can_frames import MAX_LINK_ID, SINGLE, Reassembler, parse_arbitration_id
from dh2rt.wire.frame import FrameCodec, Hello, KeepAlive, program_digest
from dh2rt.wire.motion import decode as decode_motion
from dh2rt.wire.motion import is_motion
from dh2rt.wire.negotiation import MANAGEMENT_ID, decode_bus
from dh2rt.wire.operator import decode as decode_control
from dh2rt.wire.operator import is_control
from dh2rt.wire.serial_framing import decode_serial
from dh2rt.wire.transfer import decode as decode_transfer
from dh2rt.wire.transfer import is_transfer
from tools.capture_reader import CanRecord, Record
from tools.control_view import control_text, motion_text
from tools.serial_records import SerialRecord
from tools.transfer_view import transfer_text

KINDS = ("hormone", "routed", "keepalive", "hello", "link", "transfer", "control")
#: Frames decoded once and remembered (see Decoder._memo); cleared when full, so memory stays
#: bounded whatever the capture.
MEMO_SIZE = 8192
#: How a line of :meth:`Hop.describe` starts: the time (then :meth:`Hop.rest`).
TIME_FORMAT = "%17.6f"
#: What a last segment whose train fails its check says (the Wireshark dissector says it too).
REFUSED = "train refused: its check fails (spliced from two hormones, or a piece lost)"


class Hop(NamedTuple):
    """One frame of the robot's traffic (or one reassembled hormone). Immutable; a named
    tuple rather than a dataclass because a capture makes millions of them."""

    time: float
    link: int | None
    side: int | None
    kind: str  # hormone, routed, keepalive, hello, link, transfer, segment, or error
    sender: str | None = None  # the connector it was sent through
    text: str = ""  # the hormone as X(A), the beacon's sequence number, the Hello's digest, the transfer message
    hormone: Hormone | None = None
    error: str | None = None
    medium: str = "can"  # can, or serial (an emulated infrared link)
    lost: bool = False  # serial: sent and never delivered (the link dropped it)

    def describe(self, profile: Profile = CONRO) -> str:
        """One line, like candump's but in DH2 terms: the time, then :meth:`rest`."""
        return TIME_FORMAT % self.time + self.rest(profile)

    def rest(self, profile: Profile = CONRO) -> str:
        """The line :meth:`describe` gives, after the time (hops alike but in time share it)."""
        _at, link, side, kind, sender, text, hormone, error, medium, lost = self
        label = "ir  " if medium == "serial" else "link"  # an infrared (serial) link, or a bus link id
        through = f" via {sender}" if sender else ""
        # %-formatting: the text an f-string would give, in half the time (a capture has millions)
        if link is not None:
            shown = "-" if side is None else side  # a management frame names a link, no side
            line = "  %s %4d side %s  %-9s %s%s" % (label, link, shown, kind, text, through)  # noqa: UP031
        else:
            line = "  %s    ? side ?  %-9s %s%s" % (label, kind, text, through)  # noqa: UP031
        if hormone is not None:
            if hormone.path:
                name = profile.connector_name
                line += "  path " + " ".join(f"{name(s)}>{name(r)}" for s, r in hormone.path)
            if hormone.route:
                line += "  route " + " ".join(profile.connector_name(c) for c in hormone.route)
        if lost:
            line += "  !! lost on the link (never delivered)"
        if error:
            line += f"  !! {error}"
        return line

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "time": self.time,
            "medium": self.medium,
            "link": self.link,
            "side": self.side,
            "kind": self.kind,
        }
        if self.lost:
            out["lost"] = True
        if self.sender:
            out["sender"] = self.sender
        if self.text:
            out["text"] = self.text
        if self.hormone is not None:
            out["path"] = [list(hop) for hop in self.hormone.path]
        if self.error:
            out["error"] = self.error
        return out


class Decoder:
    """Turns capture records into :class:`Hop` s (see the module's docs)."""

    def __init__(
        self, programs: Sequence[CompiledProgram], profile: Profile | None = None, *, memo: bool = True
    ) -> None:
        """``memo=False`` decodes every frame anew: slower, the same hops (what the memo is checked against)."""
        if not programs:
            raise ValueError("Decoder: no program to name the hormones")
        self.profile = profile or programs[0].profile
        count = self.profile.connector_count
        self._codecs = {program_digest(p.image): FrameCodec(p.vocabulary, count) for p in programs}
        self._default = FrameCodec(programs[0].vocabulary, count)
        self._by_end: dict[tuple[str, int, int], FrameCodec] = {}
        self._reassembler = Reassembler()
        self._rebuilding = False  # whether the reassembler has a payload in the making
        #: A single CAN frame's hop, time aside, by (arbitration id, data) (:meth:`_memo_key`):
        #: a capture repeats the same few frames (hormones, beacons) over and over, and each
        #: is decoded once. Emptied when a Hello changes the codec of a link end, and when full.
        self._memo: dict[tuple[int, bytes], tuple[Any, ...]] = {}
        #: The same for payloads reassembled from segments, by (medium, link, side, payload).
        self._reassembled: dict[tuple[str, int, int, bytes], tuple[Any, ...]] = {}
        #: For :meth:`lines`, the text after the time (:meth:`Hop.rest`): of a frame the memo
        #: holds, by its key (emptied with the memo), and of any hop, by the hop time aside.
        self._rests: dict[tuple[int, bytes], str] = {}
        self._hop_rests: dict[tuple[Any, ...], str] = {}
        self._remembering = memo

    def hops(self, records: Iterable[Record]) -> Iterator[Hop]:
        return map(self._record, records)

    def lines(self, records: Iterable[Record]) -> Iterator[str]:
        """Each record's hop as :meth:`Hop.describe` puts it with the decoder's profile (what
        ``dh2rt dump`` prints), and faster than describing each hop: a frame seen before
        reuses its text, only the time is formatted anew."""
        rests, hop_rests, memo = self._rests, self._hop_rests, self._memo
        for rec in records:
            # a frame seen before? (rests hold only what _memo_key accepts: extended ids, whole frames)
            if type(rec) is CanRecord and rec.is_extended_id and type(rec.data) is bytes and not self._rebuilding:
                rest = rests.get((rec.arbitration_id, rec.data))
                if rest is not None:
                    yield TIME_FORMAT % rec.timestamp + rest
                    continue
            key = self._memo_key(rec)
            hop = self._keyed(rec, key)
            alike = hop[1:]
            rest = hop_rests.get(alike)
            if rest is None:
                rest = hop.rest(self.profile)
                if len(hop_rests) >= MEMO_SIZE:
                    hop_rests.clear()
                hop_rests[alike] = rest
            if key is not None and key in memo:
                rests[key] = rest
            yield TIME_FORMAT % hop.time + rest

    def _memo_key(self, rec: Record) -> tuple[int, bytes] | None:
        """(arbitration id, data) of a whole frame in one CAN frame (a hormone, a beacon, a
        Hello: what the memo keeps), or None."""
        if not self._remembering or isinstance(rec, SerialRecord) or not rec.is_extended_id:
            return None
        can_id = rec.arbitration_id
        if (can_id >> 25) & 3 != SINGLE or not 0 <= can_id < 1 << 29 or can_id == MANAGEMENT_ID:
            return None
        return can_id, rec.data if type(rec.data) is bytes else bytes(rec.data)

    def _record(self, rec: Record) -> Hop:
        return self._keyed(rec, self._memo_key(rec))

    def _keyed(self, rec: Record, key: tuple[int, bytes] | None) -> Hop:
        """The hop of ``rec``, whose :meth:`_memo_key` is ``key``."""
        if key is not None and not self._rebuilding:  # (else a single frame abandons that payload)
            fields = self._memo.get(key)
            if fields is not None:
                return Hop._make((rec.timestamp, *fields))
        if isinstance(rec, SerialRecord):
            return self._serial(rec)
        return self._can(rec, key)

    def _forget(self) -> None:
        self._memo.clear()
        self._reassembled.clear()
        self._rests.clear()

    def _decode(self, key: tuple[str, int, int], payload: bytes) -> tuple[int, Any]:
        codec = self._by_end.get(key, self._default)
        sender, frame = codec.decode(payload)
        if isinstance(frame, Hello):
            announced = self._codecs.get(frame.digest, self._default)
            if announced is not codec:
                self._by_end[key] = announced
                self._forget()  # the memo's hops were decoded with the codecs the ends had then
        return sender, frame

    def _hop(self, rec_time: float, key: tuple[str, int, int], payload: bytes, note: str = "") -> Hop:
        medium, link, side = key
        if is_transfer(payload):
            return self._family(rec_time, key, payload, note, "transfer")
        if is_control(payload):
            return self._family(rec_time, key, payload, note, "control")
        try:
            sender, frame = self._decode(key, payload)
        except DecodeError as exc:
            return Hop(rec_time, link, side, "error", error=str(exc), medium=medium)
        name = self.profile.connector_name(sender)
        if isinstance(frame, KeepAlive):
            return Hop(rec_time, link, side, "keepalive", name, f"#{frame.seq}", medium=medium)
        if isinstance(frame, Hello):
            known = "" if frame.digest in self._codecs else " (a program this capture does not carry)"
            return Hop(rec_time, link, side, "hello", name, frame.digest.hex() + known, medium=medium)
        kind = "routed" if frame.route is not None else "hormone"
        return Hop(rec_time, link, side, kind, name, frame.content() + note, frame, medium=medium)

    def _family(self, rec_time: float, key: tuple[str, int, int], payload: bytes, note: str, kind: str) -> Hop:
        """A frame of flashing (``transfer``: no program names it) or of the operator
        (``control``): that kind, one line in its terms, or ``error`` with why it does not
        decode."""
        medium, link, side = key
        name = self._transfer_connector
        try:
            if kind == "transfer":
                sender, transfer = decode_transfer(payload)
                text = transfer_text(transfer, name)
            elif is_motion(payload):
                sender, motion = decode_motion(payload)
                text = motion_text(motion, name)
            else:
                sender, control = decode_control(payload)
                text = control_text(control, name, {d: codec.vocabulary for d, codec in self._codecs.items()})
        except DecodeError as exc:
            return Hop(rec_time, link, side, "error", error=str(exc), medium=medium)
        return Hop(rec_time, link, side, kind, name(sender), text + note, medium=medium)

    def _transfer_connector(self, index: int) -> str:
        """A connector a transfer frame names: the profile's name, or ``#INDEX`` beyond the
        profile's connectors (its four bits name up to 15; the dissector shows them so too)."""
        return self.profile.connector_name(index) if index <= self.profile.connector_count else f"#{index}"

    def _serial(self, rec: SerialRecord) -> Hop:
        key = ("serial", rec.link, rec.side)
        try:
            payload = decode_serial(rec.wire[:-1] if rec.wire.endswith(b"\x00") else rec.wire)
        except DecodeError as exc:
            what = "lost, and its bytes are corrupted" if rec.lost else "corrupted on the link"
            return Hop(rec.timestamp, rec.link, rec.side, "error", error=f"{what}: {exc}", medium="serial")
        hop = self._hop(rec.timestamp, key, payload)
        return hop._replace(lost=rec.lost) if rec.lost else hop

    def _can(self, rec: CanRecord, key: tuple[int, bytes] | None) -> Hop:
        """One CAN frame: a segment, the hormone its last segment completes, or an error;
        ``key``: its :meth:`_memo_key`."""
        if not rec.is_extended_id:
            return Hop(rec.timestamp, None, None, "error", error=f"11-bit id {rec.arbitration_id:#x}: not dh2rt")
        can_id = rec.arbitration_id
        if not 0 <= can_id < 1 << 29:
            try:
                parse_arbitration_id(can_id)  # it says why
            except DecodeError as exc:
                return Hop(rec.timestamp, None, None, "error", error=str(exc))
        if can_id == MANAGEMENT_ID:  # link negotiation, not a link's frame
            return self._management(rec)
        # the fields parse_arbitration_id would give are read in place: this runs for every frame
        reassembler = self._reassembler
        if (can_id >> 25) & 3 == SINGLE:
            if self._rebuilding:
                reassembler.feed(can_id, rec.data)  # it abandons what was being rebuilt at this end
                self._rebuilding = reassembler.pending
            key = key or (can_id, bytes(rec.data))
            end = ("can", (can_id >> 1) & MAX_LINK_ID, can_id & 1)
            return self._remembered(self._memo, key, rec.timestamp, end, key[1])
        link, side = (can_id >> 1) & MAX_LINK_ID, can_id & 1
        corrupted, dropped, refused = reassembler.corrupted, reassembler.dropped, reassembler.refused
        whole = reassembler.feed(can_id, rec.data)
        self._rebuilding = reassembler.pending
        if whole is None:
            seq = (can_id >> 19) & 63
            if reassembler.refused > refused:
                return Hop(rec.timestamp, link, side, "error", error=f"segment {seq}: {REFUSED}")
            if reassembler.corrupted > corrupted or reassembler.dropped > dropped:
                return Hop(rec.timestamp, link, side, "error", error=f"segment {seq} out of order: lost")
            return Hop(rec.timestamp, link, side, "segment", text=f"#{seq}")
        end = ("can", link, side)
        return self._remembered(self._reassembled, (*end, whole), rec.timestamp, end, whole, " (reassembled)")

    def _remembered(
        self,
        memo: dict[Any, tuple[Any, ...]],
        key: Any,
        at: float,
        end: tuple[str, int, int],
        payload: bytes,
        note: str = "",
    ) -> Hop:
        """The hop of ``payload`` from ``end``: as remembered in ``memo`` under ``key``, or
        decoded and remembered (a Hello is always decoded: it may change its end's codec)."""
        if not self._remembering:
            return self._hop(at, end, payload, note)
        fields = memo.get(key)
        if fields is not None:
            return Hop._make((at, *fields))
        hop = self._hop(at, end, payload, note)
        if hop.kind != "hello":
            if len(memo) >= MEMO_SIZE:
                self._forget()
            memo[key] = hop[1:]
        return hop

    @staticmethod
    def _management(rec: CanRecord) -> Hop:
        """A management frame of link negotiation: kind ``link``, its op, link id and tag."""
        try:
            msg = decode_bus(rec.data)
        except DecodeError as exc:
            return Hop(rec.timestamp, None, None, "error", error=f"link negotiation: {exc}")
        return Hop(rec.timestamp, msg.link_id, None, "link", text=f"{msg.op.name} tag {msg.tag:08x}")


def decode(records: Iterable[Record], programs: Sequence[CompiledProgram]) -> Iterator[Hop]:
    """Each capture record as a :class:`Hop`; a segmented hormone yields one ``segment`` hop
    per frame and the hormone itself with its last segment."""
    return Decoder(programs).hops(records)
