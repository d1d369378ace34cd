"""CAN frames of a capture in DH2 terms: which link and side, what kind of frame, the hormone
as text with its path; segments of a long hormone reassembled per link end, as a module's
transport does (:class:`~dh2rt.wire.can_frames.Reassembler`). Frames that do not decode are
kept, marked with the reason, so that a capture shows the robot's errors too."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from dh2rt.errors import DecodeError
from dh2rt.hormone import Hormone, Vocabulary
from dh2rt.profile import CONRO, Profile
from dh2rt.wire.can_frames import SINGLE, Reassembler, parse_arbitration_id
from dh2rt.wire.frame import FrameCodec, Hello, KeepAlive
from tools.capture_files import CanRecord

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

    def describe(self, profile: Profile = CONRO) -> str:
        """One line, like candump's but in DH2 terms."""
        where = f"link {self.link:>4} side {self.side}" if self.link is not None else "link    ? side ?"
        through = f" via {self.sender}" if self.sender else ""
        line = f"{self.time:17.6f}  {where}  {self.kind:<9} {self.text}{through}"
        if self.hormone is not None and self.hormone.path:
            hops = " ".join(f"{profile.connector_name(s)}>{profile.connector_name(r)}" for s, r in self.hormone.path)
            line += f"  path {hops}"
        if self.hormone is not None and self.hormone.route:
            line += "  route " + " ".join(profile.connector_name(c) for c in self.hormone.route)
        if self.error:
            line += f"  !! {self.error}"
        return line

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"time": self.time, "link": self.link, "side": self.side, "kind": self.kind}
        if self.sender:
            out["sender"] = self.sender
        if self.text:
            out["text"] = self.text
        if self.hormone is not None:
            out["path"] = [list(hop) for hop in self.hormone.path]
        if self.error:
            out["error"] = self.error
        return out


def decode_can(records: Iterable[CanRecord], vocabulary: Vocabulary, profile: Profile = CONRO) -> Iterator[Hop]:
    """Each capture record as a :class:`Hop`; a segmented hormone yields one ``segment`` hop
    per frame and the hormone itself with its last segment."""
    codec = FrameCodec(vocabulary, profile.connector_count)
    reassembler = Reassembler()
    for rec in records:
        if not rec.is_extended_id:
            yield Hop(rec.timestamp, None, None, "error", error=f"11-bit id {rec.arbitration_id:#x}: not dh2rt")
            continue
        try:
            can_id = parse_arbitration_id(rec.arbitration_id)
        except DecodeError as exc:
            yield Hop(rec.timestamp, None, None, "error", error=str(exc))
            continue
        link, side = can_id.link_id, can_id.side
        corrupted, dropped = reassembler.corrupted, reassembler.dropped
        payload = reassembler.feed(rec.arbitration_id, rec.data)
        if payload is None:
            if reassembler.corrupted > corrupted or reassembler.dropped > dropped:
                yield Hop(rec.timestamp, link, side, "error", error=f"segment {can_id.seq} out of order: lost")
            else:
                yield Hop(rec.timestamp, link, side, "segment", text=f"#{can_id.seq}")
            continue
        try:
            sender, frame = codec.decode(payload)
        except DecodeError as exc:
            yield Hop(rec.timestamp, link, side, "error", error=str(exc))
            continue
        name = profile.connector_name(sender)
        if isinstance(frame, KeepAlive):
            yield Hop(rec.timestamp, link, side, "keepalive", name, f"#{frame.seq}")
        elif isinstance(frame, Hello):
            yield Hop(rec.timestamp, link, side, "hello", name, frame.digest.hex())
        else:
            kind = "routed" if frame.route is not None else "hormone"
            note = "" if can_id.segment == SINGLE else " (reassembled)"
            yield Hop(rec.timestamp, link, side, kind, name, frame.content() + note, frame)
