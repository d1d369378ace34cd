"""What a module and the entry point share (:class:`Node`): ports, pacing, framing, segment
pumping, the commit flood, the report outboxes, and the first steps of every received frame.

The two state machines are its subclasses: :class:`dh2rt.flash.rollout.Rollout` (a module)
and :class:`dh2rt.flash.flasher.Flasher` (the entry point).
"""

from __future__ import annotations

import itertools
import math
import statistics
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field

from dh2rt.errors import DecodeError
from dh2rt.flash.pacing import LARGEST_CONTROL, Pacing
from dh2rt.flash.reports import Outbox
from dh2rt.flash.sender import Sender
from dh2rt.flash.store import Store
from dh2rt.flash.values import Action, RolloutCounters, Send, Timing
from dh2rt.wire.transfer import Ack, Commit, CommitAck, Decline, Message, Offer, Path, Segment, decode, encode

# ---------------------------------------------------------------------------------------------
# Ports and the commit flood


@dataclass(slots=True)
class Port:
    """One connector: who is there, what waits to go out, and this cycle's budget."""

    connector: int
    linked: bool = False  # its peer has been heard (a Hello, a transfer frame) and not lost since
    attached_at: int | None = None  # tick it was attached, while it may have a peer not yet heard
    remote: int | None = None  # the peer's connector (from its frames' headers)
    version: int | None = None  # the peer's program, from its Hello
    digest: bytes | None = None
    queue: deque[bytes] = field(default_factory=deque)
    sender: Sender | None = None
    outbox: Outbox = field(default_factory=Outbox)
    tokens: int = 0
    free_at: float = -math.inf  # when the frames sent so far would be out, at the budget's rate
    acked: set[bytes] = field(default_factory=set)  # commits the peer has (acknowledged or sent us)
    commits: set[bytes] = field(default_factory=set)  # commits to send it now


@dataclass(slots=True)
class Flood:
    """A commit known here: the switch instant on this module's clock, and the hop count
    its COMMITs carry on."""

    at: float
    hops: int
    passed_at: int | None = None  # tick the instant passed
    sent: dict[int, tuple[int, int]] = field(default_factory=dict)  # connector -> (tick last sent, sends)


#: Ticks :meth:`Node._grid` reads the cycle grid from.
GRID_TICKS = 16


# ---------------------------------------------------------------------------------------------
# What modules and the entry point share


class Node(ABC):
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
        self._ports = {c: Port(c) for c in connectors}
        if not self._ports or any(not 1 <= c <= 15 for c in self._ports):
            raise ValueError(f"connectors must be 1..15, got {sorted(self._ports)}")
        self._tick = 0
        self._now = 0.0
        self._last_tick: float | None = None  # ``now`` of the last tick
        self._period: float | None = None  # measured between the last two ticks
        self._ticks: deque[float] = deque(maxlen=GRID_TICKS)  # the last ticks, for :meth:`_grid`
        self._shared_tokens = 0
        self._shared_free_at = -math.inf
        self._rotation = 0
        self._floods: dict[bytes, Flood] = {}
        self._actions: list[Action] = []
        self._check_budget()

    def _grid(self) -> tuple[float, float] | None:
        """This node's cycle grid from its recent ticks: a cycle start on it near the last tick,
        and the period (None until three ticks). The period is the median interval and the
        start the least delayed tick's, both robust against a cycle the machine held up: the
        last interval alone, extrapolated over the commit margin's dozen cycles, put the
        "middle of the cycle" anywhere in it."""
        ticks = list(self._ticks)
        if len(ticks) < 3:
            return None
        period = statistics.median(b - a for a, b in itertools.pairwise(ticks))
        if period <= 0:
            return None
        last = ticks[-1]
        late = min((t - last + period / 2) % period - period / 2 for t in ticks)
        return last + late, period

    def join_cycle(self, start: float, period: float) -> None:
        """This node was made between ticks (a module host loads its Rollout when a transfer
        frame first concerns the module, :mod:`firmware.flash.door`): the cycle that began at
        ``start`` is under way and cycles are ``period`` long. Its budget is whole (nothing
        of the rollout went out in it), and frames go out between ticks at once. Without it,
        frames waited for the node's first tick, and for its second (the period measured)
        to go out between ticks: the REQUEST, the first segments and their forwarding went
        at ticks only at every module the image reached (about a cycle a hop)."""
        if self._last_tick is not None or period <= 0:
            return
        self._last_tick = start
        self._period = period
        self._ticks.append(start)
        self._refill()

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

    # -- a received frame ----------------------------------------------------------------------

    def receive(self, connector: int, data: bytes, now: float) -> list[Action]:
        """A transfer frame received through ``connector`` (``now``: when it arrived, not when
        the host read it: a COMMIT's time left counts from its arrival)."""
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

    @abstractmethod
    def _port(self, connector: int) -> Port:
        """The port of ``connector``; raises ValueError for a connector this node lacks."""

    @abstractmethod
    def _dispatch(self, port: Port, sender: int, message: Message) -> None:
        """Act on a decoded frame from connector ``sender`` of the peer on ``port``."""

    def _finish(self) -> list[Action]:
        """What an input ends with: whatever may go out now (see :meth:`_flush`)."""
        return self._flush()

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
        self._ticks.append(now)
        self._refill()

    def _refill(self) -> None:
        """A cycle's whole budget, on every port (or the bus)."""
        self._shared_tokens = self.pacing.budget
        for port in self._ports.values():
            port.tokens = self.pacing.budget

    def _spend(self, port: Port, frame: bytes, commit_at: float | None = None) -> bool:
        """Take ``frame``'s cost from this cycle's budget and queue its Send, or refuse.

        Two rules: at most ``budget`` units per cycle; and, once the period is known, a
        frame goes out between ticks only if, sent back to back with this cycle's earlier
        frames, it would be out before the next tick (until two ticks have measured the
        period, frames go out at ticks only). The link is then idle when the next cycle's
        hormone frames go out, whenever the transfer frames were sent. Frames are timed at
        the line's own rate when the pacing knows it (a serial connector), else at the
        budget's rate (``budget`` units per period, slower than the line): timed at the
        budget's rate, a segment frame arriving in the second half of a cycle waited for
        the next tick although the line had it out in 0.4 of one (0.64 cycles a hop in
        tests/dh2rt/rollout_sim.py's snake:20, 0.56 at the line's rate)."""
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
            rate = self.pacing.rate or self.pacing.budget / self._period
            free_at = start + cost / rate
            if free_at > self._last_tick + self._period * (1 + 1e-9):
                return False
        if self.pacing.shared:
            self._shared_tokens -= cost
            self._shared_free_at = free_at
        else:
            port.tokens -= cost
            port.free_at = free_at
        self.counters.units_sent += cost
        self._actions.append(Send(port.connector, frame, commit_at))
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

    def _drain(self, port: Port) -> bool:
        """Send due commits, queued control frames and due reports; False when the budget ran out."""
        for image in list(port.commits):
            flood = self._floods[image]
            if not self._spend(port, encode(port.connector, self._commit_message(image, flood)), flood.at):
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

    def _pump(self, port: Port) -> None:
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
    def _store_for(self, image: bytes) -> Store | None:
        """The bytes of ``image`` this node can send, if any."""

    # -- senders -------------------------------------------------------------------------------

    def _start_sender(self, port: Port, store: Store, *, running: bool) -> Sender:
        info = store.info
        offer = Offer(info.version, info.image, info.length, info.segment_size, 0, running)
        sender = Sender(info, offer, port.remote, self.timing.window, self._tick)
        port.sender = sender
        self._offer(port, sender, store)
        return sender

    def _offer(self, port: Port, sender: Sender, store: Store) -> None:
        """OFFER as things stand: the segments held now, this node's name now."""
        o = sender.offer
        held = store.available(self.cut_through)
        path = self._path_of(store)
        self._send(port.connector, Offer(o.version, o.image, o.length, o.segment_size, held, o.running, path))
        sender.offered_at = self._tick

    @abstractmethod
    def _path_of(self, store: Store) -> Path:
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

    def _on_ack(self, port: Port, ack: Ack) -> None:
        sender = port.sender
        if sender is None or sender.info.tag != ack.tag:
            self.counters.unwanted += 1
            return
        sender.on_ack(ack.next, ack.sack, self._tick)

    def _on_decline(self, port: Port, decline: Decline) -> None:
        sender = port.sender
        if sender is None or sender.info.image != decline.image:
            self.counters.unwanted += 1
            return
        sender.on_decline(decline.reason, self._tick)

    # -- links ---------------------------------------------------------------------------------

    def _link(self, port: Port, remote: int) -> None:
        port.linked = True
        port.attached_at = None
        port.remote = remote
        if port.sender is not None:
            port.sender.lost_at = None
            port.sender.remote = remote

    def _unlink(self, port: Port) -> None:
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

    def _spread(self, image: bytes, flood: Flood) -> None:
        """COMMIT to every linked neighbour that lacks it: at once the first time, then a
        cycle later, then 2, 4 cycles later (sent first when the frames go out, so that it
        states the time left when it leaves)."""
        for port in self._ports.values():
            if not port.linked or image in port.acked:
                continue
            last, sends = flood.sent.get(port.connector, (0, 0))
            if not sends or self._tick - last >= 1 << min(sends - 1, 2):
                port.commits.add(image)

    def _commit_message(self, image: bytes, flood: Flood) -> Commit:
        """The COMMIT, stating the time left from now (the host stamps it again as it leaves:
        :meth:`~dh2rt.flash.values.Send.frame`)."""
        return Commit(image, max(0, round((flood.at - self._now) * 1e6)), flood.hops)

    def _on_commit_ack(self, port: Port, ack: CommitAck) -> None:
        port.acked.add(ack.image)
        port.commits.discard(ack.image)
