"""Delivering a signed program image over the robot's own links, with no addresses (sans-IO).

One :class:`Rollout` per module, one :class:`Flasher` at the entry point (``dh2rt flash``: a
programming cable on a module's free connector, or a node on the bus). They speak the
transfer frames of :mod:`dh2rt.wire.transfer`; ``docs/flashing.md`` ("Delivery over the
links") has the message tables, the sequence and the rules. In short:

* **Transfer, per hop.** A holder OFFERs the image (version, id, length, segment size, how
  many segments it holds, its path from the entry point) and pushes the first window of
  SEGMENTs; the receiver REQUESTs from the first segment it lacks ("you are my source") and
  ACKs every segment (cumulative, plus a 16-bit selective bitmap). Unacknowledged segments
  go again after ``rto_ticks`` cycles, or at once when a later one was acknowledged. A peer
  silent for ``stall_ticks`` is given up. A module that lost its source (a link drop, a
  restart with the bytes it persisted) *probes* its neighbours (a REQUEST flagged probe);
  they OFFER what they hold, and it takes the rest from the one it is named after (its
  parent), else from the one holding most (nearest the entry point on a tie).
* **Pipelined, checked.** A module offers the image to its other neighbours as soon as it is
  offered it, and forwards each segment as soon as it holds every segment before it, but the
  *last* segment only once its own flash accepted the image: an image a module refuses is
  never complete beyond it (and the module CANCELs what it forwarded).
* **Paced.** Every frame costs link units (``Pacing.cost``: serial bytes, CAN bits); a
  connector (or, on a shared bus, the module) spends at most ``Pacing.budget`` units per
  cycle, so hormone frames keep their cycle. Control frames go before segments.
* **Staged by the host.** When every byte is in and the image id (blake2b of the bytes)
  matches, the Rollout asks the host to :class:`Stage` it (``Flash.stage``) and is told the
  verdict (:meth:`Rollout.staged`). Received bytes are persisted as they come
  (:class:`Persist`) so that a restarted module resumes (``partial=``).
* **Reports, back along the path.** Each module learns its *name*, the path from the entry
  point, from the OFFER it took; its reports (staged, committed, refused with the verdict,
  reverted, ...) travel back hop by hop along that path reversed, each hop acknowledged, as a
  DH2 reply travels along ``path-1``. A module reports *staged* only once every neighbour it
  offered the image to has reported (or declined, or fell silent: then it reports that
  neighbour *silent* by its name) and every attached connector has been heard from (or
  stayed silent for ``stall_ticks``), so the entry point knows the whole robot is staged
  when its own neighbour reports staged. A module that refuses the image reports the
  neighbours it does not pass it on to as *withheld*.
* **The switch.** The entry point then sends COMMIT, unless a module refused the image:
  "switch ``remaining_us`` from when this frame left", with a margin of ``depth + 4``
  cycles. Each module turns that into an instant on its own clock (arrival time + remaining
  - the frame's transit time), floods the commit on at once (each copy stating the time
  remaining when it leaves; re-sent after 1, 2, 4 cycles until acknowledged), and starts the
  new program at its first cycle that begins at or after that instant. Clocks are never
  compared, only their rates; cycle counters are never used. The first module moves the
  instant to the middle of its own cycle, so modules whose cycles are in step switch at the
  same cycle despite per-hop timing errors below half a period. While staged, a neighbour
  on the staged program is tolerated (:meth:`Rollout.tolerated`), and after the switch one
  on the old program, for ``tolerate_ticks`` cycles.
* **Late modules.** The Hello carries the program version; a module offers its running image
  to a neighbour on a lower version, flagged *running*: a module that stages an image a
  neighbour runs (or hears a neighbour's Hello with the staged program's digest) switches at
  once.

Sans-IO: no I/O, no threads, no clock. Time comes from the ``now`` arguments (seconds, any
origin: only differences on one module's clock are used), cycles from calls to ``tick``.
Every input returns the actions it causes, in order; carry them out before the next input.
Garbage is counted (``counters.garbage``) and ignored, never raised.
"""

from __future__ import annotations

import enum
import math
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

from dh2rt.errors import DecodeError, SignedImageError
from dh2rt.pacing import LARGEST_CONTROL, Pacing
from dh2rt.signed_image import parse as parse_image
from dh2rt.wire.transfer import (
    MAX_PATH,
    MAX_VERDICT,
    SACK_BITS,
    Ack,
    Cancel,
    Commit,
    CommitAck,
    Decline,
    DeclineReason,
    Message,
    Offer,
    Outcome,
    Path,
    Report,
    ReportAck,
    Request,
    Segment,
    cut_reason,
    decode,
    encode,
    image_id,
    tag_of,
)

# ---------------------------------------------------------------------------------------------
# Images and programs


@dataclass(frozen=True, slots=True)
class ImageInfo:
    """What an OFFER says of an image, and what a partial image is persisted with."""

    image: bytes
    version: int
    length: int
    segment_size: int

    @property
    def count(self) -> int:
        """Segments in the image."""
        return -(-self.length // self.segment_size)

    @property
    def tag(self) -> int:
        return tag_of(self.image)

    def span(self, index: int) -> tuple[int, int]:
        """Byte offsets of segment ``index``: start, end."""
        start = index * self.segment_size
        return start, min(start + self.segment_size, self.length)


@dataclass(frozen=True, slots=True)
class Program:
    """A program a module runs: its version, its Hello digest, and the signed image it came
    from (None when the module cannot offer it, e.g. an unsigned development program)."""

    version: int
    digest: bytes
    image: bytes | None = None
    ident: bytes | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        object.__setattr__(self, "ident", None if self.image is None else image_id(self.image))

    @classmethod
    def from_image(cls, data: bytes) -> Program:
        """The program of a signed (or unsigned) image; raises SignedImageError."""
        parsed = parse_image(data)
        return cls(parsed.version, parsed.digest, bytes(data))


@dataclass(frozen=True, slots=True)
class Partial:
    """An image received in part: its info and the bytes of its first segments (what the
    :class:`Persist` actions wrote), given back to a restarted module."""

    info: ImageInfo
    data: bytes


# ---------------------------------------------------------------------------------------------
# Configuration


@dataclass(frozen=True, slots=True)
class Timing:
    """Timing in cycles (calls to ``tick``) and the transfer window.

    ``rto_ticks``: an unacknowledged segment, OFFER or REPORT goes again after this many.
    ``stall_ticks``: a peer that answered nothing this long is given up (a transfer to it
    stalls, a source is replaced). ``window``: segments in flight per hop. ``linger_ticks``:
    COMMITs are re-sent this long after the switch instant. ``tolerate_ticks``: after its
    switch, a module tolerates neighbours on its old program this long."""

    rto_ticks: int = 3
    stall_ticks: int = 25
    window: int = 8
    linger_ticks: int = 50
    tolerate_ticks: int = 3

    def __post_init__(self) -> None:
        if self.rto_ticks < 1 or self.stall_ticks <= 2 * self.rto_ticks:
            raise ValueError(f"need rto_ticks >= 1 and stall_ticks > 2 * rto_ticks, got {self}")
        if not 1 <= self.window <= 64 or self.linger_ticks < 0 or self.tolerate_ticks < 1:
            raise ValueError(f"need window in 1..64, linger_ticks >= 0 and tolerate_ticks >= 1, got {self}")


# ---------------------------------------------------------------------------------------------
# Actions


@dataclass(frozen=True, slots=True)
class Send:
    """Send this transfer frame through ``connector``."""

    connector: int
    data: bytes


@dataclass(frozen=True, slots=True)
class Persist:
    """Write ``data`` at ``offset`` of the partial image ``info`` names (offset 0: start a
    new one, dropping any other), durably: a restarted module resumes from it."""

    info: ImageInfo
    offset: int
    data: bytes


@dataclass(frozen=True, slots=True)
class DropPartial:
    """The partial image is no longer needed (staged, refused, superseded or corrupt)."""


@dataclass(frozen=True, slots=True)
class Stage:
    """Every byte is in: stage ``data`` (``Flash.stage``) and tell :meth:`Rollout.staged`."""

    info: ImageInfo
    data: bytes


@dataclass(frozen=True, slots=True)
class Switch:
    """Start the staged program this cycle (``Flash.boot`` boots it on trial), then announce
    it with a Hello carrying ``program.version`` and ``program.digest``."""

    program: Program


@dataclass(frozen=True, slots=True)
class Declined:
    """An offered image was refused before a byte of it crossed: its version is lower than
    the one here (``rollback``), or another program runs on trial (``busy``). Told once per
    image, for the host to count and log as its flash counts the images it refuses."""

    version: int
    verdict: str
    reason: str


Action = Send | Persist | DropPartial | Stage | Switch | Declined


# ---------------------------------------------------------------------------------------------
# Outcomes and reports

#: Cycles the commit margin adds to the robot's depth (one per hop: a host that hands frames
#: over at its cycle start forwards a commit a cycle later; the slack covers lost COMMITs,
#: re-sent every cycle, and the first module's move of the instant to its mid-cycle).
COMMIT_SLACK = 4

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


@dataclass(slots=True)
class RolloutCounters:
    """Totals since the state machine started."""

    frames_in: int = 0
    garbage: int = 0  # frames that did not decode
    unwanted: int = 0  # frames about images not in progress here, REQUESTs for images not held
    segments_sent: int = 0
    retransmits: int = 0
    stalls: int = 0  # transfers given up (peer silent)
    corrupt_images: int = 0  # complete images whose id did not match (started over)
    reports_forwarded: int = 0
    reports_dropped: int = 0  # misrouted, or addressed past the entry point
    units_sent: int = 0  # link units (Pacing.cost) of every frame sent


# ---------------------------------------------------------------------------------------------
# The bytes of one image


class _Store:
    """The segments of one image held so far (every one when complete). ``released``: the
    last segment may be forwarded (the image is this module's: staged, running, or the
    entry point's)."""

    __slots__ = ("_segments", "contiguous", "info", "released")

    def __init__(self, info: ImageInfo, prefix: bytes = b"", *, released: bool = False) -> None:
        if len(prefix) > info.length or (len(prefix) % info.segment_size and len(prefix) != info.length):
            raise ValueError(f"a partial image of {len(prefix)} bytes is no run of whole segments of {info}")
        self.info = info
        self.released = released
        self._segments: dict[int, bytes] = {}
        self.contiguous = 0
        for i in range(info.count):
            start, end = info.span(i)
            if end > len(prefix):
                break
            self._segments[i] = bytes(prefix[start:end])
        self._advance()

    @property
    def complete(self) -> bool:
        return self.contiguous == self.info.count

    def add(self, index: int, data: bytes) -> bool:
        """Hold segment ``index``; False if held already. Raises ValueError for a segment
        that does not fit the image."""
        if not 0 <= index < self.info.count:
            raise ValueError(f"segment {index} of an image of {self.info.count}")
        start, end = self.info.span(index)
        if len(data) != end - start:
            raise ValueError(f"segment {index} of {len(data)} bytes, expected {end - start}")
        if index in self._segments:
            return False
        self._segments[index] = bytes(data)
        self._advance()
        return True

    def _advance(self) -> None:
        while self.contiguous in self._segments:
            self.contiguous += 1

    def segment(self, index: int) -> bytes:
        return self._segments[index]

    def run(self, first: int, end: int) -> bytes:
        """The bytes of segments ``first`` .. ``end - 1`` (all held)."""
        return b"".join(self._segments[i] for i in range(first, end))

    def assemble(self) -> bytes:
        return self.run(0, self.info.count)

    def prefix(self) -> bytes:
        """The bytes held from the first on."""
        return self.run(0, self.contiguous)

    def resized(self, segment_size: int) -> _Store:
        """The same bytes cut into segments of ``segment_size`` (the whole ones held)."""
        info = ImageInfo(self.info.image, self.info.version, self.info.length, segment_size)
        data = self.prefix()
        return _Store(info, data if len(data) == info.length else data[: len(data) // segment_size * segment_size])

    def sack(self) -> int:
        """The ACK bitmap: bit i set when segment ``contiguous + 1 + i`` is held."""
        base = self.contiguous + 1
        return sum(1 << i for i in range(SACK_BITS) if base + i in self._segments)

    def available(self, cut_through: bool) -> int:
        """Segments that may be sent on: all once released; else the run held from the
        first, but never the last (or none without cut-through)."""
        if self.released:
            return self.contiguous
        return min(self.contiguous, self.info.count - 1) if cut_through else 0


# ---------------------------------------------------------------------------------------------
# One transfer through one connector


class SenderState(enum.Enum):
    OFFERING = "offering"  # OFFER out, first window pushed; no answer yet
    SENDING = "sending"  # the peer asked for it
    DONE = "done"  # the peer holds every segment
    DECLINED = "declined"  # the peer does not want it
    STALLED = "stalled"  # the peer fell silent: given up
    CANCELLED = "cancelled"  # withdrawn: this module refused the image


_ACTIVE = frozenset({SenderState.OFFERING, SenderState.SENDING})


class _Sender:
    """The outgoing transfer of one image through one connector: offer, window, selective
    acknowledgements, retransmission, stall, and whether the peer has reported since."""

    def __init__(self, info: ImageInfo, offer: Offer, remote: int | None, window: int, tick: int) -> None:
        self.info = info
        self.offer = offer
        self.remote = remote
        self.window = window
        self.state = SenderState.OFFERING
        self.base = 0  # every segment below is acknowledged
        self.sacked: set[int] = set()
        self.next_new = 0  # lowest segment not yet sent since the last rewind
        self.flight: dict[int, int] = {}  # unacknowledged segment -> tick it was last sent
        self.order: dict[int, int] = {}  # segment -> when it was last sent, in send order
        self.fast: set[int] = set()  # to retransmit at once: a later segment arrived
        self.sends = 0
        self.offered_at: int | None = None
        self.heard = tick  # tick the peer last answered
        self.lost_at: int | None = None  # tick the link went down
        self.ended_at: int | None = None
        self.decline: DeclineReason | None = None
        self.reported = False  # the peer's own report came through
        self.silent_reported = False

    # -- state ---------------------------------------------------------------------------------

    @property
    def active(self) -> bool:
        return self.state in _ACTIVE

    @property
    def resolved(self) -> bool:
        """Nothing more is awaited of the peer for the report: it reported, declined as a
        module served by another neighbour, fell silent, or the image was withdrawn."""
        if self.state in (SenderState.STALLED, SenderState.CANCELLED) or self.reported:
            return True
        return self.state is SenderState.DECLINED and self.decline is DeclineReason.HAVE

    def end(self, state: SenderState, tick: int) -> None:
        self.state = state
        self.ended_at = tick
        self.flight.clear()
        self.fast.clear()

    # -- inputs --------------------------------------------------------------------------------

    def on_request(self, nxt: int, window: int, tick: int) -> None:
        """The peer holds every segment below ``nxt`` (it may have lost some: start there)."""
        self.heard = tick
        self.state = SenderState.SENDING
        self.window = max(1, min(self.window, window))
        self.base = min(nxt, self.info.count)
        self.sacked = {i for i in self.sacked if i > self.base}
        self.next_new = self.base
        self.flight.clear()
        self.fast.clear()
        self._check_done(tick)

    def on_ack(self, nxt: int, sack: int, tick: int) -> None:
        self.heard = tick
        if self.state is SenderState.OFFERING:
            self.state = SenderState.SENDING
        if self.state is not SenderState.SENDING:
            return
        if nxt > self.base:
            self.base = min(nxt, self.info.count)
        held = {nxt + 1 + i for i in range(SACK_BITS) if sack >> i & 1}
        self.sacked = {i for i in self.sacked | held if self.base < i < self.info.count}
        for i in [i for i in self.flight if i < self.base or i in self.sacked]:
            del self.flight[i]
        self._mark_holes()
        self._check_done(tick)

    def _mark_holes(self) -> None:
        """Segments sent before one the peer has since acknowledged were lost: resend them."""
        if not self.sacked:
            return
        latest = max(self.order.get(i, -1) for i in self.sacked)
        self.fast = {i for i in self.flight if self.order[i] < latest}

    def _check_done(self, tick: int) -> None:
        if self.base >= self.info.count:
            self.end(SenderState.DONE, tick)

    def reopen(self, nxt: int, tick: int) -> None:
        """Offer again (a probe): the peer holds every segment below ``nxt``; it has not
        taken the image from here (yet)."""
        self.heard = tick
        self.state = SenderState.OFFERING
        self.decline = None
        self.ended_at = None
        self.base = self.next_new = min(nxt, self.info.count)
        self.sacked.clear()
        self.flight.clear()
        self.fast.clear()

    def on_decline(self, reason: DeclineReason, tick: int) -> None:
        self.heard = tick
        self.decline = reason
        self.end(SenderState.DECLINED, tick)

    # -- output --------------------------------------------------------------------------------

    def offer_due(self, tick: int, rto: int) -> bool:
        return self.state is SenderState.OFFERING and (self.offered_at is None or tick - self.offered_at >= rto)

    def next_index(self, tick: int, available: int, rto: int) -> tuple[int, bool] | None:
        """The segment to send now and whether it is a retransmission, or None."""
        if self.state is SenderState.SENDING:
            due = self.fast | {i for i, at in self.flight.items() if tick - at >= rto}
            if due:
                return min(due), True
        elif self.state is not SenderState.OFFERING:
            return None  # pushing before an answer: each segment once
        limit = min(self.base + self.window, available)
        while self.next_new < limit and (self.next_new < self.base or self.next_new in self.sacked):
            self.next_new += 1
        if self.next_new < limit:
            return self.next_new, False
        return None

    def sent(self, index: int, tick: int) -> None:
        self.flight[index] = tick
        self.order[index] = self.sends
        self.sends += 1
        self.fast.discard(index)
        if index == self.next_new:
            self.next_new += 1

    def check_stall(self, tick: int, stall: int) -> bool:
        """Give up a peer silent for ``stall`` ticks (while transferring), or whose link has
        been down that long (while waiting for its report). True when it stalls now."""
        if self.active:
            silent = tick - self.heard >= stall
        elif self.state in (SenderState.DONE, SenderState.DECLINED) and not self.resolved:
            silent = self.lost_at is not None and tick - self.lost_at >= stall
        else:
            return False
        if silent:
            self.end(SenderState.STALLED, tick)
        return silent


# ---------------------------------------------------------------------------------------------
# Reports crossing one hop


@dataclass(slots=True)
class _Entry:
    report: Report
    sent_at: int | None = None
    sends: int = 0  # times sent: each resend waits twice as long (a congested bus drains)


class _Outbox:
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


# ---------------------------------------------------------------------------------------------
# Ports and the commit flood


@dataclass(slots=True)
class _Port:
    """One connector: who is there, what waits to go out, and this cycle's budget."""

    connector: int
    linked: bool = False  # its peer has been heard (a Hello, a transfer frame) and not lost since
    attached_at: int | None = None  # tick it was attached, while it may have a peer not yet heard
    remote: int | None = None  # the peer's connector (from its frames' headers)
    version: int | None = None  # the peer's program, from its Hello
    digest: bytes | None = None
    queue: deque[bytes] = field(default_factory=deque)
    sender: _Sender | None = None
    outbox: _Outbox = field(default_factory=_Outbox)
    tokens: int = 0
    free_at: float = -math.inf  # when the frames sent so far would be out, at the budget's rate
    acked: set[bytes] = field(default_factory=set)  # commits the peer has (acknowledged or sent us)
    commits: set[bytes] = field(default_factory=set)  # commits to send it now


@dataclass(slots=True)
class _Flood:
    """A commit known here: the switch instant on this module's clock, and the hop count
    its COMMITs carry on."""

    at: float
    hops: int
    passed_at: int | None = None  # tick the instant passed
    sent: dict[int, tuple[int, int]] = field(default_factory=dict)  # connector -> (tick last sent, sends)


# ---------------------------------------------------------------------------------------------
# What modules and the entry point share


class _Node(ABC):
    """The mechanics a module and the entry point share: ports, pacing, framing, segment
    pumping, the commit flood and the report outboxes. The subclasses own the state machines."""

    def __init__(
        self, connectors: Iterable[int], pacing: Pacing, timing: Timing, *, segment_size: int, cut_through: bool
    ) -> None:
        self.pacing = pacing
        self.timing = timing
        self.segment_size = segment_size
        self.cut_through = cut_through
        self.counters = RolloutCounters()
        #: images declined before a byte crossed (each told once as a Declined action)
        self._declined: set[bytes] = set()
        self._ports = {c: _Port(c) for c in connectors}
        if not self._ports or any(not 1 <= c <= 15 for c in self._ports):
            raise ValueError(f"connectors must be 1..15, got {sorted(self._ports)}")
        self._tick = 0
        self._now = 0.0
        self._last_tick: float | None = None  # ``now`` of the last tick
        self._period: float | None = None  # measured between the last two ticks
        self._shared_tokens = 0
        self._shared_free_at = -math.inf
        self._rotation = 0
        self._floods: dict[bytes, _Flood] = {}
        self._actions: list[Action] = []
        self._check_budget()

    def _check_budget(self) -> None:
        largest = max(self.segment_size + 6, LARGEST_CONTROL)
        if self.pacing.cost(largest) > self.pacing.budget:
            raise ValueError(
                f"a budget of {self.pacing.budget} units per cycle cannot carry the largest transfer frame "
                f"({largest} bytes, {self.pacing.cost(largest)} units)"
            )

    @property
    def tick_count(self) -> int:
        return self._tick

    # -- framing and pacing --------------------------------------------------------------------

    def _send(self, connector: int, message: Message) -> None:
        port = self._ports[connector]
        if port.linked:
            port.queue.append(encode(connector, message))

    def _begin_tick(self, now: float) -> None:
        """A cycle starts: count it, measure the period, refill the budget."""
        self._tick += 1
        self._now = now
        if self._last_tick is not None and now > self._last_tick:
            self._period = now - self._last_tick
        self._last_tick = now
        self._shared_tokens = self.pacing.budget
        for port in self._ports.values():
            port.tokens = self.pacing.budget

    def _spend(self, port: _Port, frame: bytes) -> bool:
        """Take ``frame``'s cost from this cycle's budget and queue its Send, or refuse.

        Two rules: at most ``budget`` units per cycle; and, once the period is known, a
        frame goes out between ticks only if, sent back to back with this cycle's earlier
        frames at the budget's rate (``budget`` units per period, slower than the link), it
        would be out before the next tick (until two ticks have measured the period, frames
        go out at ticks only). The link is then idle when the next cycle's hormone frames go
        out, whenever the transfer frames were sent."""
        cost = self.pacing.cost(len(frame))
        tokens = self._shared_tokens if self.pacing.shared else port.tokens
        if cost > tokens:
            return False
        free_at = self._shared_free_at if self.pacing.shared else port.free_at
        if self._last_tick is None:
            return False
        if self._period is None:
            if self._now > self._last_tick:
                return False  # the period is not known yet: frames go out at ticks only
        else:
            start = max(self._now, self._last_tick, free_at)
            free_at = start + cost * self._period / self.pacing.budget
            if free_at > self._last_tick + self._period * (1 + 1e-9):
                return False
        if self.pacing.shared:
            self._shared_tokens -= cost
            self._shared_free_at = free_at
        else:
            port.tokens -= cost
            port.free_at = free_at
        self.counters.units_sent += cost
        self._actions.append(Send(port.connector, frame))
        return True

    def _flush(self) -> list[Action]:
        """Everything that may go out now, within the budget: per port, queued control frames
        in order, due reports, then segments. Returns the actions of this input."""
        ports = list(self._ports.values())
        self._rotation = (self._rotation + 1) % len(ports)
        for port in ports[self._rotation :] + ports[: self._rotation]:
            if port.linked and self._drain(port):
                self._pump(port)
        out, self._actions = self._actions, []
        return out

    def _drain(self, port: _Port) -> bool:
        """Send due commits, queued control frames and due reports; False when the budget ran out."""
        for image in list(port.commits):
            flood = self._floods[image]
            if not self._spend(port, encode(port.connector, self._commit_message(image, flood))):
                return False
            port.commits.discard(image)
            flood.sent[port.connector] = (self._tick, flood.sent.get(port.connector, (0, 0))[1] + 1)
        while port.queue:
            if not self._spend(port, port.queue[0]):
                return False
            port.queue.popleft()
        for entry in port.outbox.due(self._tick, self.timing.rto_ticks):
            if not self._spend(port, encode(port.connector, entry.report)):
                return False
            entry.sent_at = self._tick
            entry.sends += 1
        return True

    def _pump(self, port: _Port) -> None:
        sender = port.sender
        store = None if sender is None else self._store_for(sender.info.image)
        while sender is not None and store is not None:
            pick = sender.next_index(self._tick, store.available(self.cut_through), self.timing.rto_ticks)
            if pick is None:
                return
            index, again = pick
            frame = encode(port.connector, Segment(sender.info.tag, index, store.segment(index)))
            if not self._spend(port, frame):
                return
            sender.sent(index, self._tick)
            self.counters.segments_sent += 1
            self.counters.retransmits += again

    @abstractmethod
    def _store_for(self, image: bytes) -> _Store | None:
        """The bytes of ``image`` this node can send, if any."""

    # -- senders -------------------------------------------------------------------------------

    def _start_sender(self, port: _Port, store: _Store, *, running: bool) -> _Sender:
        info = store.info
        offer = Offer(info.version, info.image, info.length, info.segment_size, 0, running)
        sender = _Sender(info, offer, port.remote, self.timing.window, self._tick)
        port.sender = sender
        self._offer(port, sender, store)
        return sender

    def _offer(self, port: _Port, sender: _Sender, store: _Store) -> None:
        """OFFER as things stand: the segments held now, this node's name now."""
        o = sender.offer
        held = store.available(self.cut_through)
        path = self._path_of(store)
        self._send(port.connector, Offer(o.version, o.image, o.length, o.segment_size, held, o.running, path))
        sender.offered_at = self._tick

    @abstractmethod
    def _path_of(self, store: _Store) -> Path:
        """This node's name as the OFFERs of ``store``'s image state it."""

    def _tick_senders(self) -> None:
        for port in self._ports.values():
            sender = port.sender
            if sender is None:
                continue
            if sender.check_stall(self._tick, self.timing.stall_ticks):
                self.counters.stalls += 1
            store = self._store_for(sender.info.image)
            if store is not None and port.linked and sender.offer_due(self._tick, self.timing.rto_ticks):
                self._offer(port, sender, store)

    def _on_ack(self, port: _Port, ack: Ack) -> None:
        sender = port.sender
        if sender is None or sender.info.tag != ack.tag:
            self.counters.unwanted += 1
            return
        sender.on_ack(ack.next, ack.sack, self._tick)

    def _on_decline(self, port: _Port, decline: Decline) -> None:
        sender = port.sender
        if sender is None or sender.info.image != decline.image:
            self.counters.unwanted += 1
            return
        sender.on_decline(decline.reason, self._tick)

    # -- links ---------------------------------------------------------------------------------

    def _link(self, port: _Port, remote: int) -> None:
        port.linked = True
        port.attached_at = None
        port.remote = remote
        if port.sender is not None:
            port.sender.lost_at = None
            port.sender.remote = remote

    def _unlink(self, port: _Port) -> None:
        port.linked = False
        port.queue.clear()
        port.commits.clear()
        port.acked.clear()  # it may come back restarted
        if port.sender is not None and port.sender.lost_at is None:
            port.sender.lost_at = self._tick

    # -- the commit flood ----------------------------------------------------------------------

    def _tick_floods(self) -> None:
        """Send each commit again to every neighbour that has not acknowledged it (see
        :meth:`_spread`), until ``linger_ticks`` after its instant."""
        linger = self.timing.linger_ticks
        for image, flood in self._floods.items():
            if flood.passed_at is None and self._now >= flood.at:
                flood.passed_at = self._tick
            if flood.passed_at is None or self._tick - flood.passed_at <= linger:
                self._spread(image, flood)

    def _spread(self, image: bytes, flood: _Flood) -> None:
        """COMMIT to every linked neighbour that lacks it: at once the first time, then a
        cycle later, then 2, 4 cycles later (sent first when the frames go out, so that it
        states the time left when it leaves)."""
        for port in self._ports.values():
            if not port.linked or image in port.acked:
                continue
            last, sends = flood.sent.get(port.connector, (0, 0))
            if not sends or self._tick - last >= 1 << min(sends - 1, 2):
                port.commits.add(image)

    def _commit_message(self, image: bytes, flood: _Flood) -> Commit:
        """The COMMIT as it leaves: the time left from now, or (a host that reads its links
        once a cycle and sends at the tick) from the tick, whichever is later."""
        leaves = max(self._now, self._last_tick if self._last_tick is not None else self._now)
        return Commit(image, max(0, round((flood.at - leaves) * 1e6)), flood.hops)

    def _on_commit_ack(self, port: _Port, ack: CommitAck) -> None:
        port.acked.add(ack.image)
        port.commits.discard(ack.image)


# ---------------------------------------------------------------------------------------------
# A module


class Role(enum.Enum):
    """Where a module stands with the image being rolled out through it."""

    RECEIVING = "receiving"
    STAGING = "staging"  # every byte in; the host is staging it
    STAGED = "staged"  # in the flash; waiting for the switch
    SWITCHED = "switched"  # running it (on trial until confirmed or reverted)
    CURRENT = "current"  # it ran this image already when it was offered
    REFUSED = "refused"  # its flash refused it, or it would be a rollback
    WITHDRAWN = "withdrawn"  # the neighbour it came from refused it


#: Roles in which the module holds the image's bytes and passes them on.
_HOLDING = frozenset({Role.RECEIVING, Role.STAGING, Role.STAGED, Role.CURRENT, Role.SWITCHED})
#: Roles that report themselves once every neighbour offered the image has, and as what.
_RESOLVED_OUTCOME = {Role.STAGED: Outcome.STAGED, Role.CURRENT: Outcome.CURRENT, Role.SWITCHED: Outcome.COMMITTED}


@dataclass(slots=True)
class _Refusal:
    """An image this module will not take: why, and (when it was offered under a name) which
    neighbours it has reported as withheld, so that neighbours linked later are too."""

    verdict: str
    reason: str
    tag: int
    name: Path | None = None
    exclude: int | None = None  # the neighbour it came from
    told: set[int] = field(default_factory=set)  # connectors reported withheld (or that report themselves)


@dataclass(slots=True)
class _Job:
    """The image being rolled out through this module."""

    store: _Store
    role: Role
    name: Path | None  # the path from the entry point (known from an OFFER)
    source: int | None  # the connector bytes come from
    running_offer: bool  # a neighbour runs it: switch once staged
    progress: int  # tick the store last grew
    score: tuple[int, int] = (-1, 0)  # the source's OFFER: segments held, minus its depth
    program: Program | None = None  # once staged
    reported: int = -1  # rank of the last outcome reported about itself
    requested: int | None = None  # tick a REQUEST last went out without a source

    @property
    def info(self) -> ImageInfo:
        return self.store.info


class Rollout(_Node):
    """The rollout state machine of one module (see the module docstring).

    ``connectors``: the module's connector numbers. ``running``: the program it runs (with
    its signed image, so that it can offer it). ``partial``: an image received in part
    before a restart (what :class:`Persist` wrote); ``staged``: an image staged before a
    restart and not yet switched to (boot the confirmed program then, not the trial).
    ``reverted``: ids of images reverted here (never taken again). ``latency``: the
    transit time of a COMMIT frame on this module's links, in seconds (its bytes at the
    link's rate), subtracted from the commit's remaining time. ``cut_through``: forward
    segments while later ones arrive (False: store and forward)."""

    def __init__(
        self,
        connectors: Iterable[int],
        running: Program,
        *,
        pacing: Pacing,
        timing: Timing | None = None,
        segment_size: int = 128,
        partial: Partial | None = None,
        staged: bytes | None = None,
        reverted: Iterable[bytes] = (),
        latency: float = 0.0,
        cut_through: bool = True,
    ) -> None:
        super().__init__(connectors, pacing, timing or Timing(), segment_size=segment_size, cut_through=cut_through)
        self.running = running
        self.latency = latency
        self._previous: Program | None = None
        self._switched_at: int | None = None
        self._on_trial = False
        self._running_store = self._whole(running)
        self._refused: dict[bytes, _Refusal] = {}
        self._reverted = set(reverted)
        self._job: _Job | None = None
        if staged is not None:
            self._resume_staged(staged)
        elif partial is not None:
            self._job = _Job(_Store(partial.info, partial.data), Role.RECEIVING, None, None, False, 0)

    def _whole(self, program: Program) -> _Store | None:
        if program.image is None:
            return None
        info = ImageInfo(image_id(program.image), program.version, len(program.image), self.segment_size)
        store = _Store(info, program.image, released=True)
        return store

    def _resume_staged(self, data: bytes) -> None:
        program = Program.from_image(data)
        store = self._whole(program)
        assert store is not None
        self._job = _Job(store, Role.STAGED, None, None, False, 0, program=program)

    # -- read-only -----------------------------------------------------------------------------

    @property
    def role(self) -> Role | None:
        """This module's role in the image being rolled out through it (None: none)."""
        return None if self._job is None else self._job.role

    @property
    def name(self) -> Path | None:
        """This module's path from the entry point, once an OFFER told it."""
        return None if self._job is None else self._job.name

    @property
    def received(self) -> int:
        """Bytes of the incoming image held from the first (the whole image once complete)."""
        if self._job is None:
            return 0
        store = self._job.store
        return store.info.span(store.contiguous - 1)[1] if store.contiguous else 0

    def tolerated(self) -> frozenset[bytes]:
        """Program digests besides its own that this module's liveness machine should accept
        from a neighbour now: the staged program's while staged, the previous program's for
        ``tolerate_ticks`` cycles after the switch."""
        out: set[bytes] = set()
        job = self._job
        if job is not None and job.role is Role.STAGED and job.program is not None:
            out.add(job.program.digest)
        recent = self._switched_at is not None and self._tick - self._switched_at <= self.timing.tolerate_ticks
        if recent and self._previous is not None:
            out.add(self._previous.digest)
        return frozenset(out)

    # -- inputs --------------------------------------------------------------------------------

    def hello(self, connector: int, remote: int, version: int | None, digest: bytes, now: float) -> list[Action]:
        """A Hello from the neighbour on ``connector`` (sent through its ``remote``): its
        program's version (None: a Hello without one) and digest. Call it for every Hello,
        verified or refused."""
        self._now = now
        port = self._port(connector)
        self._link(port, remote)
        port.version, port.digest = version, digest
        job = self._job
        if job is not None and job.role is Role.STAGED and job.program is not None and job.program.digest == digest:
            job.running_offer = True  # the neighbour switched: so do we
        self._offer_job(port)
        self._offer_running(port)
        if self._job is not None and self._job.role is Role.RECEIVING and self._job.source is None:
            self._request(port)
        for refusal in self._refused.values():
            self._withhold(refusal)
        return self._finish()

    def attach(self, connector: int, now: float) -> list[Action]:
        """``connector`` is attached (docked, or its port opened): a neighbour may be there.
        Until its Hello comes (at most ``stall_ticks`` cycles), this module does not report
        the image staged: that neighbour may still need it."""
        self._now = now
        port = self._port(connector)
        if not port.linked:
            port.attached_at = self._tick
        return self._finish()

    def detach(self, connector: int, now: float) -> list[Action]:
        """``connector`` was undocked: nobody is there."""
        self._now = now
        port = self._port(connector)
        port.attached_at = None
        self._lose(port)
        return self._finish()

    def link_down(self, connector: int, now: float) -> list[Action]:
        """The link on ``connector`` fell silent (liveness): the neighbour may come back."""
        self._now = now
        port = self._port(connector)
        self._lose(port)
        port.attached_at = self._tick
        return self._finish()

    def _lose(self, port: _Port) -> None:
        self._unlink(port)
        job = self._job
        if job is not None and job.source == port.connector:
            job.source = None

    def receive(self, connector: int, data: bytes, now: float) -> list[Action]:
        """A transfer frame received through ``connector`` (``now``: when it arrived)."""
        self._now = now
        self.counters.frames_in += 1
        try:
            sender, message = decode(data)
        except DecodeError:
            self.counters.garbage += 1
            return self._finish()
        port = self._port(connector)
        if not port.linked or port.remote != sender:
            self._link(port, sender)
        self._dispatch(port, sender, message)
        return self._finish()

    def staged(self, accepted: bool, verdict: str, reason: str, now: float) -> list[Action]:
        """The host's answer to :class:`Stage`: ``Flash.stage``'s accepted, verdict and reason."""
        self._now = now
        job = self._job
        if job is None or job.role is not Role.STAGING:
            raise ValueError("staged() answers a Stage action, and none is outstanding")
        self._actions.append(DropPartial())
        if accepted:
            self._accept(job)
        else:
            self._refuse(job, verdict, reason)
        return self._finish()

    def tick(self, now: float) -> list[Action]:
        """Once per cycle, at its start: the switch (first), retransmissions, stalls,
        commits, reports; then whatever this cycle's budget lets out."""
        self._begin_tick(now)
        self._maybe_switch()
        self._tick_senders()
        self._report_silent()
        self._tick_job()
        self._tick_floods()
        return self._finish()

    def confirmed(self, now: float) -> list[Action]:
        """The program on trial was confirmed (``Flash.confirm``)."""
        self._now = now
        self._on_trial = False
        job = self._job
        if job is not None and job.role is Role.SWITCHED:
            self._report_self(job, Outcome.CONFIRMED)
        return self._finish()

    def reverted(self, reason: str, now: float) -> list[Action]:
        """The program on trial was given up (``Flash.reject``): the previous one runs again."""
        self._now = now
        self._on_trial = False
        job = self._job
        if job is None or job.role is not Role.SWITCHED or self._previous is None:
            raise ValueError("reverted() without a switched program")
        self._reverted.add(job.info.image)
        self.running, self._previous = self._previous, None
        self._running_store = self._whole(self.running)
        job.role = Role.REFUSED
        self._refused[job.info.image] = _Refusal("reverted", cut_reason(reason), job.info.tag)
        self._report_self(job, Outcome.REVERTED, "reverted", reason)
        return self._finish()

    # -- dispatch ------------------------------------------------------------------------------

    def _dispatch(self, port: _Port, sender: int, m: Message) -> None:
        match m:
            case Offer():
                self._on_offer(port, sender, m)
            case Request():
                self._on_request(port, m)
            case Segment():
                self._on_segment(port, m)
            case Ack():
                self._on_ack(port, m)
            case Decline():
                self._on_decline(port, m)
            case Cancel():
                self._on_cancel(port, m)
            case Commit():
                self._on_commit(port, m)
            case CommitAck():
                self._on_commit_ack(port, m)
            case Report():
                self._on_report(port, sender, m)
            case ReportAck():
                port.outbox.ack(m.seq)

    def _port(self, connector: int) -> _Port:
        try:
            return self._ports[connector]
        except KeyError:
            raise ValueError(f"connector {connector!r} is not one of {sorted(self._ports)}") from None

    def _path_of(self, store: _Store) -> Path:
        job = self._job
        if job is not None and job.info.image == store.info.image and job.name is not None:
            return job.name
        return ()

    def _store_for(self, image: bytes) -> _Store | None:
        job = self._job
        if job is not None and job.info.image == image and job.role in _HOLDING:
            return job.store
        store = self._running_store
        return store if store is not None and store.info.image == image else None

    # -- offers --------------------------------------------------------------------------------

    def _on_offer(self, port: _Port, sender: int, offer: Offer) -> None:
        info = ImageInfo(offer.image, offer.version, offer.length, offer.segment_size)
        name = (*offer.path, (sender, port.connector))
        if self._job is not None and self._from_parent(self._job, info, port.connector):
            self._offered_again(port, self._job, name)
            return
        reason = self._judge(info, offer, port.connector, name)
        if reason is not None or len(name) > MAX_PATH:
            self._decline(port, info, name, reason or DeclineReason.HAVE)
            return
        job = self._job
        if job is not None and job.info.image == info.image and job.role is Role.RECEIVING:
            self._change_source(job, port, offer, name)
        else:
            if job is not None:
                self._drop(job)
            job = _Job(_Store(info), Role.RECEIVING, name, port.connector, offer.running, self._tick, _score(offer))
            self._job = job
            for other in self._ports.values():
                self._offer_job(other)
        self._send(port.connector, Request(info.image, job.store.contiguous, self.timing.window))

    def _change_source(self, job: _Job, port: _Port, offer: Offer, name: Path) -> None:
        """Take the rest of the image from ``port``; the neighbour left (if any) is told, so
        that it does not wait for this module. The name follows the source until this
        module has reported under one."""
        old = job.source
        if old is not None and old != port.connector:
            self._send(old, Decline(job.info.image, DeclineReason.HAVE, self.running.version))
        if offer.segment_size != job.info.segment_size:  # the bytes held, cut as this source cuts them
            job.store = job.store.resized(offer.segment_size)
            self._actions.append(Persist(job.info, 0, job.store.prefix()))
        job.source = port.connector
        job.score = _score(offer)
        job.progress = self._tick
        job.running_offer |= offer.running
        if job.name is None or (job.reported < 0 and offer.path):
            named = job.name is None
            job.name = name
            if named:  # its offers until now named nobody: offer again, naming them
                for other in self._ports.values():
                    self._offer_job(other, again=True)

    def _judge(self, info: ImageInfo, offer: Offer, connector: int, name: Path) -> DeclineReason | None:
        """Why this module does not take ``info`` from ``connector`` now (None: it does)."""
        job = self._job
        if job is not None and job.info.image == info.image and job.role is not Role.WITHDRAWN:
            if job.role is Role.RECEIVING and self._better_source(job, offer, connector, name):
                return None
            return DeclineReason.REFUSED if job.role is Role.REFUSED else DeclineReason.HAVE
        if info.image == self.running.ident:
            return DeclineReason.CURRENT
        if info.image in self._reverted:
            return DeclineReason.REVERTED
        if info.image in self._refused:
            return DeclineReason.REFUSED
        if info.version < self.running.version:
            return DeclineReason.NEWER
        if self._on_trial:
            return DeclineReason.BUSY
        if job is not None and job.role in _HOLDING and job.role is not Role.CURRENT:
            return DeclineReason.NEWER if info.version <= job.info.version else None
        return None

    def _from_parent(self, job: _Job, info: ImageInfo, connector: int) -> bool:
        """An OFFER of the job's image from its source (or, without one, anyone) to a module
        that holds it whole: the same image flashed again, or the offer repeated."""
        return (
            job.info.image == info.image
            and job.role in (Role.STAGED, Role.CURRENT, Role.SWITCHED)
            and (job.source is None or connector == job.source)
        )

    def _offered_again(self, port: _Port, job: _Job, name: Path) -> None:
        """Answer with what it holds (the sender finishes at once), offer the neighbours
        again, and report once they have: a new entry point hears of the whole robot."""
        job.source = port.connector
        job.name = job.name or name
        job.reported = -1
        self._send(port.connector, Request(job.info.image, job.store.contiguous, self.timing.window))
        for other in self._ports.values():
            self._offer_job(other, again=True)

    def _better_source(self, job: _Job, offer: Offer, connector: int, name: Path) -> bool:
        """Whether to take the image from ``connector``: it is the source, or the neighbour
        this module is named after (its parent, back after a restart or a link drop); or it
        holds more than this module and there is no source, or the source made no progress
        for ``stall_ticks``, or it holds more than the source held when it offered (nearer
        the entry point on a tie)."""
        if connector == job.source or name == job.name:
            return True
        if offer.held <= job.store.contiguous:
            return False  # nothing to give yet (a REQUEST wakes it once it has)
        if job.source is None:
            return True
        stale = self._tick - job.progress >= self.timing.stall_ticks
        return stale or _score(offer) > job.score

    def _decline(self, port: _Port, info: ImageInfo, name: Path, reason: DeclineReason) -> None:
        """Decline an offer, and answer the offerer's wait for a report: every decline but
        HAVE (another neighbour serves this module) is reported under the offer's name."""
        self._send(port.connector, Decline(info.image, reason, self.running.version))
        if reason is DeclineReason.HAVE:
            return
        if reason is DeclineReason.CURRENT:
            self._join_current(port, info, name)
            return
        verdict, why = self._refusal(info, reason)
        if reason in (DeclineReason.NEWER, DeclineReason.BUSY) and info.image not in self._declined:
            self._declined.add(info.image)
            self._actions.append(Declined(info.version, verdict, why))
        outcome = Outcome.REVERTED if reason is DeclineReason.REVERTED else Outcome.REFUSED
        self._report(outcome, name, len(name), info.tag, verdict, why)
        if reason is DeclineReason.NEWER and info.image not in self._refused and not self._holds_newer(info):
            refusal = _Refusal(verdict, why, info.tag, name, port.connector)  # a rollback: refused for good
            self._refused[info.image] = refusal
            self._withhold(refusal)

    def _refusal(self, info: ImageInfo, reason: DeclineReason) -> tuple[str, str]:
        """The verdict and reason a refusal of ``info`` reports."""
        if reason is DeclineReason.NEWER:
            job = self._job
            held = job.info.version if job is not None and self._holds_newer(info) else self.running.version
            return "rollback", f"version {info.version} is lower than version {held} here"
        if reason is DeclineReason.BUSY:
            return "busy", "another program runs on trial"
        refusal = self._refused.get(info.image)
        if refusal is not None:
            return refusal.verdict, refusal.reason
        return ("reverted", "reverted on trial here") if reason is DeclineReason.REVERTED else ("refused", "")

    def _holds_newer(self, info: ImageInfo) -> bool:
        job = self._job
        return job is not None and job.role in _HOLDING and job.info.image != info.image

    def _join_current(self, port: _Port, info: ImageInfo, name: Path) -> None:
        """Offered the image it runs: it takes part as a holder (offers it on, and reports
        itself current once its neighbours have), unless it takes part already. Without the
        image's bytes it cannot pass it on, and reports itself current at once."""
        store = self._running_store
        if self._job is not None and self._job.info.image == info.image:
            return
        if store is None:
            self._report(Outcome.CURRENT, name, len(name), info.tag)
            return
        self._job = _Job(store, Role.CURRENT, name, port.connector, False, self._tick, program=self.running)
        for other in self._ports.values():
            self._offer_job(other)

    def _offer_job(self, port: _Port, *, again: bool = False) -> None:
        """Offer the image being rolled out through this module to the neighbour on ``port``
        (not to its source), unless that neighbour has it in hand already (``again``: unless
        it is taking it now)."""
        job = self._job
        if job is None or job.role not in _HOLDING or not port.linked or port.connector == job.source:
            return
        if job.name is None:
            return  # unnamed (resuming after a restart): it cannot name the modules it would serve
        sender = port.sender
        if sender is not None and sender.info.image == job.info.image and sender.state is SenderState.OFFERING:
            if again:
                self._offer(port, sender, job.store)  # at once, with this module's name now
            return
        if sender is not None and _keeps(sender, job.info, again=again):
            return
        self._start_sender(port, job.store, running=job.role in (Role.CURRENT, Role.SWITCHED))

    def _offer_running(self, port: _Port) -> None:
        """Offer the running image to a neighbour whose Hello states a lower version."""
        store = self._running_store
        if store is None or port.version is None or port.version >= self.running.version:
            return
        sender = port.sender
        if sender is not None and sender.info.version >= self.running.version:
            recent = sender.ended_at is not None and self._tick - sender.ended_at < self.timing.stall_ticks
            if sender.active or recent or sender.state is SenderState.DONE:
                return
        self._start_sender(port, store, running=True)

    def _on_request(self, port: _Port, request: Request) -> None:
        store = self._store_for(request.image)
        if store is None:
            self.counters.unwanted += 1
            return
        sender = port.sender
        if sender is None or sender.info.image != request.image:
            sender = self._start_sender(port, store, running=store is self._running_store)
            if request.probe:
                sender.reopen(request.next, self._tick)
        elif request.probe:
            if sender.state is not SenderState.SENDING:
                sender.reopen(request.next, self._tick)
            self._offer(port, sender, store)
        if not request.probe:
            sender.on_request(request.next, request.window, self._tick)

    # -- segments ------------------------------------------------------------------------------

    def _on_segment(self, port: _Port, segment: Segment) -> None:
        job = self._job
        if job is None or job.info.tag != segment.tag:
            self.counters.unwanted += 1
            return
        store = job.store
        if job.role is not Role.RECEIVING:
            self._send(port.connector, Ack(segment.tag, store.contiguous, 0))
            return
        before = store.contiguous
        try:
            new = store.add(segment.index, segment.data)
        except ValueError:
            self.counters.garbage += 1
            return
        if new:
            job.progress = self._tick
            if job.source is None:
                job.source = port.connector
                job.score = (-1, 0)
        if store.contiguous > before:
            start = job.info.span(before)[0]
            self._actions.append(Persist(job.info, start, store.run(before, store.contiguous)))
        self._send(port.connector, Ack(segment.tag, store.contiguous, store.sack()))
        if store.complete:
            self._complete(job)

    def _complete(self, job: _Job) -> None:
        data = job.store.assemble()
        if image_id(data) != job.info.image:
            self.counters.corrupt_images += 1
            job.store = _Store(job.info)
            self._actions.append(DropPartial())
            if job.source is not None:
                self._send(job.source, Request(job.info.image, 0, self.timing.window))
            return
        job.role = Role.STAGING
        self._actions.append(Stage(job.info, data))

    def _accept(self, job: _Job) -> None:
        job.role = Role.STAGED
        job.store.released = True
        try:
            job.program = Program.from_image(job.store.assemble())
        except SignedImageError:
            job.program = Program(job.info.version, b"", job.store.assemble())
        if any(p.linked and p.digest == job.program.digest for p in self._ports.values()):
            job.running_offer = True  # a neighbour runs it already

    def _refuse(self, job: _Job, verdict: str, reason: str) -> None:
        """The flash refused the image: withdraw what was passed on (a neighbour that took
        it reports itself when the CANCEL reaches it), and report the others withheld."""
        job.role = Role.REFUSED
        verdict = verdict[:MAX_VERDICT]
        refusal = _Refusal(verdict, cut_reason(reason), job.info.tag, job.name, job.source)
        self._refused[job.info.image] = refusal
        for port in self._ports.values():
            sender = port.sender
            if sender is not None and sender.info.image == job.info.image and sender.state is not SenderState.STALLED:
                if sender.state is SenderState.SENDING:
                    refusal.told.add(port.connector)
                sender.end(SenderState.CANCELLED, self._tick)
                self._send(port.connector, Cancel(job.info.image, verdict))
        if job.name is not None:
            self._report_self(job, Outcome.REFUSED, verdict, reason)
            self._withhold(refusal)

    def _withhold(self, refusal: _Refusal) -> None:
        """Report, by name, the linked neighbours this module does not pass a refused image
        on to (once each; called again when a neighbour links)."""
        name = refusal.name
        if name is None:
            return
        for port in self._ports.values():
            if port.connector in refusal.told or port.connector == refusal.exclude:
                continue
            if not port.linked or port.remote is None:
                continue
            refusal.told.add(port.connector)
            path = (*name, (port.connector, port.remote))
            why = f"not passed on: refused at {describe_path(name)}"
            self._report(Outcome.WITHHELD, path, len(name), refusal.tag, refusal.verdict, why, port.version or 0)

    def _on_cancel(self, port: _Port, cancel: Cancel) -> None:
        job = self._job
        if job is None or job.info.image != cancel.image or job.role is not Role.RECEIVING:
            self.counters.unwanted += 1
            return
        if job.source not in (None, port.connector):
            return  # another neighbour may still complete it
        job.role = Role.WITHDRAWN
        self._actions.append(DropPartial())
        self._refuse_onwards(job, cancel.verdict)
        if job.name is not None:
            why = f"withdrawn upstream ({cancel.verdict})"
            self._report_self(job, Outcome.WITHHELD, cancel.verdict, why)

    def _refuse_onwards(self, job: _Job, verdict: str) -> None:
        for port in self._ports.values():
            sender = port.sender
            if sender is not None and sender.info.image == job.info.image and sender.active:
                sender.end(SenderState.CANCELLED, self._tick)
                self._send(port.connector, Cancel(job.info.image, verdict))

    def _drop(self, job: _Job) -> None:
        """Give up the job's image for a newer one (its neighbours will be offered that)."""
        if job.role in (Role.RECEIVING, Role.STAGING):
            self._actions.append(DropPartial())

    # -- the commit and the switch -------------------------------------------------------------

    def _on_commit(self, port: _Port, commit: Commit) -> None:
        self._send(port.connector, CommitAck(commit.image))
        port.acked.add(commit.image)
        port.commits.discard(commit.image)
        if commit.image in self._floods:
            return
        at = self._now + commit.remaining_us / 1e6 - self.latency
        if commit.hops == 0:
            at = self._mid_cycle(at)
        flood = self._floods[commit.image] = _Flood(at, min(255, commit.hops + 1))
        self._spread(commit.image, flood)

    def _mid_cycle(self, at: float) -> float:
        """The middle of this module's cycle at or after ``at`` (``at`` itself until two
        ticks have measured the period)."""
        if self._last_tick is None or self._period is None:
            return at
        k = max(0, math.ceil((at - self._last_tick) / self._period - 0.5))
        return self._last_tick + (k + 0.5) * self._period

    def _maybe_switch(self) -> None:
        job = self._job
        if job is None or job.role is not Role.STAGED or job.program is None:
            return
        flood = self._floods.get(job.info.image)
        if not job.running_offer and (flood is None or self._now < flood.at):
            return
        self._previous, self.running = self.running, job.program
        self._running_store = job.store
        self._switched_at = self._tick
        self._on_trial = True
        job.role = Role.SWITCHED
        self._actions.append(Switch(job.program))
        self._report_self(job, Outcome.COMMITTED)

    # -- reports -------------------------------------------------------------------------------

    def _on_report(self, port: _Port, sender: int, report: Report) -> None:
        self._send(port.connector, ReportAck(report.seq))
        hop = report.path[report.left - 1]
        if hop != (port.connector, sender) or report.left < 2:
            self.counters.reports_dropped += 1
            return
        if report.left == len(report.path) and port.sender is not None and port.sender.info.tag == report.tag:
            port.sender.reported = True
        left = report.left - 1
        self.counters.reports_forwarded += 1
        self._route(
            Report(report.tag, 0, report.outcome, report.version, left, report.path, report.verdict, report.reason)
        )

    def _route(self, report: Report) -> None:
        """Queue ``report`` on the hop towards the entry point: out through the receiving
        connector of hop ``left`` of its path."""
        connector = report.path[report.left - 1][1]
        port = self._ports.get(connector)
        if port is None:
            self.counters.reports_dropped += 1
            return
        port.outbox.put(report)

    def _report(
        self,
        outcome: Outcome,
        path: Path,
        depth: int,
        tag: int,
        verdict: str = "",
        reason: str = "",
        version: int | None = None,
    ) -> None:
        """Originate a report about the module named ``path``, from this module at ``depth``."""
        if depth < 1:
            self.counters.reports_dropped += 1  # no entry point to send it to
            return
        version = self.running.version if version is None else version
        self._route(Report(tag, 0, outcome, version, depth, path, verdict[:MAX_VERDICT], cut_reason(reason)))

    def _report_self(self, job: _Job, outcome: Outcome, verdict: str = "", reason: str = "") -> None:
        if job.name is None:
            return
        job.reported = max(job.reported, RANK[outcome])
        self._report(outcome, job.name, len(job.name), job.info.tag, verdict, reason)

    def _report_resolved(self) -> None:
        """Staged (or current, or switched), and every neighbour offered the image has
        reported: say so."""
        job = self._job
        if job is None or job.role not in _RESOLVED_OUTCOME or job.name is None:
            return
        outcome = _RESOLVED_OUTCOME[job.role]
        if outcome is Outcome.COMMITTED and not self._on_trial:
            outcome = Outcome.CONFIRMED
        if job.reported >= RANK[outcome]:
            return
        for port in self._ports.values():
            sender = port.sender
            child = port.connector != job.source  # the source is never a child
            if child and sender is not None and sender.info.image == job.info.image and not sender.resolved:
                return
            if port.attached_at is not None and self._tick - port.attached_at < self.timing.stall_ticks:
                return  # a neighbour may be there, not yet heard
        self._report_self(job, outcome)

    def _report_silent(self) -> None:
        job = self._job
        if job is None or job.name is None:
            return
        for port in self._ports.values():
            sender = port.sender
            silent = sender is not None and sender.state is SenderState.STALLED and not sender.reported
            if not silent or sender is None or sender.silent_reported or sender.info.image != job.info.image:
                continue
            sender.silent_reported = True
            if sender.remote is not None:
                path = (*job.name, (port.connector, sender.remote))
                self._report(Outcome.SILENT, path, len(job.name), job.info.tag, "", "no answer", port.version or 0)

    # -- once a cycle --------------------------------------------------------------------------

    def _tick_job(self) -> None:
        job = self._job
        if job is None or job.role is not Role.RECEIVING:
            return
        source = None if job.source is None else self._ports[job.source]
        if source is not None and (not source.linked or self._tick - job.progress >= self.timing.stall_ticks):
            job.source = None
        if job.source is not None:
            return
        if job.requested is None or self._tick - job.requested >= self.timing.rto_ticks:
            job.requested = self._tick
            for port in self._ports.values():
                self._request(port)

    def _request(self, port: _Port) -> None:
        """Probe the neighbour on ``port``: what does it hold of the image? (Its OFFER says,
        and names this module.)"""
        job = self._job
        if job is not None and port.linked:
            self._send(port.connector, Request(job.info.image, job.store.contiguous, self.timing.window, probe=True))

    def _finish(self) -> list[Action]:
        self._report_resolved()
        return self._flush()


def _score(offer: Offer) -> tuple[int, int]:
    """How good a source an offerer is: segments it holds, then nearness to the entry point."""
    return offer.held, -len(offer.path)


def _keeps(sender: _Sender, info: ImageInfo, *, again: bool) -> bool:
    """Whether a port's sender stays rather than make way for an offer of ``info``: it is
    offering or sending ``info`` (or a newer image), or it offered ``info`` already and the
    peer did not fall silent (unless ``again``)."""
    if sender.info.image != info.image:
        return sender.active and sender.info.version > info.version
    return sender.active or (not again and sender.state is not SenderState.STALLED)


# ---------------------------------------------------------------------------------------------
# The entry point


class FlasherPhase(enum.Enum):
    SENDING = "sending"  # the image spreads; waiting for the neighbour's report
    COMMITTING = "committing"  # the commit spreads; the switch instant is ahead
    SETTLING = "settling"  # past the switch: collecting the modules' reports
    DONE = "done"


@dataclass(frozen=True, slots=True)
class Progress:
    """What ``dh2rt flash`` shows while it runs."""

    phase: FlasherPhase
    modules: int  # modules heard of
    staged: int
    committed: int
    failed: int  # refused, reverted, withheld or silent
    bytes_acked: int  # image bytes the neighbour acknowledged
    elapsed: float  # seconds since the first tick
    rate: float  # image bytes per second delivered to modules (staged ones count whole)


#: Outcomes that stop a commit: the robot would be split between two programs.
_BLOCKING = frozenset({Outcome.REFUSED, Outcome.REVERTED, Outcome.WITHHELD})
#: Outcomes after which a module's report will not change on its own.
_FINAL = frozenset({*COMMITTED, Outcome.REFUSED, Outcome.REVERTED, Outcome.WITHHELD})


class Flasher(_Node):
    """The entry point of a rollout: it holds the image, offers it through ``connector``
    (the cable), decides the switch instant once the robot is staged, and collects every
    module's report (see the module docstring).

    ``period``: the robot's cycle period in seconds (the commit margin is counted in
    cycles). ``settle_ticks``: after the switch instant, how long to wait for modules still
    staged or silent. ``confirm``: wait for CONFIRMED reports too. ``latency``: as for
    :class:`Rollout` (unused here; the first module re-anchors the instant)."""

    def __init__(
        self,
        image: bytes,
        *,
        pacing: Pacing,
        period: float,
        connector: int = 1,
        timing: Timing | None = None,
        segment_size: int = 128,
        settle_ticks: int = 250,
        quiet_ticks: int = 5,
        confirm: bool = False,
    ) -> None:
        super().__init__([connector], pacing, timing or Timing(), segment_size=segment_size, cut_through=True)
        if period <= 0:
            raise ValueError(f"period {period!r} must be positive")
        self.program = Program.from_image(image)
        info = ImageInfo(image_id(image), self.program.version, len(image), segment_size)
        self.info = info
        self.period = period
        self.connector = connector
        self.settle_ticks = settle_ticks
        self.quiet_ticks = quiet_ticks
        self.confirm = confirm
        self.phase = FlasherPhase.SENDING
        self._store = _Store(info, image, released=True)
        self._modules: dict[Path, ModuleReport] = {}
        self._started: float | None = None
        self._heard_at = 0  # tick a report last changed something
        self._decided_at: int | None = None  # tick the switch instant passed, or the rollout failed
        self._failure: str | None = None
        port = self._ports[connector]
        port.linked = True

    # -- read-only -----------------------------------------------------------------------------

    @property
    def done(self) -> bool:
        return self.phase is FlasherPhase.DONE

    @property
    def succeeded(self) -> bool:
        """Done, and every module heard of runs the image (confirmed, with ``confirm``)."""
        wanted = {Outcome.CONFIRMED, Outcome.CURRENT} if self.confirm else COMMITTED
        return self.done and bool(self._modules) and all(m.outcome in wanted for m in self._modules.values())

    @property
    def failure(self) -> str | None:
        """Why the rollout stopped before a commit (None: it did not)."""
        return self._failure

    def report(self) -> list[ModuleReport]:
        """Every module heard of, by path from the entry point."""
        return [self._modules[p] for p in sorted(self._modules, key=lambda p: (len(p), p))]

    def progress(self) -> Progress:
        modules = self._modules.values()
        staged = sum(m.outcome in COMMITTED or m.outcome in (Outcome.STAGED, Outcome.REVERTED) for m in modules)
        committed = sum(m.committed for m in modules)
        failed = sum(
            m.outcome in (Outcome.REFUSED, Outcome.REVERTED, Outcome.WITHHELD, Outcome.SILENT) for m in modules
        )
        sender = self._ports[self.connector].sender
        acked = 0 if sender is None else self.info.span(sender.base - 1)[1] if sender.base else 0
        elapsed = 0.0 if self._started is None else self._now - self._started
        # image bytes delivered per second: the staged modules' images, or, before the first
        # module staged, what the module at the cable acknowledged
        rate = max(staged * self.info.length, acked) / elapsed if elapsed > 0 else 0.0
        return Progress(self.phase, len(self._modules), staged, committed, failed, acked, elapsed, rate)

    # -- inputs --------------------------------------------------------------------------------

    def hello(self, connector: int, remote: int, version: int | None, digest: bytes, now: float) -> list[Action]:
        """A Hello through the cable (the module there is alive): a stalled offer starts again."""
        self._now = now
        port = self._port(connector)
        self._link(port, remote)
        sender = port.sender
        if self.phase is FlasherPhase.SENDING and sender is not None and sender.state is SenderState.STALLED:
            self._start_sender(port, self._store, running=False)
        return self._flush()

    def attach(self, connector: int, now: float) -> list[Action]:
        """The cable is plugged in (again): offers go out through it."""
        self._now = now
        self._port(connector).linked = True
        return self._flush()

    def detach(self, connector: int, now: float) -> list[Action]:
        """The cable was unplugged: nothing goes out until it is plugged in again."""
        return self.link_down(connector, now)

    def link_down(self, connector: int, now: float) -> list[Action]:
        """The module at the cable fell silent; a stalled offer starts again at its next Hello."""
        self._now = now
        self._unlink(self._port(connector))
        return self._flush()

    def receive(self, connector: int, data: bytes, now: float) -> list[Action]:
        self._now = now
        self.counters.frames_in += 1
        try:
            sender, message = decode(data)
        except DecodeError:
            self.counters.garbage += 1
            return self._flush()
        port = self._port(connector)
        if not port.linked or port.remote != sender:
            self._link(port, sender)
        match message:
            case Ack():
                self._on_ack(port, message)
            case Decline():
                self._on_decline(port, message)
            case Request():
                self._on_request(port, message)
            case CommitAck():
                self._on_commit_ack(port, message)
            case Report():
                self._on_report(port, sender, message)
            case _:
                self.counters.unwanted += 1
        return self._flush()

    def tick(self, now: float) -> list[Action]:
        self._begin_tick(now)
        if self._started is None:
            self._started = now
        port = self._ports[self.connector]
        if port.sender is None:
            self._start_sender(port, self._store, running=False)
        self._tick_senders()
        self._tick_phase(port)
        self._tick_floods()
        return self._flush()

    # -- the phases ----------------------------------------------------------------------------

    def _tick_phase(self, port: _Port) -> None:
        sender = port.sender
        if self.phase is FlasherPhase.SENDING and sender is not None and sender.state is SenderState.STALLED:
            self._fail("the module at the cable fell silent")
        elif self.phase is FlasherPhase.COMMITTING and self._now >= self._floods[self.info.image].at:
            self.phase = FlasherPhase.SETTLING
            self._decided_at = self._tick
        if self.phase is FlasherPhase.SETTLING and self._settled():
            self.phase = FlasherPhase.DONE

    def _settled(self) -> bool:
        """Past the settle time, or every module's report is final and none changed lately."""
        if self._decided_at is not None and self._tick - self._decided_at >= self.settle_ticks:
            return True
        final = _FINAL - ({Outcome.COMMITTED} if self.confirm else set())
        quiet = self._tick - self._heard_at >= self.quiet_ticks
        return quiet and all(m.outcome in final for m in self._modules.values())

    def _fail(self, why: str) -> None:
        self._failure = why
        self.phase = FlasherPhase.SETTLING
        self._decided_at = self._tick

    def _commit(self) -> None:
        depth = max((len(p) for p in self._modules), default=1)
        at = self._now + (depth + COMMIT_SLACK) * self.period
        self._floods[self.info.image] = _Flood(at, 0)
        self.phase = FlasherPhase.COMMITTING

    # -- messages ------------------------------------------------------------------------------

    def _port(self, connector: int) -> _Port:
        if connector != self.connector:
            raise ValueError(f"connector {connector!r}: the flasher has only connector {self.connector}")
        return self._ports[connector]

    def _store_for(self, image: bytes) -> _Store | None:
        return self._store if image == self.info.image else None

    def _path_of(self, store: _Store) -> Path:
        return ()

    def _on_request(self, port: _Port, request: Request) -> None:
        if request.image != self.info.image:
            self.counters.unwanted += 1
            return
        sender = port.sender
        if sender is None or sender.state is SenderState.STALLED:
            sender = self._start_sender(port, self._store, running=False)
        elif request.probe:
            self._offer(port, sender, self._store)
        if not request.probe:
            sender.on_request(request.next, request.window, self._tick)

    def _on_report(self, port: _Port, sender: int, report: Report) -> None:
        self._send(port.connector, ReportAck(report.seq))
        if report.left != 1 or report.path[0] != (port.connector, sender) or report.tag != self.info.tag:
            self.counters.reports_dropped += 1
            return
        self._record(report)
        if len(report.path) == 1 and self.phase is FlasherPhase.SENDING:
            self._on_neighbour(report.outcome)

    def _record(self, report: Report) -> None:
        old = self._modules.get(report.path)
        if old is not None and RANK[old.outcome] > RANK[report.outcome]:
            return
        if old is None or old.outcome is not report.outcome:
            self._heard_at = self._tick
        self._modules[report.path] = ModuleReport(
            report.path, report.outcome, report.version, report.verdict, report.reason
        )

    def _on_neighbour(self, outcome: Outcome) -> None:
        """The module at the cable reported on itself, after its whole subtree: commit,
        unless a module refused the image (a robot half on each program would fall apart;
        silent modules catch up later)."""
        sender = self._ports[self.connector].sender
        if sender is not None:
            sender.reported = True
        refusals = [m for m in self.report() if m.outcome in _BLOCKING]
        if refusals:
            first = refusals[0]
            self._fail(f"not committed: {describe_path(first.path)} {first.outcome.name.lower()} the image")
        elif outcome in (Outcome.STAGED, Outcome.CURRENT, Outcome.COMMITTED, Outcome.CONFIRMED):
            self._commit()
