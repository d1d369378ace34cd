"""Link negotiation: docked connectors agree on a CAN link id, with no central assigner.

On a shared CAN bus every frame names a *link id* and a *side* (:mod:`dh2rt.wire.can_frames`).
Nobody hands those out on a real robot, and DH2 allows no module ids, so the two modules of a
docked pair agree on one themselves, over the *connector-local channel* (CLC) each connector
has (CONRO's infrared pair: it senses contact and carries a few bytes, ≤ 8 per message, to
the connector it touches, and may lose or garble them), then claim it on the bus, where every
module hears every claim. ``docs/link-layer.md`` ("Link negotiation") has the message
formats, the message sequences and the failure cases.

In short, per connector: on contact each side draws a 32-bit *nonce* and sends ``OFFER``; the
higher nonce is the *leader* (side 0), and ``tag = leader nonce ^ follower nonce`` names the
pair for as long as the negotiation lasts. The leader picks a random id nobody is known to use,
``PROPOSE``s it, gets ``ACCEPT`` (or ``REJECT``: the follower knows the id to be taken), then
``CLAIM``s it on the bus for ``claim_ticks`` cycles. If no rival objects it sends ``CONFIRM``
and both ends attach; the leader re-announces the id (``HOLD``) every ``reannounce_s``. Two
pairs on one id: an established pair beats a claiming one, otherwise the lower tag keeps it;
the loser picks again. Undock: both ends detach and ``RELEASE`` the id, which every module
then avoids for ``quarantine_s``. Nonces live only as long as one negotiation: nothing here
names a module.

Sans-IO: no I/O, no threads, no clock, no third-party imports. Randomness comes from the
injected :class:`random.Random` (nonces from ``rng.getrandbits(32)``, candidate ids from
``rng.randint(lo, hi)``); time only from :meth:`LinkNegotiator.tick`'s argument. Seed the
generator from real entropy on a module (``random.Random()`` does): two modules that draw the
same numbers in the same order can never tell who leads.

Driving it from a cycle loop (the module runtime; ``transport`` a CAN transport, ``clc`` the
connector-local channels, ``bus`` the raw CAN bus)::

    neg = LinkNegotiator(CONRO_CONNECTORS, random.Random(), now=time.monotonic())
    for c in clc.touching():                      # contacts already made at power-up
        do(neg.contact(c, True))
    while running:
        for c, made in clc.contact_changes():     # edges sensed this cycle
            do(neg.contact(c, made))
        for c, data in clc.received():            # CLC messages, ≤ 8 bytes each
            do(neg.local_received(c, data))
        for frame in bus.management_frames():     # arbitration id == MANAGEMENT_ID
            do(neg.bus_received(frame.data))
        do(neg.tick(time.monotonic()))            # once per cycle, after the inputs
        ...                                        # the rest of the cycle (engine, hormones)

    def do(actions):
        for a in actions:
            match a:
                case SendLocal(c, data): clc.send(c, data)
                case SendBus(): bus.send(a.frame)               # CanFrame(MANAGEMENT_ID, data)
                case Attach(c, end): transport.attach(c, end)
                case Detach(c): transport.detach(c)

Every input returns the actions it causes, in order; carry them out before the next input.
A module's own management frames echoed back by its bus (``udp_multicast``) are harmless.
Garbage from either medium is counted (``counters.garbage``) and ignored, never raised.
"""

from __future__ import annotations

import enum
import random
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

from dh2rt.errors import DecodeError, EncodeError, FrameCorrupted
from dh2rt.transport.base import BusEnd
from dh2rt.wire.can_frames import MANAGEMENT_ID as MANAGEMENT_ID  # the channel is CAN framing's
from dh2rt.wire.can_frames import MAX_LINK_ID, CanFrame

#: The ids links may be given: 0 is left out (the HIL world's numbering starts there) and
#: MAX_LINK_ID is the management channel's.
FIRST_LINK_ID = 1
LAST_LINK_ID = MAX_LINK_ID - 1
#: The most a CLC message may carry.
LOCAL_MAX = 8

_U32 = 0xFFFFFFFF
_U24 = 0xFFFFFF


def management_filter() -> dict[str, int | bool]:
    """A python-can filter accepting the management frames (and nothing else)."""
    return {"can_id": MANAGEMENT_ID, "can_mask": (1 << 29) - 1, "extended": True}


# ---------------------------------------------------------------------------------------------
# Connector-local channel messages


class LocalType(enum.IntEnum):
    """Byte 0 of a CLC message."""

    OFFER = 1  # nonce u32, check u24
    PROPOSE = 2  # link id u24, seal u32 (leader -> follower)
    ACCEPT = 3  # link id u24, seal u32 (follower -> leader)
    CONFIRM = 4  # link id u24, seal u32 (leader -> follower)
    REJECT = 5  # link id u24, seal u32 (follower -> leader: that id is taken)


@dataclass(frozen=True, slots=True)
class Offer:
    """``OFFER``: the sender's nonce for this negotiation."""

    nonce: int


@dataclass(frozen=True, slots=True)
class Sealed:
    """``PROPOSE``/``ACCEPT``/``CONFIRM``/``REJECT``: a link id and a seal binding it to a tag.

    ``seal = tag ^ crc32(type byte ‖ link id)``: only a receiver holding the same tag (the same
    two nonces) accepts it, and a garbled type or id (any error in those 4 bytes) or seal never
    passes. A message from an older negotiation fails the same way.
    """

    kind: LocalType
    link_id: int
    seal: int

    def opens(self, tag: int) -> bool:
        """Whether this message belongs to the negotiation whose tag is ``tag``."""
        return self.seal == _seal(self.kind, self.link_id, tag)


LocalMessage = Offer | Sealed


def _offer_check(head: bytes) -> int:
    return zlib.crc32(head) & _U24


def _seal(kind: LocalType, link_id: int, tag: int) -> int:
    return (tag ^ zlib.crc32(bytes((kind,)) + link_id.to_bytes(3, "big"))) & _U32


def _check_link_id(link_id: int) -> None:
    if isinstance(link_id, bool) or not isinstance(link_id, int) or not FIRST_LINK_ID <= link_id <= LAST_LINK_ID:
        raise EncodeError(f"link id {link_id!r} is outside {FIRST_LINK_ID}..{LAST_LINK_ID}")


def _check_u32(name: str, value: int, *, nonzero: bool = False) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or not (1 if nonzero else 0) <= value <= _U32:
        raise EncodeError(f"{name} {value!r} is not a{' non-zero' if nonzero else ''} 32-bit value")


def encode_offer(nonce: int) -> bytes:
    """``OFFER``: type, nonce (4 bytes BE), low 24 bits of the CRC-32 of those 5 bytes."""
    _check_u32("nonce", nonce)
    head = bytes((LocalType.OFFER,)) + nonce.to_bytes(4, "big")
    return head + _offer_check(head).to_bytes(3, "big")


def encode_sealed(kind: LocalType, link_id: int, tag: int) -> bytes:
    """A sealed message: type, link id (3 bytes BE), seal (4 bytes BE); 8 bytes."""
    if kind is LocalType.OFFER:
        raise EncodeError("an OFFER carries a nonce, not a link id: use encode_offer")
    _check_link_id(link_id)
    _check_u32("tag", tag, nonzero=True)
    return bytes((kind,)) + link_id.to_bytes(3, "big") + _seal(kind, link_id, tag).to_bytes(4, "big")


def decode_local(data: bytes) -> LocalMessage:
    """One CLC message; raises DecodeError (FrameCorrupted for a failed check) on garbage."""
    if len(data) != LOCAL_MAX:
        raise DecodeError(f"CLC message of {len(data)} bytes; every message is {LOCAL_MAX}")
    try:
        kind = LocalType(data[0])
    except ValueError:
        raise DecodeError(f"CLC message type {data[0]} is unknown") from None
    if kind is LocalType.OFFER:
        if int.from_bytes(data[5:8], "big") != _offer_check(bytes(data[:5])):
            raise FrameCorrupted("OFFER check does not match")
        return Offer(int.from_bytes(data[1:5], "big"))
    link_id = int.from_bytes(data[1:4], "big")
    if not FIRST_LINK_ID <= link_id <= LAST_LINK_ID:
        raise DecodeError(f"CLC {kind.name} names link id {link_id}, outside {FIRST_LINK_ID}..{LAST_LINK_ID}")
    return Sealed(kind, link_id, int.from_bytes(data[4:8], "big"))


# ---------------------------------------------------------------------------------------------
# Bus management frames


class BusOp(enum.IntEnum):
    """Byte 0 of a management frame."""

    CLAIM = 1  # a pair wants this id (sent every cycle of its claim window)
    RELEASE = 2  # a pair let go of this id
    HOLD = 3  # an established pair owns this id (re-announced; also its defence)


@dataclass(frozen=True, slots=True)
class BusMessage:
    """A management frame's data: op, link id, the claiming pair's tag."""

    op: BusOp
    link_id: int
    tag: int


def encode_bus(msg: BusMessage) -> bytes:
    """op (1 byte), link id (3 bytes BE), tag (4 bytes BE): one classic CAN frame's 8 bytes."""
    _check_link_id(msg.link_id)
    _check_u32("tag", msg.tag, nonzero=True)
    return bytes((BusOp(msg.op),)) + msg.link_id.to_bytes(3, "big") + msg.tag.to_bytes(4, "big")


def decode_bus(data: bytes) -> BusMessage:
    """A management frame's data; raises DecodeError on garbage (CAN's CRC caught the noise)."""
    if len(data) != 8:
        raise DecodeError(f"management frame of {len(data)} bytes; it must be 8")
    try:
        op = BusOp(data[0])
    except ValueError:
        raise DecodeError(f"management op {data[0]} is unknown") from None
    link_id = int.from_bytes(data[1:4], "big")
    tag = int.from_bytes(data[4:8], "big")
    if not FIRST_LINK_ID <= link_id <= LAST_LINK_ID:
        raise DecodeError(f"management frame names link id {link_id}, outside {FIRST_LINK_ID}..{LAST_LINK_ID}")
    if tag == 0:
        raise DecodeError("management frame with tag 0 (no pair has it)")
    return BusMessage(op, link_id, tag)


# ---------------------------------------------------------------------------------------------
# Actions


@dataclass(frozen=True, slots=True)
class SendLocal:
    """Send ``data`` (≤ 8 bytes) over ``connector``'s connector-local channel."""

    connector: int
    data: bytes


@dataclass(frozen=True, slots=True)
class SendBus:
    """Broadcast a management frame with these 8 data bytes (id :data:`MANAGEMENT_ID`)."""

    data: bytes

    @property
    def frame(self) -> CanFrame:
        return CanFrame(MANAGEMENT_ID, self.data)


@dataclass(frozen=True, slots=True)
class Attach:
    """``connector`` is now the ``end.side`` end of link ``end.link_id``: attach the transport."""

    connector: int
    end: BusEnd


@dataclass(frozen=True, slots=True)
class Detach:
    """``connector``'s link is gone: detach the transport (and clear its ConnectorStatus)."""

    connector: int


Action = SendLocal | SendBus | Attach | Detach


# ---------------------------------------------------------------------------------------------
# The state machine


class LinkState(enum.Enum):
    """Where one connector's negotiation stands."""

    IDLE = "idle"  # no contact
    OFFERING = "offering"  # contact: OFFER every cycle, the peer's nonce not yet known
    PROPOSING = "proposing"  # leader: PROPOSE sent, waiting for ACCEPT
    CLAIMING = "claiming"  # leader: CLAIM on the bus every cycle of the window
    AWAIT_PROPOSE = "await-propose"  # follower: waiting for a PROPOSE under our tag
    AWAIT_CONFIRM = "await-confirm"  # follower: ACCEPT sent, waiting for CONFIRM
    ESTABLISHED = "established"  # attached


#: States that give up and start over after ``timeout_ticks`` cycles without a change.
_TIMED = frozenset({LinkState.PROPOSING, LinkState.AWAIT_PROPOSE, LinkState.AWAIT_CONFIRM})


@dataclass(slots=True)
class _Port:
    """One connector's negotiation."""

    connector: int
    state: LinkState = LinkState.IDLE
    nonce: int = 0
    peer_nonce: int | None = None
    proven: bool = False  # the peer sent a valid sealed message: it knows our nonce
    link_id: int | None = None  # candidate (leader), accepted id (follower), or the link's id
    entered: int = 0  # cycle the state was entered
    sent: int = 0  # cycle PROPOSE/ACCEPT last went out
    offered: int = -1  # cycle OFFER last went out
    claims: int = 0  # CLAIMs sent in this window
    defended: int = -1  # cycle a HOLD last went out in defence
    announced: float = 0.0  # leader: when HOLD last went out
    heard: float = 0.0  # follower: when the leader was last heard (HOLD, CLAIM, CONFIRM)

    @property
    def tag(self) -> int | None:
        return None if self.peer_nonce is None else self.nonce ^ self.peer_nonce

    @property
    def leader(self) -> bool:
        return self.peer_nonce is not None and self.nonce > self.peer_nonce

    @property
    def on_bus(self) -> bool:
        """Whether this end's id is known on the bus as ours (claimed or held)."""
        return self.link_id is not None and self.state in (LinkState.CLAIMING, LinkState.ESTABLISHED)


@dataclass(slots=True)
class _Seen:
    tag: int
    at: float


@dataclass(frozen=True, slots=True)
class NegotiationCounters:
    """Totals since the negotiator started."""

    negotiations: int = 0  # links attached at this module (either side)
    collisions: int = 0  # ids this module's leaders lost to another pair (claimed or held)
    defences: int = 0  # HOLDs sent at once to defend an established id against a rival
    repicks: int = 0  # candidates dropped before claiming (seen in use on the bus, or REJECTed)
    retries: int = 0  # CLC retransmissions of PROPOSE, ACCEPT and CONFIRM
    resets: int = 0  # negotiations started over (timeout, peer restarted, peer silent or gone)
    releases: int = 0  # RELEASE frames sent
    garbage: int = 0  # CLC messages or management frames that did not decode
    stale: int = 0  # CLC messages whose seal did not open (older negotiation, or garbled)


class LinkNegotiator:
    """The link negotiation of one module's connectors (see the module docstring).

    ``connectors``: the module's connector numbers. ``rng``: the only source of randomness.
    Timing, in cycles (calls to :meth:`tick`): ``claim_ticks`` claims before an id is taken
    (it must cover a defence's round trip: at least 2 + 2 × the cycles a bus frame may be read
    late; the default 3 leaves one cycle of slack),
    ``retry_ticks`` between PROPOSE retransmissions, ``timeout_ticks`` without progress before
    a negotiation starts over. In seconds (of ``tick``'s clock): ``reannounce_s`` between an
    established leader's HOLDs, ``leader_silence_s`` after which a follower whose leader went
    silent lets go, ``in_use_s`` after which an id nobody announced is free again,
    ``quarantine_s`` during which a released id is not picked. ``link_ids``: the inclusive range
    candidates are drawn from. ``now``: the clock at construction.
    """

    def __init__(
        self,
        connectors: Sequence[int],
        rng: random.Random,
        *,
        claim_ticks: int = 3,
        retry_ticks: int = 2,
        timeout_ticks: int = 25,
        reannounce_s: float = 1.0,
        leader_silence_s: float = 3.5,
        in_use_s: float = 5.0,
        quarantine_s: float = 10.0,
        link_ids: tuple[int, int] = (FIRST_LINK_ID, LAST_LINK_ID),
        now: float = 0.0,
    ) -> None:
        _check_connectors(connectors)
        _check_timing(claim_ticks, retry_ticks, timeout_ticks, reannounce_s, leader_silence_s, in_use_s, quarantine_s)
        lo, hi = link_ids
        if not FIRST_LINK_ID <= lo <= hi <= LAST_LINK_ID:
            raise ValueError(f"link_ids {link_ids!r} must be a range inside {FIRST_LINK_ID}..{LAST_LINK_ID}")
        self._rng = rng
        self.claim_ticks = claim_ticks
        self.retry_ticks = retry_ticks
        self.timeout_ticks = timeout_ticks
        self.reannounce_s = reannounce_s
        self.leader_silence_s = leader_silence_s
        self.in_use_s = in_use_s
        self.quarantine_s = quarantine_s
        self.link_ids = (lo, hi)
        self._ports = {c: _Port(c) for c in connectors}
        self._in_use: dict[int, _Seen] = {}
        self._quarantine: dict[int, float] = {}
        self._now = now
        self._cycle = 0
        self._counts = dict.fromkeys(NegotiationCounters.__dataclass_fields__, 0)

    # ------------------------------------------------------------------ what it knows

    @property
    def links(self) -> Mapping[int, BusEnd]:
        """The established links: connector -> link end."""
        return {
            c: BusEnd(p.link_id, 0 if p.leader else 1)
            for c, p in self._ports.items()
            if p.state is LinkState.ESTABLISHED and p.link_id is not None
        }

    def state(self, connector: int) -> LinkState:
        return self._port(connector).state

    @property
    def ids_in_use(self) -> frozenset[int]:
        """Ids heard claimed or held on the bus within ``in_use_s`` (a module hears its own
        frames only if its bus echoes them)."""
        return frozenset(self._in_use)

    @property
    def ids_quarantined(self) -> frozenset[int]:
        """Ids released within ``quarantine_s``."""
        return frozenset(self._quarantine)

    @property
    def counters(self) -> NegotiationCounters:
        """A snapshot of the counters."""
        return NegotiationCounters(**self._counts)

    # ------------------------------------------------------------------ inputs

    def contact(self, connector: int, made: bool) -> list[Action]:
        """The contact sensor of ``connector`` changed (or reads ``made`` at start-up)."""
        p = self._port(connector)
        out: list[Action] = []
        if made and p.state is LinkState.IDLE:
            self._start(p, out)
        elif not made and p.state is not LinkState.IDLE:
            self._leave(p, out, release=True)
            self._enter(p, LinkState.IDLE)
            p.peer_nonce = None
        return out

    def local_received(self, connector: int, data: bytes) -> list[Action]:
        """A message arrived over ``connector``'s connector-local channel."""
        p = self._port(connector)
        try:
            msg = decode_local(data)
        except DecodeError:
            self._count("garbage")
            return []
        out: list[Action] = []
        if p.state is LinkState.IDLE:
            return out  # no contact sensed yet: the peer keeps offering
        if isinstance(msg, Offer):
            self._on_offer(p, msg.nonce, out)
            return out
        tag = p.tag
        if tag is None or not msg.opens(tag):
            self._count("stale")
            return out
        p.proven = True
        if p.leader:
            self._on_sealed_as_leader(p, msg, out)
        else:
            self._on_sealed_as_follower(p, msg, out)
        return out

    def bus_received(self, data: bytes) -> list[Action]:
        """A management frame (arbitration id :data:`MANAGEMENT_ID`) arrived; ``data`` its bytes."""
        try:
            msg = decode_bus(data)
        except DecodeError:
            self._count("garbage")
            return []
        self._record(msg)
        out: list[Action] = []
        for p in self._ports.values():
            if p.link_id == msg.link_id and p.state is not LinkState.IDLE:
                self._on_bus(p, msg, out)
        return out

    def tick(self, now: float) -> list[Action]:
        """End of a cycle: retransmissions, claim windows, re-announcements, timeouts, ageing."""
        self._now = now
        self._age()
        out: list[Action] = []
        for p in self._ports.values():
            self._tick_port(p, out)
        self._cycle += 1
        return out

    def shutdown(self) -> list[Action]:
        """The module is stopping: detach and release every link, forget every negotiation."""
        out: list[Action] = []
        for p in self._ports.values():
            if p.state is not LinkState.IDLE:
                self._leave(p, out, release=True)
                self._enter(p, LinkState.IDLE)
                p.peer_nonce = None
        return out

    # ------------------------------------------------------------------ CLC handling

    def _on_offer(self, p: _Port, nonce: int, out: list[Action]) -> None:
        if nonce == p.peer_nonce:
            return  # a repeat: the peer has not yet heard from us under our tag
        if p.state is not LinkState.OFFERING:
            # The peer drew a new nonce: it restarted, re-touched, or gave up and started over.
            self._leave(p, out, release=True)
            self._count("resets")
        self._adopt(p, nonce, out)

    def _adopt(self, p: _Port, nonce: int, out: list[Action]) -> None:
        """Take the peer's nonce; the higher one leads. Our own nonce stays: only a tie (or
        starting over) redraws it, so two sides never chase each other's fresh nonces."""
        if nonce == p.nonce:
            self._start(p, out)  # a tie: both sides see it and redraw
            return
        p.peer_nonce = nonce
        p.proven = False
        if p.leader:
            self._offer(p, out)  # before the PROPOSE: the peer needs our nonce to open it
            self._propose(p, out)
        else:
            self._enter(p, LinkState.AWAIT_PROPOSE)

    def _on_sealed_as_leader(self, p: _Port, msg: Sealed, out: list[Action]) -> None:
        if msg.link_id != p.link_id:
            return  # about a candidate we dropped
        if msg.kind is LocalType.ACCEPT:
            if p.state is LinkState.PROPOSING:
                self._start_claim(p, out)
            elif p.state is LinkState.ESTABLISHED:
                self._count("retries")  # our CONFIRM was lost
                out.append(SendLocal(p.connector, encode_sealed(LocalType.CONFIRM, msg.link_id, self._tag(p))))
        elif msg.kind is LocalType.REJECT and p.state is LinkState.PROPOSING:
            self._quarantine[msg.link_id] = self._now + self.quarantine_s
            self._count("repicks")
            self._propose(p, out)

    def _on_sealed_as_follower(self, p: _Port, msg: Sealed, out: list[Action]) -> None:
        if msg.kind is LocalType.PROPOSE:
            self._on_propose(p, msg.link_id, out)
        elif msg.kind is LocalType.CONFIRM:
            if p.state is LinkState.AWAIT_CONFIRM and msg.link_id == p.link_id:
                self._enter(p, LinkState.ESTABLISHED)
                p.heard = self._now
                self._count("negotiations")
                out.append(Attach(p.connector, BusEnd(msg.link_id, 1)))
            elif p.state is LinkState.ESTABLISHED and msg.link_id == p.link_id:
                p.heard = self._now

    def _on_propose(self, p: _Port, link_id: int, out: list[Action]) -> None:
        if p.state is LinkState.ESTABLISHED:
            if link_id == p.link_id:
                return  # a retransmission that crossed our ACCEPT
            out.append(Detach(p.connector))  # the leader lost our id and picked another
            p.link_id = None
        tag = self._tag(p)
        if p.state is LinkState.AWAIT_CONFIRM and p.link_id == link_id:
            # Accepted already: the leader did not get our ACCEPT. Never veto it now: rival
            # claims we hear are the leader's contest to win or lose, not ours.
            self._count("retries")
        elif self._taken(link_id, tag, p):
            out.append(SendLocal(p.connector, encode_sealed(LocalType.REJECT, link_id, tag)))
            self._enter(p, LinkState.AWAIT_PROPOSE)
            return
        else:
            p.link_id = link_id
            self._enter(p, LinkState.AWAIT_CONFIRM)
        p.sent = self._cycle
        out.append(SendLocal(p.connector, encode_sealed(LocalType.ACCEPT, link_id, tag)))

    # ------------------------------------------------------------------ bus handling

    def _record(self, msg: BusMessage) -> None:
        if msg.op is BusOp.RELEASE:
            seen = self._in_use.get(msg.link_id)
            if seen is not None and seen.tag == msg.tag:
                del self._in_use[msg.link_id]
            self._quarantine[msg.link_id] = self._now + self.quarantine_s
        else:
            self._in_use[msg.link_id] = _Seen(msg.tag, self._now)

    def _on_bus(self, p: _Port, msg: BusMessage, out: list[Action]) -> None:
        """A management frame about the id ``p`` proposes, claims or holds."""
        tag = p.tag
        if msg.tag == tag:
            self._on_own_pair(p, msg, out)
        elif p.state is LinkState.PROPOSING:
            self._count("repicks")  # someone else wants it too: pick before claiming
            self._propose(p, out)
        elif p.state is LinkState.CLAIMING and msg.op is not BusOp.RELEASE:
            if msg.op is BusOp.HOLD or msg.tag < self._tag(p):
                self._lose(p, out)
        elif p.state is LinkState.ESTABLISHED and msg.op is not BusOp.RELEASE:
            if msg.op is BusOp.HOLD and msg.tag < self._tag(p):
                self._lose(p, out)
            else:
                self._defend(p, out)

    def _on_own_pair(self, p: _Port, msg: BusMessage, out: list[Action]) -> None:
        """A frame under our own tag: the other end (or our own echo)."""
        if p.state is not LinkState.ESTABLISHED:
            return
        if msg.op is BusOp.RELEASE:
            # The other end let go (it sensed undock first, or saw us restart): start over.
            self._leave(p, out, release=False)
            self._count("resets")
            self._start(p, out)
        elif not p.leader:
            p.heard = self._now

    def _lose(self, p: _Port, out: list[Action]) -> None:
        """Our pair lost its id to a rival: the leader picks another, the follower waits for it."""
        if p.state is LinkState.ESTABLISHED:
            out.append(Detach(p.connector))
        p.link_id = None
        if p.leader:
            self._count("collisions")
            self._propose(p, out)
        else:
            self._enter(p, LinkState.AWAIT_PROPOSE)

    def _defend(self, p: _Port, out: list[Action]) -> None:
        if p.defended == self._cycle or p.link_id is None:
            return  # at most once a cycle, however many rivals speak
        p.defended = self._cycle
        if p.leader:
            p.announced = self._now
        self._count("defences")
        out.append(self._bus(BusOp.HOLD, p.link_id, self._tag(p)))

    # ------------------------------------------------------------------ once a cycle

    def _tick_port(self, p: _Port, out: list[Action]) -> None:
        if p.state is LinkState.IDLE:
            return
        if p.state in _TIMED and self._cycle - p.entered > self.timeout_ticks:
            self._restart(p, out)
            return
        if not p.proven and p.state in (LinkState.OFFERING, LinkState.AWAIT_PROPOSE, LinkState.PROPOSING):
            self._offer(p, out)
        if p.state is LinkState.PROPOSING:
            self._tick_proposing(p, out)
        elif p.state is LinkState.AWAIT_CONFIRM:
            if p.link_id is not None and self._cycle - p.sent >= self.claim_ticks + self.retry_ticks + 1:
                p.sent = self._cycle
                self._count("retries")
                out.append(SendLocal(p.connector, encode_sealed(LocalType.ACCEPT, p.link_id, self._tag(p))))
        elif p.state is LinkState.CLAIMING:
            self._tick_claiming(p, out)
        elif p.state is LinkState.ESTABLISHED:
            self._tick_established(p, out)

    def _tick_proposing(self, p: _Port, out: list[Action]) -> None:
        if p.link_id is None:
            self._propose(p, out, keep_entered=True)  # no free id last time: try again
        elif self._cycle - p.sent >= self.retry_ticks:
            self._count("retries")
            self._send_propose(p, out)

    def _tick_claiming(self, p: _Port, out: list[Action]) -> None:
        assert p.link_id is not None
        if p.claims < self.claim_ticks:
            p.claims += 1
            out.append(self._bus(BusOp.CLAIM, p.link_id, self._tag(p)))
            return
        self._enter(p, LinkState.ESTABLISHED)
        p.announced = self._now
        self._count("negotiations")
        out.append(SendLocal(p.connector, encode_sealed(LocalType.CONFIRM, p.link_id, self._tag(p))))
        out.append(Attach(p.connector, BusEnd(p.link_id, 0)))

    def _tick_established(self, p: _Port, out: list[Action]) -> None:
        assert p.link_id is not None
        if p.leader:
            if self._now - p.announced >= self.reannounce_s:
                p.announced = self._now
                out.append(self._bus(BusOp.HOLD, p.link_id, self._tag(p)))
        elif self._now - p.heard > self.leader_silence_s:
            self._restart(p, out)  # the leader died: let go before others may reuse the id

    def _age(self) -> None:
        for link_id in [i for i, seen in self._in_use.items() if self._now - seen.at > self.in_use_s]:
            del self._in_use[link_id]
        for link_id in [i for i, until in self._quarantine.items() if until <= self._now]:
            del self._quarantine[link_id]

    # ------------------------------------------------------------------ transitions

    def _enter(self, p: _Port, state: LinkState) -> None:
        p.state = state
        p.entered = self._cycle

    def _start(self, p: _Port, out: list[Action]) -> None:
        """A new negotiation: a fresh nonce, the peer unknown, OFFER at once."""
        p.nonce = self._rng.getrandbits(32)
        p.peer_nonce = None
        p.proven = False
        p.link_id = None
        self._enter(p, LinkState.OFFERING)
        self._offer(p, out)

    def _restart(self, p: _Port, out: list[Action]) -> None:
        self._leave(p, out, release=True)
        self._count("resets")
        self._start(p, out)

    def _leave(self, p: _Port, out: list[Action], *, release: bool) -> None:
        """Drop whatever link or claim ``p`` has: detach, and release the id if it is ours."""
        if p.state is LinkState.ESTABLISHED:
            out.append(Detach(p.connector))
        if release and p.on_bus and p.link_id is not None:
            tag = self._tag(p)
            self._record(BusMessage(BusOp.RELEASE, p.link_id, tag))
            self._count("releases")
            out.append(self._bus(BusOp.RELEASE, p.link_id, tag))
        p.link_id = None

    def _offer(self, p: _Port, out: list[Action]) -> None:
        if p.offered == self._cycle:
            return
        p.offered = self._cycle
        out.append(SendLocal(p.connector, encode_offer(p.nonce)))

    def _propose(self, p: _Port, out: list[Action], *, keep_entered: bool = False) -> None:
        """Pick a candidate and PROPOSE it (or wait a cycle if every id is taken)."""
        if not keep_entered:
            self._enter(p, LinkState.PROPOSING)
        p.link_id = self._pick(p)
        if p.link_id is not None:
            self._send_propose(p, out)

    def _send_propose(self, p: _Port, out: list[Action]) -> None:
        assert p.link_id is not None
        p.sent = self._cycle
        out.append(SendLocal(p.connector, encode_sealed(LocalType.PROPOSE, p.link_id, self._tag(p))))

    def _start_claim(self, p: _Port, out: list[Action]) -> None:
        assert p.link_id is not None
        if self._taken(p.link_id, self._tag(p), p):
            self._count("repicks")  # claimed by others while we proposed it
            self._propose(p, out)
            return
        self._enter(p, LinkState.CLAIMING)
        p.claims = 0

    # ------------------------------------------------------------------ ids

    def _pick(self, p: _Port) -> int | None:
        """A random id nobody is known to use, preferring ids not recently released."""
        lo, hi = self.link_ids
        own = {q.link_id for q in self._ports.values() if q is not p and q.link_id is not None}
        for _ in range(32):
            candidate = self._rng.randint(lo, hi)
            if candidate not in self._in_use and candidate not in self._quarantine and candidate not in own:
                return candidate
        for avoid in (self._quarantine.keys() | own, own):
            free = [i for i in range(lo, hi + 1) if i not in self._in_use and i not in avoid]
            if free:
                return self._rng.choice(free)
        return None

    def _taken(self, link_id: int, tag: int, p: _Port) -> bool:
        """Whether ``link_id`` is known to belong to another pair, or was released lately."""
        seen = self._in_use.get(link_id)
        if seen is not None and seen.tag != tag:
            return True
        if link_id in self._quarantine and seen is None:
            return True
        return any(q is not p and q.link_id == link_id for q in self._ports.values())

    # ------------------------------------------------------------------ small helpers

    def _port(self, connector: int) -> _Port:
        try:
            return self._ports[connector]
        except KeyError:
            raise ValueError(f"connector {connector!r} is not one of {sorted(self._ports)}") from None

    @staticmethod
    def _tag(p: _Port) -> int:
        tag = p.tag
        assert tag is not None
        return tag

    @staticmethod
    def _bus(op: BusOp, link_id: int, tag: int) -> SendBus:
        return SendBus(encode_bus(BusMessage(op, link_id, tag)))

    def _count(self, name: str, n: int = 1) -> None:
        self._counts[name] += n


def _check_connectors(connectors: Iterable[int]) -> None:
    seen: set[int] = set()
    for c in connectors:
        if isinstance(c, bool) or not isinstance(c, int) or c < 1 or c in seen:
            raise ValueError(f"connectors must be distinct positive integers, got {c!r}")
        seen.add(c)
    if not seen:
        raise ValueError("a negotiator needs at least one connector")


def _check_timing(
    claim_ticks: int,
    retry_ticks: int,
    timeout_ticks: int,
    reannounce_s: float,
    leader_silence_s: float,
    in_use_s: float,
    quarantine_s: float,
) -> None:
    if claim_ticks < 2:
        raise ValueError(f"claim_ticks {claim_ticks!r} must be at least 2 (a round trip on the bus)")
    if retry_ticks < 1:
        raise ValueError(f"retry_ticks {retry_ticks!r} must be at least 1")
    if timeout_ticks <= claim_ticks + 2 * retry_ticks:
        raise ValueError(f"timeout_ticks {timeout_ticks!r} must exceed claim_ticks + 2 * retry_ticks")
    if not 0 < reannounce_s < leader_silence_s < in_use_s:
        raise ValueError(
            f"need 0 < reannounce_s ({reannounce_s}) < leader_silence_s ({leader_silence_s}) < in_use_s ({in_use_s})"
        )
    if quarantine_s < 0:
        raise ValueError(f"quarantine_s {quarantine_s!r} must not be negative")
