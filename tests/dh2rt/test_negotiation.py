"""Link negotiation (dh2rt.negotiation) in a simulated robot: many negotiators, one bus.

The harness is deterministic and in-process: a virtual clock advancing ``DT`` per step; a
shared bus delivering every management frame to every other live module of the same bus
partition (and back to its sender with ``echo``) at the next step, or up to ``bus_jitter``
steps later (a module whose cycle runs late); connector-local channels joining the two
connectors of each dock while it is physically made, with optional loss, garbling and
``clc_jitter``; nothing overtakes on one sender-receiver path. Contact edges are fed to each
side at a chosen step (the two sides may sense a dock at different steps). Each step, every
live module is fed what arrived for it, then ticked, in a fixed order. Attach/Detach actions
are applied to each module's attachment table, which refuses an attach on an attached
connector and a detach of a free one; a monitor records every step at which an id is
attached anywhere but at the two opposite ends of one dock (``violations``).

Every property is swept over seeds and over the timing of the contacts (which step each dock
is made, how late each side senses it, how late messages arrive).
"""

from __future__ import annotations

import random
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import pytest

from dh2rt.errors import DecodeError, EncodeError, FrameCorrupted
from dh2rt.negotiation import (
    FIRST_LINK_ID,
    LAST_LINK_ID,
    MANAGEMENT_ID,
    Action,
    Attach,
    BusMessage,
    BusOp,
    Detach,
    LinkNegotiator,
    LinkState,
    LocalType,
    NegotiationCounters,
    Offer,
    Sealed,
    SendBus,
    SendLocal,
    decode_bus,
    decode_local,
    encode_bus,
    encode_offer,
    encode_sealed,
    management_filter,
)
from dh2rt.transport.base import BusEnd
from dh2rt.wire.can_frames import MAX_LINK_ID, SINGLE, parse_arbitration_id

DT = 0.02  # 50 Hz cycles
SEEDS = range(6)
REANNOUNCE_STEPS = round(1.0 / DT)  # the default reannounce_s in steps
#: Few ids to pick from, so that a stale id picked again would not go unnoticed.
SMALL_POOL = (1, 4)
#: Delivery timings: everything arrives the next step; or bus frames up to 1 step and CLC
#: messages up to 2 steps later, with the claim window grown by the bus round trip's slack.
LATENESS = [
    pytest.param({}, id="prompt"),
    pytest.param({"bus_jitter": 1, "clc_jitter": 2, "claim_ticks": 4}, id="late"),
]


# ---------------------------------------------------------------------------------------------
# The simulated world


@dataclass(frozen=True)
class LocalIn:
    connector: int
    data: bytes


@dataclass(frozen=True)
class BusIn:
    data: bytes


@dataclass(frozen=True)
class ContactIn:
    connector: int
    made: bool


Input = LocalIn | BusIn | ContactIn


class Rigged(random.Random):
    """A seeded generator whose first draws are forced. The negotiator draws nonces with
    ``getrandbits(32)`` and candidate ids with ``randint`` (its docstring says so); other
    internal draws (``randint``'s own, ``choice``) use fewer bits and are left alone."""

    def __init__(self, seed: str, *, nonces: Sequence[int] = (), picks: Sequence[int] = ()) -> None:
        super().__init__(seed)
        self.nonces = list(nonces)
        self.picks = list(picks)
        self.nonce_draws = 0

    def getrandbits(self, k: int, /) -> int:
        if k == 32:
            self.nonce_draws += 1
            if self.nonces:
                return self.nonces.pop(0)
        return super().getrandbits(k)

    def randint(self, a: int, b: int) -> int:
        if self.picks:
            return self.picks.pop(0)
        return super().randint(a, b)


@dataclass
class Node:
    """A module: its negotiator and what its transport is attached to."""

    name: str
    connectors: tuple[int, ...]
    neg: LinkNegotiator
    partition: int = 0
    alive: bool = True
    attached: dict[int, BusEnd] = field(default_factory=dict)
    history: list[tuple[int, Action]] = field(default_factory=list)  # (step, Attach | Detach)

    def detaches(self, connector: int | None = None, since: int = 0) -> list[int]:
        """Steps at which ``connector`` (any, if None) was detached."""
        return [
            s
            for s, a in self.history
            if isinstance(a, Detach) and s >= since and (connector is None or a.connector == connector)
        ]


@dataclass(eq=False)
class Dock:
    """Two connectors that touch (``made``) or not; the CLC joins them while made."""

    a: tuple[str, int]
    b: tuple[str, int]
    made: bool = False

    def other(self, end: tuple[str, int]) -> tuple[str, int]:
        return self.b if end == self.a else self.a


class World:
    """Negotiators on one simulated bus (see the module docstring)."""

    def __init__(
        self,
        seed: int,
        *,
        loss: float = 0.0,
        garble: float = 0.0,
        echo: bool = False,
        clc_jitter: int = 0,
        bus_jitter: int = 0,
        monitor: bool = True,
        **options: Any,
    ) -> None:
        self.seed = seed
        self.loss = loss
        self.garble = garble
        self.echo = echo
        self.clc_jitter = clc_jitter
        self.bus_jitter = bus_jitter
        self.monitor = monitor
        self.options = options
        self.rng = random.Random(f"world/{seed}")
        self.nodes: dict[str, Node] = {}
        self.docks: list[Dock] = []
        self._dock_at: dict[tuple[str, int], Dock] = {}
        self.step_no = 0
        self.now = 0.0
        self._mail: dict[int, dict[str, list[Input]]] = defaultdict(lambda: defaultdict(list))
        self._last_mail: dict[tuple[str, str], int] = {}  # keeps each sender->receiver in order
        self._due: dict[int, list[Callable[[], None]]] = defaultdict(list)
        self._lives: dict[str, int] = defaultdict(int)
        self.rngs: dict[str, random.Random] = {}
        self.bus_log: list[tuple[int, str, BusMessage]] = []
        self.violations: list[tuple[int, int, list[tuple[str, BusEnd]]]] = []

    # ---------------------------------------------------------------- building

    def add(self, name: str, connectors: Sequence[int] = (1, 2, 3, 4), rng: random.Random | None = None) -> Node:
        self._lives[name] += 1
        rng = rng or random.Random(f"{self.seed}/{name}/{self._lives[name]}")
        self.rngs[name] = rng
        old = self.nodes.get(name)
        node = Node(name, tuple(connectors), LinkNegotiator(connectors, rng, now=self.now, **self.options))
        if old is not None:
            node.partition = old.partition
        self.nodes[name] = node
        return node

    def dock(self, a: str, ca: int, b: str, cb: int, *, at: int = 0, skew: int = 0) -> Dock:
        """Connectors touch from step ``at``; ``a`` senses it then, ``b`` ``skew`` steps later."""
        dock = Dock((a, ca), (b, cb))
        self.docks.append(dock)
        self._dock_at[dock.a] = dock
        self._dock_at[dock.b] = dock
        self.redock(dock, at=at, skew=skew)
        return dock

    def redock(self, dock: Dock, *, at: int, skew: int = 0) -> None:
        self._at(at, lambda: setattr(dock, "made", True))
        self._sense(dock.a, True, at)
        self._sense(dock.b, True, at + skew)

    def undock(self, dock: Dock, *, at: int, skew: int = 0, sensed: tuple[bool, bool] = (True, True)) -> None:
        """The connectors part at step ``at``; each side senses it (if ``sensed``) then or
        ``skew`` steps later."""
        self._at(at, lambda: setattr(dock, "made", False))
        if sensed[0]:
            self._sense(dock.a, False, at)
        if sensed[1]:
            self._sense(dock.b, False, at + skew)

    def kill(self, name: str) -> None:
        """The module stops at once: no more inputs or ticks, its transport is gone."""
        node = self.nodes[name]
        node.alive = False
        node.attached.clear()
        for box in self._mail.values():
            box.pop(name, None)

    def restart(self, name: str, rng: random.Random | None = None) -> Node:
        """A fresh process on the same module: it reads its contact sensors at start-up."""
        old = self.nodes[name]
        node = self.add(name, old.connectors, rng)
        for (n, c), dock in self._dock_at.items():
            if n == name and dock.made:
                self._mail[self.step_no][name].append(ContactIn(c, True))
        return node

    def _at(self, step: int, change: Callable[[], None]) -> None:
        """Make ``change`` at the start of ``step`` (now, if that step has begun or passed)."""
        if step <= self.step_no:
            change()
        else:
            self._due[step].append(change)

    def _sense(self, end: tuple[str, int], made: bool, step: int) -> None:
        def deliver() -> None:
            self._mail[self.step_no][end[0]].append(ContactIn(end[1], made))

        self._at(step, deliver)  # queued before the step's mail is taken: read in that step

    def _post(self, sender: str, receiver: str, item: Input, jitter: int) -> None:
        """Deliver ``item`` next step, or up to ``jitter`` steps later, never overtaking."""
        at = self.step_no + 1 + (self.rng.randrange(jitter + 1) if jitter else 0)
        at = max(at, self._last_mail.get((sender, receiver), 0))
        self._last_mail[sender, receiver] = at
        self._mail[at][receiver].append(item)

    # ---------------------------------------------------------------- running

    def step(self) -> None:
        for change in self._due.pop(self.step_no, []):
            change()
        inboxes = self._mail.pop(self.step_no, {})
        for node in self.nodes.values():
            if not node.alive:
                continue
            for item in inboxes.get(node.name, []):
                self._apply(node, self._feed(node, item))
            self._apply(node, node.neg.tick(self.now))
        if self.monitor:
            self._watch()
        self.step_no += 1
        self.now = self.step_no * DT

    def run(self, steps: int) -> None:
        for _ in range(steps):
            self.step()

    def run_until(self, done: Callable[[], bool], limit: int) -> int:
        """Steps until ``done()`` holds (checked after each step); fails past ``limit``."""
        start = self.step_no
        while not done():
            assert self.step_no - start < limit, f"not done within {limit} steps (seed {self.seed})"
            self.step()
        return self.step_no - start

    def _feed(self, node: Node, item: Input) -> list[Action]:
        if isinstance(item, ContactIn):
            return node.neg.contact(item.connector, item.made)
        if isinstance(item, LocalIn):
            if not self._dock_at[node.name, item.connector].made:
                return []  # parted while the message was under way
            return node.neg.local_received(item.connector, item.data)
        return node.neg.bus_received(item.data)

    def _apply(self, node: Node, actions: Iterable[Action]) -> None:
        for a in actions:
            if isinstance(a, SendLocal):
                assert len(a.data) <= 8, a
                self._send_local(node, a)
            elif isinstance(a, SendBus):
                self._send_bus(node, a.data)
            elif isinstance(a, Attach):
                assert a.connector not in node.attached, f"{node.name} attached {a.connector} twice"
                node.attached[a.connector] = a.end
                node.history.append((self.step_no, a))
            else:
                assert a.connector in node.attached, f"{node.name} detached a free connector {a.connector}"
                del node.attached[a.connector]
                node.history.append((self.step_no, a))

    def _send_local(self, node: Node, a: SendLocal) -> None:
        dock = self._dock_at.get((node.name, a.connector))
        assert dock is not None, f"{node.name} sent over connector {a.connector}, which touches nothing"
        if not dock.made or self.rng.random() < self.loss:
            return
        data = _garbled(a.data, self.rng) if self.rng.random() < self.garble else a.data
        name, connector = dock.other((node.name, a.connector))
        self._post(node.name, name, LocalIn(connector, data), self.clc_jitter)

    def _send_bus(self, node: Node, data: bytes) -> None:
        assert len(data) == 8
        self.bus_log.append((self.step_no, node.name, decode_bus(data)))
        self.broadcast(data, partition=node.partition, sender=node.name)

    def broadcast(
        self, data: bytes, *, partition: int = 0, sender: str | None = None, only: Sequence[str] | None = None
    ) -> None:
        """Put a management frame on the bus (from ``sender``, or injected from outside);
        ``only``: the modules that receive it (the others' receive queues overflowed)."""
        for other in self.nodes.values():
            if not other.alive or other.partition != partition or (other.name == sender and not self.echo):
                continue
            if only is None or other.name in only:
                self._post(sender or "outside", other.name, BusIn(data), self.bus_jitter)

    def _watch(self) -> None:
        """Safety: an id is never attached at more than the two ends of one dock."""
        by_id: dict[int, list[tuple[str, BusEnd, int]]] = defaultdict(list)
        for node in self.nodes.values():
            for c, end in node.attached.items():
                by_id[end.link_id].append((node.name, end, c))
        for link_id, ends in by_id.items():
            if len(ends) == 1:
                continue
            docks = {id(self._dock_at[(n, c)]) for n, _, c in ends}
            if len(ends) > 2 or len(docks) > 1 or {e.side for _, e, _ in ends} != {0, 1}:
                self.violations.append((self.step_no, link_id, [(n, e) for n, e, _ in ends]))

    # ---------------------------------------------------------------- what came of it

    def link_id(self, dock: Dock) -> int | None:
        """The dock's id if both ends are attached to it with opposite sides, else None."""
        ea = self.nodes[dock.a[0]].attached.get(dock.a[1])
        eb = self.nodes[dock.b[0]].attached.get(dock.b[1])
        if ea is None or eb is None or ea.link_id != eb.link_id or ea.side == eb.side:
            return None
        return ea.link_id

    def all_linked(self) -> bool:
        """Every made dock between live modules is linked, all ids distinct, no attachment
        anywhere else."""
        live = [d for d in self.docks if d.made and self.nodes[d.a[0]].alive and self.nodes[d.b[0]].alive]
        ids = [self.link_id(d) for d in live]
        if None in ids or len(set(ids)) != len(ids):
            return False
        attached = sum(len(n.attached) for n in self.nodes.values() if n.alive)
        return attached == 2 * len(live)

    def settled(self) -> bool:
        """Every scheduled dock, undock and contact edge happened, and :meth:`all_linked`."""
        return not any(self._due.values()) and self.all_linked()

    def counters(self) -> NegotiationCounters:
        """The counters of every live module, summed."""
        totals = dict.fromkeys(NegotiationCounters.__dataclass_fields__, 0)
        for node in self.nodes.values():
            if node.alive:
                for k in totals:
                    totals[k] += getattr(node.neg.counters, k)
        return NegotiationCounters(**totals)

    def sent(self, op: BusOp, link_id: int | None = None, since: int = 0) -> list[tuple[int, str, BusMessage]]:
        return [e for e in self.bus_log if e[2].op is op and e[0] >= since and link_id in (None, e[2].link_id)]


def _garbled(data: bytes, rng: random.Random) -> bytes:
    """One of: a bit flipped, a byte replaced, the message cut short, a byte added."""
    b = bytearray(data)
    mode = rng.randrange(4)
    if mode == 0:
        i = rng.randrange(len(b) * 8)
        b[i // 8] ^= 1 << (i % 8)
    elif mode == 1:
        b[rng.randrange(len(b))] = rng.randrange(256)
    elif mode == 2:
        del b[rng.randrange(len(b)) :]
    else:
        b.insert(rng.randrange(len(b) + 1), rng.randrange(256))
    return bytes(b)


# ---------------------------------------------------------------------------------------------
# Robots


def pairs(world: World, n: int, *, at: Callable[[int], int] = lambda i: 2, skew: int = 0) -> list[Dock]:
    """``n`` separate pairs of modules (front to back), pair ``i`` docking at ``at(i)``."""
    docks = []
    for i in range(n):
        world.add(f"p{i}a")
        world.add(f"p{i}b")
        docks.append(world.dock(f"p{i}a", 2, f"p{i}b", 1, at=at(i), skew=skew))
    return docks


def snake(world: World, n: int, *, at: Callable[[int], int] = lambda i: 2) -> list[Dock]:
    """``n`` modules back (2) to front (1); link ``i`` docks at ``at(i)``."""
    for i in range(n):
        world.add(f"s{i}")
    return [world.dock(f"s{i}", 2, f"s{i + 1}", 1, at=at(i)) for i in range(n - 1)]


def branching(world: World, *, at: Callable[[int], int] = lambda i: 2) -> list[Dock]:
    """A hub with all four connectors docked: three legs (left, right, back) and a head, a
    two-module tail behind the back leg."""
    for name in ("hub", "head", "left", "right", "back", "tail"):
        world.add(name)
    shape = [("hub", 1, "head", 2), ("hub", 3, "left", 1), ("hub", 4, "right", 1), ("hub", 2, "back", 1)]
    shape.append(("back", 2, "tail", 1))
    return [world.dock(a, ca, b, cb, at=at(i)) for i, (a, ca, b, cb) in enumerate(shape)]


def timing(kind: str, seed: int) -> Callable[[int], int]:
    """When dock ``i`` is made: all in one step, staggered at random, or one after another."""
    rng = random.Random(f"timing/{kind}/{seed}")
    if kind == "together":
        return lambda i: 3
    if kind == "random":
        steps: dict[int, int] = {}
        return lambda i: steps.setdefault(i, rng.randrange(1, 40))
    return lambda i: 1 + 7 * i  # "sequential"


def leader_end(world: World, dock: Dock) -> tuple[str, int]:
    """The end of ``dock`` attached as side 0."""
    for end in (dock.a, dock.b):
        attached = world.nodes[end[0]].attached.get(end[1])
        if attached is not None and attached.side == 0:
            return end
    raise AssertionError("no end of the dock is side 0")


# ---------------------------------------------------------------------------------------------
# Message formats


def test_offer_round_trip() -> None:
    data = encode_offer(0xDEADBEEF)
    assert len(data) == 8 and data[0] == LocalType.OFFER
    assert decode_local(data) == Offer(0xDEADBEEF)


@pytest.mark.parametrize("kind", [LocalType.PROPOSE, LocalType.ACCEPT, LocalType.CONFIRM, LocalType.REJECT])
def test_sealed_message_opens_only_under_its_tag(kind: LocalType) -> None:
    data = encode_sealed(kind, 0x2ABCD, 0x1234_5678)
    assert len(data) == 8
    msg = decode_local(data)
    assert isinstance(msg, Sealed) and msg.kind is kind and msg.link_id == 0x2ABCD
    assert msg.opens(0x1234_5678)
    assert not msg.opens(0x1234_5679)


@pytest.mark.parametrize("kind", list(LocalType))
def test_every_single_bit_error_is_caught(kind: LocalType) -> None:
    """A flipped bit anywhere in a CLC message fails decoding (OFFER's check, the type, the id
    range) or the seal: never a different message that is accepted."""
    tag = 0x0BAD_F00D
    data = encode_offer(0x600DCAFE) if kind is LocalType.OFFER else encode_sealed(kind, 12345, tag)
    for bit in range(64):
        flipped = bytearray(data)
        flipped[bit // 8] ^= 1 << (bit % 8)
        try:
            msg = decode_local(bytes(flipped))
        except DecodeError:
            continue
        assert isinstance(msg, Sealed) and not msg.opens(tag), f"bit {bit}: {msg}"


def test_bus_round_trip_and_management_id() -> None:
    for op in BusOp:
        msg = BusMessage(op, LAST_LINK_ID, 0xFFFF_FFFF)
        data = encode_bus(msg)
        assert len(data) == 8 and decode_bus(data) == msg
    f = parse_arbitration_id(MANAGEMENT_ID)
    assert (f.kind, f.segment, f.seq, f.link_id, f.side) == (3, SINGLE, 0, MAX_LINK_ID, 0)
    assert management_filter() == {"can_id": MANAGEMENT_ID, "can_mask": (1 << 29) - 1, "extended": True}
    assert SendBus(encode_bus(BusMessage(BusOp.CLAIM, 5, 9))).frame.arbitration_id == MANAGEMENT_ID


@pytest.mark.parametrize(
    "encode",
    [
        lambda: encode_offer(1 << 32),
        lambda: encode_offer(-1),
        lambda: encode_sealed(LocalType.PROPOSE, 0, 1),
        lambda: encode_sealed(LocalType.PROPOSE, MAX_LINK_ID, 1),
        lambda: encode_sealed(LocalType.PROPOSE, 5, 0),
        lambda: encode_sealed(LocalType.OFFER, 5, 1),
        lambda: encode_bus(BusMessage(BusOp.CLAIM, 0, 1)),
        lambda: encode_bus(BusMessage(BusOp.HOLD, 5, 0)),
        lambda: encode_bus(BusMessage(BusOp.HOLD, 5, 1 << 32)),
    ],
)
def test_encoders_refuse_values_out_of_range(encode: Callable[[], bytes]) -> None:
    with pytest.raises(EncodeError):
        encode()


@pytest.mark.parametrize(
    "data",
    [
        b"",
        encode_offer(7)[:7],
        encode_offer(7) + b"\x00",
        bytes([9]) + bytes(7),
        bytes([0]) + bytes(7),
        bytes([LocalType.ACCEPT]) + bytes(3) + bytes([1, 2, 3, 4]),  # link id 0
        bytes([LocalType.ACCEPT]) + MAX_LINK_ID.to_bytes(3, "big") + bytes([1, 2, 3, 4]),
    ],
)
def test_local_decoder_refuses_garbage(data: bytes) -> None:
    with pytest.raises(DecodeError):
        decode_local(data)


def test_offer_with_a_bad_check_is_corrupted() -> None:
    data = bytearray(encode_offer(42))
    data[7] ^= 1
    with pytest.raises(FrameCorrupted):
        decode_local(bytes(data))


@pytest.mark.parametrize(
    "data",
    [
        b"",
        bytes(7),
        bytes(9),
        bytes([0, 0, 0, 5, 0, 0, 0, 1]),  # op 0
        bytes([4, 0, 0, 5, 0, 0, 0, 1]),  # op 4
        bytes([1, 0, 0, 0, 0, 0, 0, 1]),  # link id 0
        bytes([1, 3, 0xFF, 0xFF, 0, 0, 0, 1]),  # link id MAX_LINK_ID
        bytes([1, 0, 0, 5, 0, 0, 0, 0]),  # tag 0
    ],
)
def test_bus_decoder_refuses_garbage(data: bytes) -> None:
    with pytest.raises(DecodeError):
        decode_bus(data)


# ---------------------------------------------------------------------------------------------
# The negotiator's own checks


@pytest.mark.parametrize(
    "kwargs",
    [
        {"connectors": []},
        {"connectors": [1, 1]},
        {"connectors": [0]},
        {"claim_ticks": 1},
        {"retry_ticks": 0},
        {"timeout_ticks": 5},
        {"reannounce_s": 4.0},
        {"leader_silence_s": 6.0},
        {"quarantine_s": -1.0},
        {"link_ids": (0, 10)},
        {"link_ids": (10, 9)},
        {"link_ids": (1, MAX_LINK_ID)},
    ],
)
def test_bad_settings_are_refused(kwargs: dict[str, object]) -> None:
    args: dict[str, object] = {"connectors": [1, 2], "rng": random.Random(0)}
    args.update(kwargs)
    with pytest.raises(ValueError):
        LinkNegotiator(**args)  # type: ignore[arg-type]


def test_unknown_connector_is_refused() -> None:
    neg = LinkNegotiator([1, 2], random.Random(0))
    with pytest.raises(ValueError, match="connector 3"):
        neg.contact(3, True)


def test_a_lone_contact_offers_every_cycle_and_never_attaches() -> None:
    """Touching something that does not answer: the same OFFER each cycle, nothing else."""
    neg = LinkNegotiator([1], random.Random(0))
    actions = neg.contact(1, True)
    for n in range(1, 50):
        actions += neg.tick(n * DT)
    sent = [a.data for a in actions if isinstance(a, SendLocal) and a.connector == 1]
    assert len(sent) == len(actions) == 49  # at contact, then one per cycle after the contact's
    assert len(set(sent)) == 1 and isinstance(decode_local(sent[0]), Offer)
    assert neg.state(1) is LinkState.OFFERING and not neg.links


# ---------------------------------------------------------------------------------------------
# Two modules


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("skew", [0, 1, 4])
def test_two_modules_dock_and_agree(seed: int, skew: int) -> None:
    world = World(seed, echo=seed % 2 == 1)
    a, b = world.add("a"), world.add("b")
    dock = world.dock("a", 2, "b", 1, at=3 + seed, skew=skew)
    world.run_until(lambda: world.link_id(dock) is not None, limit=3 + seed + skew + 12)
    link_id = world.link_id(dock)
    assert link_id is not None and FIRST_LINK_ID <= link_id <= LAST_LINK_ID
    assert {a.attached[2].side, b.attached[1].side} == {0, 1}
    world.run(3 * REANNOUNCE_STEPS + 5)  # and it stays so, re-announced
    assert world.link_id(dock) == link_id
    assert [type(x) for _, x in a.history] == [Attach] and [type(x) for _, x in b.history] == [Attach]
    leader = leader_end(world, dock)[0]
    claims = world.sent(BusOp.CLAIM)
    assert len(claims) == 3 and {name for _, name, _ in claims} == {leader}
    assert len(world.sent(BusOp.HOLD)) == 3  # one a second, only from the leader
    assert not world.sent(BusOp.RELEASE)
    assert a.neg.counters.negotiations == b.neg.counters.negotiations == 1
    assert a.neg.links == {2: a.attached[2]} and b.neg.links == {1: b.attached[1]}
    assert not world.violations


def test_a_nonce_tie_is_redrawn() -> None:
    world = World(0)
    ra = Rigged("tie/a", nonces=[0x1234_5678])
    rb = Rigged("tie/b", nonces=[0x1234_5678])
    world.add("a", rng=ra)
    world.add("b", rng=rb)
    dock = world.dock("a", 1, "b", 1, at=1)
    world.run_until(lambda: world.link_id(dock) is not None, limit=20)
    assert ra.nonce_draws == rb.nonce_draws == 2


# ---------------------------------------------------------------------------------------------
# Many docks on one bus


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("when", ["together", "random"])
@pytest.mark.parametrize("late", LATENESS)
def test_twenty_pairs_get_distinct_links(seed: int, when: str, late: dict[str, Any]) -> None:
    world = World(seed, echo=True, **late)
    docks = pairs(world, 20, at=timing(when, seed))
    world.run_until(world.settled, limit=60)
    assert len({world.link_id(d) for d in docks}) == 20
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("late", LATENESS)
def test_twenty_pairs_drawing_the_same_id_at_once(seed: int, late: dict[str, Any]) -> None:
    """Every leader's first candidate is 4242: one pair keeps it, the 19 others lose the
    claim and pick again; no two pairs are ever attached to one id."""
    world = World(seed, **late)
    for i in range(20):
        for side in "ab":
            world.add(f"p{i}{side}", rng=Rigged(f"{seed}/p{i}{side}", picks=[4242]))
    docks = [world.dock(f"p{i}a", 2, f"p{i}b", 1, at=3) for i in range(20)]
    world.run_until(world.settled, limit=60)
    assert len({world.link_id(d) for d in docks}) == 20
    assert [world.link_id(d) for d in docks].count(4242) == 1
    totals = world.counters()
    # 19 pairs gave 4242 up: in a claim contest, or (when late messages spread the claims out)
    # before claiming, having heard another pair's claim
    assert totals.collisions + totals.repicks >= 19
    assert totals.collisions >= (19 if not late else 1)
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("when", ["together", "random"])
def test_twenty_pairs_share_a_pool_of_twenty_ids(seed: int, when: str) -> None:
    """With exactly 20 ids to go round, every id ends up used once: collisions are the norm."""
    world = World(seed, link_ids=(1, 20))
    docks = pairs(world, 20, at=timing(when, seed))
    world.run_until(world.settled, limit=400)
    assert sorted(world.link_id(d) or 0 for d in docks) == list(range(1, 21))
    totals = world.counters()
    assert totals.collisions > 0 if when == "together" else totals.collisions + totals.repicks > 0
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
def test_a_snake_of_21_docking_at_once(seed: int) -> None:
    world = World(seed)
    docks = snake(world, 21, at=lambda i: 4)
    world.run_until(world.settled, limit=60)
    assert len({world.link_id(d) for d in docks}) == 20
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("when", ["together", "random", "sequential"])
@pytest.mark.parametrize("shape", [snake, branching], ids=["snake8", "branching"])
@pytest.mark.parametrize("late", LATENESS)
def test_robots_link_up(seed: int, when: str, shape: Callable[..., list[Dock]], late: dict[str, Any]) -> None:
    world = World(seed, **late)
    docks = shape(world, 8, at=timing(when, seed)) if shape is snake else shape(world, at=timing(when, seed))
    world.run_until(world.settled, limit=80)
    if shape is branching:
        assert len(world.nodes["hub"].attached) == 4
    world.run(2 * REANNOUNCE_STEPS)
    assert world.all_linked()
    assert all(len(n.history) == len(n.attached) for n in world.nodes.values()), "a link was dropped"
    assert len(docks) == len({world.link_id(d) for d in docks})
    assert not world.violations


# ---------------------------------------------------------------------------------------------
# Collisions between established pairs


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("phase", [0, 17, 49])
def test_two_established_pairs_on_one_id_are_separated(seed: int, phase: int) -> None:
    """Two pairs establish id 77 on two separate buses; the buses are joined (two robots
    docking together). Within one re-announce period one pair yields; the other never
    detaches."""
    world = World(seed)
    for i, partition in ((0, 1), (1, 2)):
        for side in "ab":
            world.add(f"p{i}{side}", rng=Rigged(f"{seed}/p{i}{side}", picks=[77])).partition = partition
    docks = [world.dock(f"p{i}a", 2, f"p{i}b", 1, at=2 + 5 * i) for i in range(2)]
    world.run_until(lambda: all(world.link_id(d) == 77 for d in docks), limit=30)
    world.run(phase)
    joined = world.step_no
    for node in world.nodes.values():
        node.partition = 0
    world.run_until(lambda: world.link_id(docks[0]) != world.link_id(docks[1]), limit=REANNOUNCE_STEPS + 3)
    world.run_until(world.settled, limit=20)
    winner, loser = (docks[0], docks[1]) if world.link_id(docks[0]) == 77 else (docks[1], docks[0])
    assert world.link_id(loser) not in (None, 77)
    for end in (winner.a, winner.b):
        assert world.nodes[end[0]].detaches(end[1]) == [], "the winner was disturbed"
    for end in (loser.a, loser.b):
        assert len(world.nodes[end[0]].detaches(end[1], since=joined)) == 1
    assert world.counters().collisions == 1
    assert all(step < joined + REANNOUNCE_STEPS + 3 for step, *_ in world.violations)


@pytest.mark.parametrize("seed", SEEDS)
def test_an_injected_hold_with_a_lower_tag_takes_the_id(seed: int) -> None:
    """A forged HOLD for our id with the lowest tag there is: both ends yield at once and the
    pair moves to a fresh id."""
    world = World(seed)
    world.add("a")
    world.add("b")
    dock = world.dock("a", 1, "b", 1, at=1)
    world.run_until(world.settled, limit=20)
    old = world.link_id(dock)
    assert old is not None
    world.broadcast(encode_bus(BusMessage(BusOp.HOLD, old, 1)))
    world.step()
    world.step()
    assert world.link_id(dock) is None and not any(n.attached for n in world.nodes.values())
    world.run_until(world.settled, limit=15)
    assert world.link_id(dock) != old
    assert world.counters().collisions == 1


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("later", [1, 20, 45])
@pytest.mark.parametrize("late", LATENESS)
def test_newcomers_claiming_a_held_id_yield(seed: int, later: int, late: dict[str, Any]) -> None:
    """Two modules that started after the last HOLD (so they know nothing of the bus) dock
    ``later`` steps after a pair established an id, and their leader tries that very id: the
    owners' HOLD beats the claim, the newcomers pick again, the owners never notice."""
    world = World(seed, **late)
    world.add("a")
    world.add("b")
    owners = world.dock("a", 1, "b", 1, at=1)
    world.run_until(world.settled, limit=20)
    held = world.link_id(owners)
    assert held is not None
    world.run(later)
    for name in ("c", "d"):
        world.add(name, rng=Rigged(f"{seed}/{name}", picks=[held]))
    newcomers = world.dock("c", 1, "d", 1, at=world.step_no)
    world.run_until(world.settled, limit=25)
    assert world.link_id(owners) == held and world.link_id(newcomers) != held
    assert len(world.nodes["a"].history) == len(world.nodes["b"].history) == 1
    totals = world.counters()
    if later < REANNOUNCE_STEPS - 5:  # no HOLD in between: they could only learn of it by claiming
        assert totals.collisions == 1 and totals.defences >= 1
    else:  # a re-announce may come first: then they never propose or never claim it
        assert totals.collisions <= 1 and (totals.collisions == 0) == (totals.defences == 0)
    assert not world.violations


@pytest.mark.parametrize("claim_ticks", [2, 4])
def test_the_claim_window_must_cover_the_bus_round_trip(claim_ticks: int) -> None:
    """With bus frames up to a step late, a claim's round trip (claim -> owner's next cycle ->
    HOLD -> claimer's next cycle) takes up to 4 cycles: a 2-cycle window lets newcomers
    conclude before the owners' defence arrives (two pairs on one id), a 4-cycle one never."""
    unsafe = 0
    for seed in range(12):
        world = World(seed, bus_jitter=1, claim_ticks=claim_ticks)
        world.add("a")
        world.add("b")
        owners = world.dock("a", 1, "b", 1, at=1)
        world.run_until(world.settled, limit=20)
        for name in ("c", "d"):
            world.add(name, rng=Rigged(f"{seed}/{name}", picks=[world.link_id(owners) or 0]))
        world.dock("c", 1, "d", 1, at=world.step_no)
        world.run_until(world.settled, limit=4 * REANNOUNCE_STEPS)
        unsafe += bool(world.violations)
    assert (unsafe > 0) == (claim_ticks == 2)


@pytest.mark.parametrize("seed", SEEDS)
def test_a_hold_only_the_follower_heard(seed: int) -> None:
    """A rival HOLD reaches the follower but not the leader (its receive queue overflowed):
    the follower yields and waits for a new PROPOSE that never comes; after ``timeout_ticks``
    it starts over, the leader sees the new OFFER, releases the id, and the pair relinks."""
    world = World(seed)
    world.add("a")
    world.add("b")
    dock = world.dock("a", 1, "b", 1, at=1)
    world.run_until(world.settled, limit=20)
    old = world.link_id(dock)
    assert old is not None
    follower = dock.other(leader_end(world, dock))
    world.broadcast(encode_bus(BusMessage(BusOp.HOLD, old, 1)), only=[follower[0]])
    world.step()
    world.step()
    assert follower[1] not in world.nodes[follower[0]].attached
    timeout = world.nodes[follower[0]].neg.timeout_ticks
    world.run(timeout - 2)
    assert world.link_id(dock) is None  # still waiting
    world.run_until(world.settled, limit=15)
    assert world.link_id(dock) != old and world.counters().resets >= 2


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("op", [BusOp.CLAIM, BusOp.HOLD])
def test_an_injected_rival_that_should_lose_is_answered(seed: int, op: BusOp) -> None:
    """A rival CLAIM (any tag: established beats claiming) or a rival HOLD with the highest
    tag: both ends answer with a HOLD at once and keep the link."""
    world = World(seed)
    world.add("a")
    world.add("b")
    dock = world.dock("a", 1, "b", 1, at=1)
    world.run_until(world.settled, limit=20)
    link_id = world.link_id(dock)
    assert link_id is not None
    tag = 1 if op is BusOp.CLAIM else 0xFFFF_FFFF
    injected = world.step_no
    world.broadcast(encode_bus(BusMessage(op, link_id, tag)))
    world.run(2)
    holds = world.sent(BusOp.HOLD, link_id, since=injected)
    assert {name for _, name, _ in holds} == {"a", "b"}
    assert world.counters().defences == 2
    assert world.link_id(dock) == link_id and all(len(n.history) == 1 for n in world.nodes.values())


# ---------------------------------------------------------------------------------------------
# Undock, re-dock, restart


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("skew", [0, 3])
@pytest.mark.parametrize("away", [1, 10, 200])
@pytest.mark.parametrize("late", LATENESS)
def test_undock_releases_and_redock_gets_a_fresh_id(seed: int, skew: int, away: int, late: dict[str, Any]) -> None:
    world = World(seed, link_ids=SMALL_POOL, **late)  # a re-used id would show in one seed of four
    world.add("a")
    world.add("b")
    dock = world.dock("a", 3, "b", 4, at=2)
    world.run_until(world.settled, limit=20)
    old = world.link_id(dock)
    apart = world.step_no + 5
    world.undock(dock, at=apart, skew=skew)
    world.run(5 + skew + 1)
    assert not any(n.attached for n in world.nodes.values())
    # the first to sense it releases; the other hears that (with skew 0 both send one)
    assert {name for _, name, _ in world.sent(BusOp.RELEASE, old)} == ({"a", "b"} if skew == 0 else {"a"})
    assert world.nodes["a"].detaches(3) and world.nodes["b"].detaches(4)
    assert all(old in n.neg.ids_quarantined for n in world.nodes.values())
    world.redock(dock, at=apart + away)
    world.run_until(lambda: world.link_id(dock) is not None, limit=away + 20)
    assert world.link_id(dock) != old
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("newcomer_leads", [False, True])
def test_a_newcomer_never_gets_a_released_id(seed: int, newcomer_leads: bool) -> None:
    """``b`` undocks from ``a`` and docks with ``c``, which started after the RELEASE and knows
    nothing of it, and whose leader is forced to try the released id first. If ``b`` leads, its
    own quarantine keeps it off that id; if ``c`` leads, ``b`` REJECTs it."""
    world = World(seed, link_ids=SMALL_POOL)
    world.add("a")
    rb = Rigged(f"{seed}/b")
    world.add("b", rng=rb)
    first = world.dock("a", 2, "b", 1, at=2)
    world.run_until(world.settled, limit=20)
    old = world.link_id(first)
    assert old is not None
    world.undock(first, at=world.step_no + 1)
    world.run(3)
    rc = Rigged(f"{seed}/c", nonces=[0xFFFF_FFFF if newcomer_leads else 0], picks=[old])
    rb.picks = [old]
    world.add("c", rng=rc)
    second = world.dock("b", 1, "c", 2, at=world.step_no + 1)
    world.run_until(world.settled, limit=20)
    assert world.link_id(second) not in (None, old)
    assert (leader_end(world, second)[0] == "c") == newcomer_leads
    assert world.counters().repicks == (1 if newcomer_leads else 0)  # the REJECT
    assert (not rc.picks, not rb.picks) == (newcomer_leads, not newcomer_leads)  # the leader's forced pick was drawn


@pytest.mark.parametrize("seed", SEEDS)
def test_undocking_one_link_leaves_the_others_alone(seed: int) -> None:
    world = World(seed)
    docks = snake(world, 5, at=timing("random", seed))
    world.run_until(world.settled, limit=80)
    before = {d: world.link_id(d) for d in docks}
    world.undock(docks[1], at=world.step_no + 1, skew=1)
    world.run(2 * REANNOUNCE_STEPS)
    assert world.all_linked()  # docks[1] is no longer made
    assert all(world.link_id(d) == before[d] for d in docks if d is not docks[1])
    assert world.link_id(docks[1]) is None
    assert sum(len(n.detaches()) for n in world.nodes.values()) == 2


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("missed_by", [0, 1])
def test_a_bounce_one_side_missed(seed: int, missed_by: int) -> None:
    """The connectors part and touch again two cycles later; one side never sensed it. The side
    that did releases the link and offers again; the other, still established, hears its link
    released (or the new OFFER) and starts over."""
    world = World(seed)
    world.add("a")
    world.add("b")
    dock = world.dock("a", 1, "b", 2, at=2)
    world.run_until(world.settled, limit=20)
    old = world.link_id(dock)
    at = world.step_no + 3
    saw = dock.b if missed_by == 0 else dock.a
    world._at(at, lambda: setattr(dock, "made", False))
    world._sense(saw, False, at)
    world._at(at + 2, lambda: setattr(dock, "made", True))
    world._sense(saw, True, at + 2)
    world.run_until(lambda: world.settled(), limit=40)
    assert world.link_id(dock) != old
    missed = dock.other(saw)
    assert len(world.nodes[missed[0]].detaches(missed[1])) == 1
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("who", ["leader", "follower"])
@pytest.mark.parametrize("down", [0, 5, 300])
@pytest.mark.parametrize("late", LATENESS)
def test_a_module_killed_and_restarted_rejoins(seed: int, who: str, down: int, late: dict[str, Any]) -> None:
    """The module's process dies (no release) and a fresh one starts ``down`` steps later with
    the contact still made: it rejoins with a fresh id, the neighbour dropped the old one. A
    bystander pair on the same bus is never disturbed."""
    world = World(seed, link_ids=SMALL_POOL, **late)
    world.add("a")
    world.add("b")
    dock = world.dock("a", 2, "b", 1, at=2)
    bystanders = pairs(world, 1, at=lambda i: 4)
    world.run_until(world.settled, limit=20)
    old = world.link_id(dock)
    leader = leader_end(world, dock)
    victim = leader if who == "leader" else dock.other(leader)
    neighbour = dock.other(victim)
    killed = world.step_no
    world.kill(victim[0])
    world.run(down)
    if down * DT > 3.5 + 2 * DT and who == "leader":  # the follower gave up on its silent leader
        (gave_up,) = world.nodes[neighbour[0]].detaches(neighbour[1])
        assert killed < gave_up <= killed + round(3.5 / DT) + 2
        assert world.sent(BusOp.RELEASE, old)
    world.restart(victim[0])
    world.run_until(world.settled, limit=40)  # a restarted leader knows nothing: it may be REJECTed
    assert world.link_id(dock) != old
    assert len(world.nodes[neighbour[0]].detaches(neighbour[1])) == 1
    assert len(world.nodes[bystanders[0].a[0]].history) == 1
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
def test_the_hub_of_a_branching_robot_restarts(seed: int) -> None:
    world = World(seed, link_ids=(1, 10))  # 4 released, 1 in use: the hub must avoid 5 of 10
    docks = branching(world, at=timing("random", seed))
    world.run_until(world.settled, limit=80)
    old = {d: world.link_id(d) for d in docks}
    world.kill("hub")
    world.run(7)
    world.restart("hub")
    world.run_until(world.settled, limit=30)
    for d in docks:
        assert (world.link_id(d) != old[d]) == ("hub" in (d.a[0], d.b[0]))
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
def test_a_follower_lets_go_of_a_dead_leader_before_the_id_ages_out(seed: int) -> None:
    world = World(seed)
    world.add("a")
    world.add("b")
    dock = world.dock("a", 2, "b", 1, at=2)
    pairs(world, 1, at=lambda i: 2)
    world.run_until(world.settled, limit=20)
    old = world.link_id(dock)
    leader = leader_end(world, dock)
    follower = dock.other(leader)
    world.kill(leader[0])
    dead = world.step_no
    world.run(round(3.5 / DT) + 2)
    assert world.nodes[follower[0]].detaches(follower[1]), "the follower still holds the id"
    assert world.nodes[follower[0]].neg.state(follower[1]) is LinkState.OFFERING
    bystander = world.nodes["p0a"].neg
    assert old not in bystander.ids_in_use and old in bystander.ids_quarantined
    assert world.sent(BusOp.RELEASE, old, since=dead)[0][1] == follower[0]


@pytest.mark.parametrize("seed", SEEDS)
def test_shutdown_releases_every_link(seed: int) -> None:
    world = World(seed)
    docks = branching(world)
    world.run_until(world.settled, limit=40)
    hub = world.nodes["hub"]
    world._apply(hub, hub.neg.shutdown())
    world.kill("hub")
    assert len(world.sent(BusOp.RELEASE)) == 4
    world.run(3)
    for d in docks[:4]:  # the hub's four links: the far ends heard them released
        end = d.b if d.a[0] == "hub" else d.a
        assert world.nodes[end[0]].neg.state(end[1]) is LinkState.OFFERING
        assert end[1] not in world.nodes[end[0]].attached
    assert world.link_id(docks[4]) is not None  # back-tail never involved


def test_ids_nobody_announces_age_out() -> None:
    neg = LinkNegotiator([1], random.Random(0))
    neg.tick(0.0)
    neg.bus_received(encode_bus(BusMessage(BusOp.CLAIM, 99, 5)))
    neg.bus_received(encode_bus(BusMessage(BusOp.RELEASE, 98, 5)))
    assert neg.ids_in_use == {99} and neg.ids_quarantined == {98}
    neg.tick(4.9)
    assert neg.ids_in_use == {99}
    neg.tick(5.1)
    assert neg.ids_in_use == frozenset() and neg.ids_quarantined == {98}
    neg.tick(10.1)
    assert neg.ids_quarantined == frozenset()


# ---------------------------------------------------------------------------------------------
# A lossy, garbling channel and garbage


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize(("loss", "garble"), [(0.3, 0.0), (0.0, 0.2), (0.3, 0.1)])
@pytest.mark.parametrize("late", LATENESS)
def test_a_lossy_garbling_channel_still_converges(seed: int, loss: float, garble: float, late: dict[str, Any]) -> None:
    world = World(seed, loss=loss, garble=garble, **late)
    docks = snake(world, 8, at=timing("random", seed))
    world.run_until(world.settled, limit=600)
    settled = world.step_no
    world.run(2 * REANNOUNCE_STEPS)
    assert world.all_linked()
    assert all(not n.detaches(since=settled) for n in world.nodes.values())
    assert len({world.link_id(d) for d in docks}) == 7
    totals = world.counters()
    if loss:
        assert totals.retries > 0
    if garble:
        assert totals.garbage + totals.stale > 0
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
def test_garbage_is_counted_and_ignored(seed: int) -> None:
    """Random bytes on the bus and on every CLC, in every phase of a negotiation: counted as
    garbage (or stale, for well-formed messages under no tag of ours), never raised, and the
    links come out as without them."""
    rng = random.Random(f"garbage/{seed}")
    world = World(seed)
    docks = snake(world, 4, at=timing("random", seed))
    undecodable = 0
    while not world.all_linked() or world.step_no < 60:
        for node in world.nodes.values():
            for c in (1, 2, 3, 4):
                data = rng.randbytes(rng.choice([0, 3, 7, 8, 8, 8, 9]))
                undecodable += _undecodable(decode_local, data)
                world._apply(node, node.neg.local_received(c, data))
            data = rng.randbytes(rng.choice([0, 8, 8, 12]))
            undecodable += _undecodable(decode_bus, data)
            world._apply(node, node.neg.bus_received(data))
        world.step()
        assert world.step_no < 200
    assert world.counters().garbage == undecodable > 0
    assert len({world.link_id(d) for d in docks}) == 3
    assert not world.violations


def _undecodable(decode: Callable[[bytes], object], data: bytes) -> int:
    try:
        decode(data)
    except DecodeError:
        return 1
    return 0


def test_messages_from_another_negotiation_are_stale() -> None:
    world = World(0)
    world.add("a")
    world.add("b")
    dock = world.dock("a", 1, "b", 1, at=1)
    world.run_until(world.settled, limit=20)
    link_id = world.link_id(dock)
    assert link_id is not None
    for kind in (LocalType.PROPOSE, LocalType.ACCEPT, LocalType.CONFIRM, LocalType.REJECT):
        for node in world.nodes.values():
            assert node.neg.local_received(1, encode_sealed(kind, link_id ^ 1, 0x5EA1)) == []
    world.run(5)
    assert world.counters().stale == 8 and world.link_id(dock) == link_id
