"""What modules report of an image, and how reports cross one hop towards the entry point.

A module's report (staged, committed, refused, ...) travels back along its name, the path
from the entry point, hop by hop; each hop holds it in an :class:`Outbox` until the next
module acknowledges it. :class:`ModuleReport` is what the entry point keeps of each module.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

from dh2rt.wire.transfer import Outcome, Path, Report

# ---------------------------------------------------------------------------------------------
# Outcomes and reports


#: Outcomes by precedence: a report never replaces one of higher rank about the same module.
RANK = {
    Outcome.WITHHELD: 0,
    Outcome.SILENT: 0,
    Outcome.STAGED: 1,
    Outcome.COMMITTED: 2,
    Outcome.CURRENT: 2,
    Outcome.CONFIRMED: 3,
    Outcome.REFUSED: 4,
    Outcome.REVERTED: 5,
}
#: Outcomes of a module that runs the image.
COMMITTED = frozenset({Outcome.COMMITTED, Outcome.CURRENT, Outcome.CONFIRMED})


def describe_path(path: Path, name: Callable[[int], str] = str) -> str:
    """A module's name: the hops from the entry point, ``sent>received`` each, e.g.
    ``1>1 2>1 2>1`` (the third module of a snake whose first front holds the cable)."""
    return " ".join(f"{name(s)}>{name(r)}" for s, r in path) or "(entry)"


@dataclass(frozen=True, slots=True)
class ModuleReport:
    """What the entry point knows of one module."""

    path: Path
    outcome: Outcome
    version: int
    verdict: str = ""
    reason: str = ""

    @property
    def committed(self) -> bool:
        return self.outcome in COMMITTED

    def describe(self, name: Callable[[int], str] = str) -> str:
        why = f" ({self.verdict}: {self.reason})" if self.verdict or self.reason else ""
        return f"{describe_path(self.path, name)}: {self.outcome.name.lower()}, runs version {self.version}{why}"


# ---------------------------------------------------------------------------------------------
# Reports crossing one hop


@dataclass(slots=True)
class _Entry:
    report: Report
    sent_at: int | None = None
    sends: int = 0  # times sent: each resend waits twice as long (a congested bus drains)


class Outbox:
    """Reports waiting to cross one hop towards the entry point, each until its REPORT_ACK.
    A newer report about the same module replaces an older one of no higher rank."""

    __slots__ = ("_entries", "_seq")

    def __init__(self) -> None:
        self._entries: dict[tuple[int, Path], _Entry] = {}
        self._seq = 0

    def put(self, report: Report) -> None:
        key = (report.tag, report.path)
        old = self._entries.get(key)
        if old is not None and RANK[old.report.outcome] > RANK[report.outcome]:
            return
        self._seq = (self._seq + 1) & 0xFFFF
        self._entries.pop(key, None)
        self._entries[key] = _Entry(_with_seq(report, self._seq))

    def ack(self, seq: int) -> None:
        for key, entry in self._entries.items():
            if entry.report.seq == seq:
                del self._entries[key]
                return

    def due(self, tick: int, rto: int) -> Iterator[_Entry]:
        """Reports to send now: new ones, and unacknowledged ones after ``rto`` ticks,
        doubled for each resend (up to 8 x ``rto``)."""
        for entry in list(self._entries.values()):
            if entry.sent_at is None or tick - entry.sent_at >= rto << min(entry.sends - 1, 3):
                yield entry

    def __len__(self) -> int:
        return len(self._entries)


def _with_seq(r: Report, seq: int) -> Report:
    return Report(r.tag, seq, r.outcome, r.version, r.left, r.path, r.verdict, r.reason)
