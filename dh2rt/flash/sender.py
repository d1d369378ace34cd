"""The per-hop retransmission: one image's transfer out through one connector (:class:`Sender`).

Its state machine (:class:`SenderState`) offers the image, pushes a window of segments,
takes the peer's cumulative and selective acknowledgements, sends again what went
unacknowledged for ``rto_ticks`` (or at once, when a later segment was acknowledged), and
gives up a peer silent for ``stall_ticks``. How many bytes it may send each cycle is the
node's (:mod:`dh2rt.flash.pacing`, :meth:`dh2rt.flash.node.Node._spend`).
"""

from __future__ import annotations

import enum

from dh2rt.flash.values import ImageInfo
from dh2rt.wire.transfer import SACK_BITS, DeclineReason, Offer


class SenderState(enum.Enum):
    OFFERING = "offering"  # OFFER out, first window pushed; no answer yet
    SENDING = "sending"  # the peer asked for it
    DONE = "done"  # the peer holds every segment
    DECLINED = "declined"  # the peer does not want it
    STALLED = "stalled"  # the peer fell silent: given up
    CANCELLED = "cancelled"  # withdrawn: this module refused the image


_ACTIVE = frozenset({SenderState.OFFERING, SenderState.SENDING})


class Sender:
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
