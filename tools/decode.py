"""A capture's frames in DH2 terms: which link and side, what kind of frame, the hormone as
text with its path. CAN frames: segments of a long hormone reassembled per link end, as a
module's transport does (:class:`~dh2rt.wire.can_frames.Reassembler`). Serial link frames:
COBS and CRC-32 undone, lost frames (sent, never delivered) marked. Frames that do not decode
are kept, marked with the reason, so that a capture shows the robot's errors too.

Each link end is decoded with the program its sender announced in its last Hello (matched by
digest among the capture's programs); before any Hello, with the first program."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

from dh2rt.errors import DecodeError
from dh2rt.hormone import Hormone
from dh2rt.profile import CONRO, Profile
from dh2rt.program import CompiledProgram
from dh2rt.wire.can_frames import SINGLE, Reassembler, parse_arbitration_id
from dh2rt.wire.frame import FrameCodec, Hello, KeepAlive, program_digest
from dh2rt.wire.serial_framing import decode_serial
from tools.capture_files import CanRecord, Record
from tools.serial_records import SerialRecord

KINDS = ("hormone", "routed", "keepalive", "hello")


@dataclass(frozen=True, slots=True)
class Hop:
    """One frame of the robot's traffic (or one reassembled hormone)."""

    time: float
    link: int | None
    side: int | None
    kind: str  # hormone, routed, keepalive, hello, segment, or error
    sender: str | None = None  # the connector it was sent through
    text: str = ""  # the hormone as X(A), the beacon's sequence number, the Hello's digest
    hormone: Hormone | None = None
    error: str | None = None
    medium: str = "can"  # can, or serial (an emulated infrared link)
    lost: bool = False  # serial: sent and never delivered (the link dropped it)

    def describe(self, profile: Profile = CONRO) -> str:
        """One line, like candump's but in DH2 terms."""
        label = "ir  " if self.medium == "serial" else "link"  # an infrared (serial) link, or a bus link id
        where = f"{label} {self.link:>4} side {self.side}" if self.link is not None else f"{label}    ? side ?"
        through = f" via {self.sender}" if self.sender else ""
        line = f"{self.time:17.6f}  {where}  {self.kind:<9} {self.text}{through}"
        if self.hormone is not None and self.hormone.path:
            hops = " ".join(f"{profile.connector_name(s)}>{profile.connector_name(r)}" for s, r in self.hormone.path)
            line += f"  path {hops}"
        if self.hormone is not None and self.hormone.route:
            line += "  route " + " ".join(profile.connector_name(c) for c in self.hormone.route)
        if self.lost:
            line += "  !! lost on the link (never delivered)"
        if self.error:
            line += f"  !! {self.error}"
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

    def __init__(self, programs: Sequence[CompiledProgram], profile: Profile | None = None) -> None:
        if not programs:
            raise ValueError("Decoder: no program to name the hormones")
        self.profile = profile or programs[0].profile
        count = self.profile.connector_count
        self._codecs = {program_digest(p.image): FrameCodec(p.vocabulary, count) for p in programs}
        self._default = FrameCodec(programs[0].vocabulary, count)
        self._by_end: dict[tuple[str, int, int], FrameCodec] = {}
        self._reassembler = Reassembler()

    def hops(self, records: Iterable[Record]) -> Iterator[Hop]:
        for rec in records:
            if isinstance(rec, SerialRecord):
                yield self._serial(rec)
            else:
                yield from self._can(rec)

    def _decode(self, key: tuple[str, int, int], payload: bytes) -> tuple[int, Any]:
        codec = self._by_end.get(key, self._default)
        sender, frame = codec.decode(payload)
        if isinstance(frame, Hello):
            self._by_end[key] = self._codecs.get(frame.digest, self._default)
        return sender, frame

    def _hop(self, rec_time: float, key: tuple[str, int, int], payload: bytes, note: str = "") -> Hop:
        medium, link, side = key
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

    def _serial(self, rec: SerialRecord) -> Hop:
        key = ("serial", rec.link, rec.side)
        try:
            payload = decode_serial(rec.wire[:-1] if rec.wire.endswith(b"\x00") else rec.wire)
        except DecodeError as exc:
            what = "lost, and its bytes are corrupted" if rec.lost else "corrupted on the link"
            return Hop(rec.timestamp, rec.link, rec.side, "error", error=f"{what}: {exc}", medium="serial")
        hop = self._hop(rec.timestamp, key, payload)
        return replace(hop, lost=rec.lost) if rec.lost else hop

    def _can(self, rec: CanRecord) -> Iterator[Hop]:
        if not rec.is_extended_id:
            yield Hop(rec.timestamp, None, None, "error", error=f"11-bit id {rec.arbitration_id:#x}: not dh2rt")
            return
        try:
            can_id = parse_arbitration_id(rec.arbitration_id)
        except DecodeError as exc:
            yield Hop(rec.timestamp, None, None, "error", error=str(exc))
            return
        link, side = can_id.link_id, can_id.side
        reassembler = self._reassembler
        corrupted, dropped = reassembler.corrupted, reassembler.dropped
        payload = reassembler.feed(rec.arbitration_id, rec.data)
        if payload is None:
            if reassembler.corrupted > corrupted or reassembler.dropped > dropped:
                yield Hop(rec.timestamp, link, side, "error", error=f"segment {can_id.seq} out of order: lost")
            else:
                yield Hop(rec.timestamp, link, side, "segment", text=f"#{can_id.seq}")
            return
        note = "" if can_id.segment == SINGLE else " (reassembled)"
        yield self._hop(rec.timestamp, ("can", link, side), payload, note)


def decode(records: Iterable[Record], programs: Sequence[CompiledProgram]) -> Iterator[Hop]:
    """Each capture record as a :class:`Hop`; a segmented hormone yields one ``segment`` hop
    per frame and the hormone itself with its last segment."""
    return Decoder(programs).hops(records)
