"""The simulated robot tests/dh2rt/test_negotiation.py runs link negotiation
(:mod:`dh2rt.negotiation`) in: many negotiators, one bus.

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

The robots (:func:`pairs`, :func:`snake`, :func:`branching`) dock on a :func:`timing`.
"""

from __future__ import annotations

import random
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from dh2rt.negotiation import Action, Attach, Detach, LinkNegotiator, NegotiationCounters, SendBus, SendLocal
from dh2rt.transport.base import BusEnd
from dh2rt.wire.negotiation import BusMessage, BusOp, decode_bus

DT = 0.02  # 50 Hz cycles

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
        self.at(at, lambda: setattr(dock, "made", True))
        self.sense(dock.a, True, at)
        self.sense(dock.b, True, at + skew)

    def undock(self, dock: Dock, *, at: int, skew: int = 0, sensed: tuple[bool, bool] = (True, True)) -> None:
        """The connectors part at step ``at``; each side senses it (if ``sensed``) then or
        ``skew`` steps later."""
        self.at(at, lambda: setattr(dock, "made", False))
        if sensed[0]:
            self.sense(dock.a, False, at)
        if sensed[1]:
            self.sense(dock.b, False, at + skew)

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

    def at(self, step: int, change: Callable[[], None]) -> None:
        """Make ``change`` at the start of ``step`` (now, if that step has begun or passed)."""
        if step <= self.step_no:
            change()
        else:
            self._due[step].append(change)

    def sense(self, end: tuple[str, int], made: bool, step: int) -> None:
        """Connector ``end`` senses the contact ``made`` (or broken) at ``step``, whatever the
        dock is (:meth:`at` changes the dock: the two together make a bounce one side missed)."""

        def deliver() -> None:
            self._mail[self.step_no][end[0]].append(ContactIn(end[1], made))

        self.at(step, deliver)  # queued before the step's mail is taken: read in that step

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
                self.apply(node, self._feed(node, item))
            self.apply(node, node.neg.tick(self.now))
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

    def apply(self, node: Node, actions: Iterable[Action]) -> None:
        """Carry out ``node``'s actions: CLC messages and bus frames are posted, attaches and
        detaches change its attachment table (refusing a double attach or a free detach)."""
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
