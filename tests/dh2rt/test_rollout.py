"""The rollout (dh2rt.rollout) in a simulated robot: a signed image spreading over the
modules' own links, staged, committed and switched to together.

The harness is an in-process, event-driven world with a continuous clock. Each module is a
:class:`~dh2rt.rollout.Rollout` with a fake flash that checks images with the real
:mod:`dh2rt.signed_image` and real Ed25519 keys; the entry point is a
:class:`~dh2rt.rollout.Flasher` on a cable to a module's free connector. Modules tick every
``PERIOD`` at phases of their own (or all in step: ``aligned``), and each keeps its own
clock (a random offset): nothing compares clocks across modules. Every cycle a module ticks
its Rollout (a switch takes effect at once), sends one link frame through each linked
connector (a Hello when one is due, else a 4-byte hormone or keep-alive), then the transfer
frames the tick let out. Transfer frames reach the Rollout when they arrive (``prompt``) or
at its next tick (``cycle``: a host that reads its links once a cycle).

Media: a serial link per docked pair (115,200 baud, 11,520 bytes/s each way; every frame
costs its COBS + CRC-32 bytes, serialized one after another with optional latency, jitter and
loss), or one 1 Mbit/s CAN bus (frames cut into classic CAN frames of worst-case stuffed
length; arbitration by priority among the nodes' pending frames: hormones first, then control
frames, then segments; a node finishes one payload before its next, as the reassembler
needs). Links can be dropped and re-docked; modules killed and restarted (their Rollout
replaced, their persisted partial image and flash kept, their clock changed). A module's
liveness is simulated far enough for the Hello: it sends one when a link comes up, after a
switch, every cycle to a neighbour it has not verified (no Hello heard, or one stating a
program it refuses: neither its own nor tolerated), and in answer to a Hello when its own
last one is three cycles old; it tells the Rollout a link is down three cycles after it went
silent, and forgets the peer.
"""

from __future__ import annotations

import heapq
import itertools
import math
import random
import statistics
import sys
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest

from dh2rt import signed_image as si
from dh2rt.compiler import compile_source
from dh2rt.rollout import (
    COMMITTED,
    LARGEST_CONTROL,
    Action,
    DropPartial,
    Flasher,
    FlasherPhase,
    ImageInfo,
    Pacing,
    Partial,
    Persist,
    Program,
    Role,
    Rollout,
    Send,
    SenderState,
    Stage,
    Switch,
    Timing,
    _Sender,
    _Store,
    describe_path,
)
from dh2rt.topology import Topology, parse_spec
from dh2rt.wire import transfer as tw
from dh2rt.wire.can_frames import CLASSIC_DATA
from dh2rt.wire.transfer import Outcome

PERIOD = 0.02  # 50 Hz cycles
SILENCE = 3  # cycles of silence before liveness reports a link down
TRIAL = 10  # clean cycles before a switched program is confirmed
LINK_FRAME = 4  # bytes of a hormone or keep-alive frame
CABLE = 1  # the flasher's connector


# ---------------------------------------------------------------------------------------------
# Images and keys


@dataclass(frozen=True)
class Images:
    key: bytes
    trust: list[bytes]
    v1: bytes  # the caterpillar, ClockCycle 40
    v2: bytes  # the caterpillar, ClockCycle 20: the new program
    v3: bytes
    other_key: bytes  # v2's program signed by a key nobody trusts
    tampered: bytes  # v2 with a byte of its body flipped


def _caterpillar(clock_cycle: int, source: str) -> bytes:
    text = source.replace("const ClockCycle = 40", f"const ClockCycle = {clock_cycle}")
    return compile_source(text, "caterpillar.dh2").image


@pytest.fixture(scope="module")
def images(examples: Any) -> Images:
    source = (examples / "caterpillar.dh2").read_text()
    key, stranger = si.new_private_key(), si.new_private_key()
    v2 = si.pack(_caterpillar(20, source), 2, key)
    body = bytearray(v2)
    body[40] ^= 0x01
    return Images(
        key,
        [si.public_key(key)],
        si.pack(_caterpillar(40, source), 1, key),
        v2,
        si.pack(_caterpillar(10, source), 3, key),
        si.pack(_caterpillar(20, source), 2, stranger),
        bytes(body),
    )


# ---------------------------------------------------------------------------------------------
# Media


@dataclass(frozen=True)
class Medium:
    name: str
    rate: float  # link units per second: serial bytes, CAN bits
    cost: Callable[[int], int]  # units of a frame of n bytes
    budget: int  # transfer units per cycle: per connector, or per module on a shared bus
    segment_size: int
    shared: bool
    throughput: float  # payload bytes per second one hop carries at best (the limits' rate)

    @property
    def pacing(self) -> Pacing:
        return Pacing(self.budget, self.cost, self.shared)

    def seconds(self, payload: int) -> float:
        return self.cost(payload) / self.rate


#: 230 bytes per 20 ms cycle each way; 80 % to the rollout, the rest for the hormones.
SERIAL = Medium("serial 115,200 baud", 11_520.0, tw.serial_cost, 184, 80, False, 11_520.0)
#: 20,000 bits per cycle on the whole bus; a module may put 30 % of them on it.
CAN = Medium("CAN 1 Mbit/s", 1_000_000.0, tw.can_cost, 6_000, 56, True, 1_000_000.0 * CLASSIC_DATA / 160)
MEDIA = {"serial": SERIAL, "can": CAN}


# ---------------------------------------------------------------------------------------------
# The fake flash


class FakeFlash:
    """A module's A/B flash in memory: what ``drivers.flash_slots.Flash`` decides, with the
    real signature checks (trust store, rollback below the confirmed version)."""

    def __init__(self, trust: list[bytes], confirmed: bytes) -> None:
        self.trust = trust
        self.confirmed = confirmed
        self.pending: bytes | None = None  # staged, not switched to
        self.trial: bytes | None = None  # switched to, not yet confirmed

    def stage(self, data: bytes) -> tuple[bool, str, str]:
        exam = si.examine(data, self.trust)
        if exam.verdict is not si.Verdict.OK or exam.image is None:
            return False, str(exam.verdict), exam.reason
        confirmed = si.parse(self.confirmed).version
        if exam.image.version < confirmed:
            return False, "rollback", f"version {exam.image.version} is lower than the confirmed {confirmed}"
        self.pending = data
        return True, "ok", exam.reason


# ---------------------------------------------------------------------------------------------
# The world


@dataclass
class Frame:
    payload: bytes
    link: bool  # a link frame (hormone, keep-alive, Hello), not a transfer frame
    sent_at: float
    src: tuple[int, int]  # (node, connector) it left through


class Wire:
    """One direction of a serial link: frames one after another at the line rate."""

    def __init__(self, world: World, src: tuple[int, int], dst: tuple[int, int]) -> None:
        self.world = world
        self.src = src
        self.dst = dst
        self.busy_until = 0.0
        self.last_arrival = 0.0

    def send(self, frame: Frame) -> None:
        w = self.world
        start = max(w.t, self.busy_until)
        self.busy_until = start + w.medium.seconds(len(frame.payload))
        if w.rng.random() < w.loss:
            w.lost += not frame.link
            return
        arrival = max(self.busy_until + w.latency + w.rng.uniform(0, w.jitter), self.last_arrival)
        self.last_arrival = arrival
        w.schedule(arrival, lambda: w.arrive(self.dst, frame))


@dataclass(order=True)
class _Queued:
    priority: int
    seq: int
    frame: Frame = field(compare=False)
    dst: tuple[int, int] = field(compare=False)
    pieces: list[int] = field(compare=False)  # bits of each classic CAN frame still to send


class Bus:
    """A CAN bus. Each node queues payloads by priority (link frames, then control frames,
    then segments: what the CAN transport should do); the segments of one payload are never
    interleaved with another payload of the same kind on the same link end, but payloads of
    other kinds may go between them (a reassembler per link end and kind, which
    ``dh2rt.wire.can_frames.Reassembler`` needs for this: today it keys on the link end
    alone). The bus arbitrates frame by frame among the nodes' best frames (lowest priority
    value, then lowest node)."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.queues: dict[int, list[_Queued]] = defaultdict(list)
        self.started: dict[tuple[int, int, int], _Queued] = {}  # (node, connector, kind) -> payload under way
        self.busy = False
        self.seq = itertools.count()

    def send(self, frame: Frame, dst: tuple[int, int]) -> None:
        payload = frame.payload
        priority = 0 if frame.link else (payload[0] >> 4) & 3
        full, rest = divmod(len(payload), 8)
        pieces = [tw.can_frame_bits(8)] * full + ([tw.can_frame_bits(rest)] if rest else [])
        heapq.heappush(self.queues[frame.src[0]], _Queued(priority, next(self.seq), frame, dst, pieces))
        self._next()

    def _best(self, node: int) -> _Queued | None:
        """The payload whose next frame the node offers: the most urgent one under way or
        waiting whose link end has no other payload under way."""
        under_way = [q for (n, _, _), q in self.started.items() if n == node]
        waiting = [q for q in self.queues[node] if (node, q.frame.src[1], q.priority) not in self.started]
        candidates = under_way + waiting
        return min(candidates) if candidates else None

    def _next(self) -> None:
        if self.busy:
            return
        offers = [(best.priority, node, best) for node in list(self.queues) if (best := self._best(node))]
        if not offers:
            return
        _, node, best = min(offers, key=lambda o: (o[0], o[1]))
        end = (node, best.frame.src[1], best.priority)
        if end not in self.started:
            self.queues[node].remove(best)
            heapq.heapify(self.queues[node])
            self.started[end] = best
        bits = best.pieces.pop(0)
        self.busy = True
        self.world.schedule(self.world.t + bits / self.world.medium.rate, lambda: self._done(end))

    def _done(self, end: tuple[int, int, int]) -> None:
        self.busy = False
        head = self.started[end]
        if not head.pieces:
            del self.started[end]
            w = self.world
            if w.rng.random() >= w.loss:
                w.schedule(w.t + w.latency, lambda: w.arrive(head.dst, head.frame))
            else:
                w.lost += not head.frame.link
        self._next()


class Node:
    """A module or the entry point: a state machine, a clock, a cycle schedule."""

    def __init__(self, world: World, index: int, phase: float) -> None:
        self.world = world
        self.index = index
        self.phase = phase
        self.offset = world.rng.uniform(-1e4, 1e4)  # this node's clock: unrelated to any other
        self.alive = True
        self.machine: Rollout | Flasher
        self.buffer: list[tuple[float, int, Frame]] = []
        self.units: Counter[tuple[int, int]] = Counter()  # (cycle, connector or 0) -> units sent
        self.generation = 0

    def local(self, t: float) -> float:
        return t + self.offset

    def next_tick(self, t: float) -> float:
        """The first tick at or after ``t``."""
        return self.phase + math.ceil((t - self.phase) / PERIOD - 1e-9) * PERIOD

    def run(self, actions: Iterable[Action]) -> None:
        for action in actions:
            self.carry_out(action)

    def carry_out(self, action: Action) -> None:
        assert isinstance(action, Send), action
        key = 0 if self.world.medium.shared else action.connector
        self.units[(self.machine.tick_count, key)] += self.world.medium.cost(len(action.data))
        self.world.transmit(self, action.connector, action.data, link=False)

    def tick(self) -> None:
        """A cycle: the state machine's tick (a switch takes effect at once), the link
        frames (hormones, beacons: the new program's Hello after a switch), then the
        transfer frames the tick let out."""
        w = self.world
        actions = self.machine.tick(self.local(w.t))
        self.run(a for a in actions if not isinstance(a, Send))
        self.send_link_frames()
        self.run(a for a in actions if isinstance(a, Send))
        if not w.prompt:
            buffered, self.buffer = self.buffer, []
            for at, connector, frame in buffered:
                self.take(at, connector, frame)

    def send_link_frames(self) -> None:
        pass

    def forget(self, connector: int) -> None:
        """Liveness found the link on ``connector`` silent: its peer must announce itself again."""

    def take(self, at: float, connector: int, frame: Frame) -> None:
        """A frame arrived at ``at`` through ``connector``."""
        if frame.link:
            self.take_link_frame(at, connector, frame)
        else:
            self.run(self.machine.receive(connector, frame.payload, self.local(at)))

    def take_link_frame(self, at: float, connector: int, frame: Frame) -> None:
        if len(frame.payload) > LINK_FRAME:
            hello = tw.decode_hello(frame.payload)
            self.run(self.machine.hello(connector, hello.sender, hello.version, hello.digest, self.local(at)))


class Module(Node):
    def __init__(self, world: World, index: int, phase: float, running: bytes, trust: list[bytes]) -> None:
        super().__init__(world, index, phase)
        self.flash = FakeFlash(trust, running)
        self.running = running
        self.partial: tuple[ImageInfo, bytearray] | None = None
        self.hello_due: set[int] = set()
        self.peers: dict[int, bytes] = {}  # connector -> the digest its last Hello stated
        self.hello_sent: dict[int, int] = {}  # connector -> tick a Hello last went out
        self.trial_left = 0
        self.switched_at: float | None = None
        self.switched_cycle: int | None = None
        self.staged_at: float | None = None
        self.refusals: list[tuple[float, int]] = []  # (time, connector) of Hellos refused
        self.faulty = False  # its trial faults (the host reverts it) instead of running clean
        self.stages = 0
        self.machine = self.boot()

    @property
    def program(self) -> Program:
        return Program.from_image(self.running)

    def boot(self) -> Rollout:
        partial = None if self.partial is None else Partial(self.partial[0], bytes(self.partial[1]))
        w = self.world
        return Rollout(
            range(1, w.topology.profile.connector_count + 1),
            self.program,
            pacing=w.pacing,
            timing=w.timing,
            segment_size=w.medium.segment_size,
            partial=partial,
            staged=self.flash.pending,
            latency=w.commit_latency,
            cut_through=w.cut_through,
        )

    def carry_out(self, action: Action) -> None:
        assert isinstance(self.machine, Rollout)
        match action:
            case Send():
                super().carry_out(action)
            case Persist(info, offset, data):
                if offset == 0:
                    self.partial = (info, bytearray())
                assert self.partial is not None and self.partial[0] == info and len(self.partial[1]) == offset
                self.partial[1].extend(data)
            case DropPartial():
                self.partial = None
            case Stage(_, data):
                self.stages += 1
                accepted, verdict, reason = self.flash.stage(data)
                if accepted:
                    self.staged_at = self.world.t
                self.run(self.machine.staged(accepted, verdict, reason, self.local(self.world.t)))
            case Switch(program):
                assert self.flash.pending is not None and Program.from_image(self.flash.pending) == program
                self.flash.trial, self.flash.pending = self.flash.pending, None
                self.running = self.flash.trial
                self.switched_at = self.world.t
                self.switched_cycle = round((self.world.t - self.phase) / PERIOD)
                self.trial_left = TRIAL
                self.hello_due = set(self.world.connectors(self.index))

    def tick(self) -> None:
        super().tick()
        if self.trial_left and self.flash.trial is not None:
            self.trial_left -= 1
            assert isinstance(self.machine, Rollout)
            if self.faulty:  # Flash.reject: the confirmed program runs again, announced
                self.flash.trial, self.trial_left = None, 0
                self.running = self.flash.confirmed
                self.hello_due = set(self.world.connectors(self.index))
                self.run(self.machine.reverted("receptor r faulted on trial", self.local(self.world.t)))
            elif not self.trial_left:
                self.flash.confirmed, self.flash.trial = self.flash.trial, None
                self.run(self.machine.confirmed(self.local(self.world.t)))

    def send_link_frames(self) -> None:
        program = self.program
        assert isinstance(self.machine, Rollout)
        tolerated = self.machine.tolerated() | {program.digest}
        for connector in self.world.connectors(self.index):
            unverified = connector not in self.peers or self.peers[connector] not in tolerated
            if connector in self.hello_due or unverified:
                self.hello_due.discard(connector)
                self.hello_sent[connector] = self.machine.tick_count
                payload = tw.encode_hello(connector, program.digest, program.version)
            else:
                payload = bytes((0x40 | connector, 0, 0, 0))  # a hormone X(A) sent through it
            self.world.transmit(self, connector, payload, link=True)

    def forget(self, connector: int) -> None:
        self.peers.pop(connector, None)

    def take_link_frame(self, at: float, connector: int, frame: Frame) -> None:
        if len(frame.payload) > LINK_FRAME:
            digest = tw.decode_hello(frame.payload).digest
            self.peers[connector] = digest
            assert isinstance(self.machine, Rollout)
            if digest != self.program.digest and digest not in self.machine.tolerated():
                self.refusals.append((self.world.t, connector))
            if self.machine.tick_count - self.hello_sent.get(connector, -SILENCE) >= SILENCE:
                self.hello_due.add(connector)  # the peer may not have heard ours: answer
        super().take_link_frame(at, connector, frame)

    def kill(self) -> None:
        self.alive = False
        self.generation += 1
        self.buffer = []
        self.world.silence(self.index)

    def restart(self) -> None:
        """Boot again: the confirmed program (a trial booted before is reverted), the staged
        image and the partial one kept, a new clock, every link announced."""
        if self.flash.trial is not None:
            self.flash.trial = None
        self.running = self.flash.confirmed
        self.offset = self.world.rng.uniform(-1e4, 1e4)
        self.machine = self.boot()
        self.alive = True
        self.peers = {}
        self.hello_sent = {}
        self.hello_due = set(self.world.connectors(self.index))
        for connector in self.hello_due:
            self.run(self.machine.attach(connector, self.local(self.world.t)))
        self.world.announce(self.index)


class Entry(Node):
    def __init__(
        self, world: World, index: int, phase: float, image: bytes, settle_ticks: int, *, confirm: bool = False
    ) -> None:
        super().__init__(world, index, phase)
        self.machine = Flasher(
            image,
            pacing=world.pacing,
            period=PERIOD,
            connector=CABLE,
            timing=world.timing,
            segment_size=world.medium.segment_size,
            settle_ticks=settle_ticks,
            confirm=confirm,
        )
        self.done_at: float | None = None

    def tick(self) -> None:
        super().tick()
        assert isinstance(self.machine, Flasher)
        if self.machine.done and self.done_at is None:
            self.done_at = self.world.t


LinkKey = tuple[tuple[int, int], tuple[int, int]]


class World:
    """A robot: modules on a topology, the entry point on a cable, one medium."""

    def __init__(
        self,
        spec: str | Topology,
        medium: Medium,
        images: Images,
        *,
        seed: int,
        image: bytes | None = None,
        running: bytes | None = None,
        running_at: dict[int, bytes] | None = None,
        trust_at: dict[int, list[bytes]] | None = None,
        prompt: bool = True,
        aligned: bool = False,
        loss: float = 0.0,
        latency: float = 0.0,
        jitter: float = 0.0,
        cut_through: bool = True,
        pacing: Pacing | None = None,
        timing: Timing | None = None,
        entry: tuple[int, int] = (0, 1),
        undocked: Iterable[int] = (),
        settle_ticks: int = 250,
        confirm: bool = False,
        faulty: Iterable[int] = (),
    ) -> None:
        self.topology = parse_spec(spec) if isinstance(spec, str) else spec
        self.medium = medium
        self.rng = random.Random(seed)
        self.t = 0.0
        self.prompt = prompt
        self.loss, self.latency, self.jitter = loss, latency, jitter
        self.cut_through = cut_through
        #: What a host would configure as a COMMIT's transit time: the frame at the line's
        #: rate, the link's mean latency, and (a host that sends at its cycle start) the
        #: cycle's link frame ahead of it on a serial line.
        self.commit_latency = medium.seconds(15) + latency + jitter / 2
        if not prompt and not medium.shared:
            self.commit_latency += medium.seconds(LINK_FRAME)
        self.pacing = pacing or medium.pacing
        self.timing = timing or Timing()
        self.events: list[tuple[float, int, Callable[[], None]]] = []
        self.seq = itertools.count()
        self.hormone_delays: list[tuple[float, float]] = []  # (sent at, delay beyond an idle link)
        self.lost = 0  # transfer frames the medium lost
        self._peer: dict[tuple[int, int], tuple[int, int]] = {}
        self._up: dict[LinkKey, bool] = {}
        self._wires: dict[tuple[int, int], Wire] = {}
        self.bus = Bus(self)
        n = self.topology.size
        self.entry_index = n
        for link in self.topology.links:
            self._join((link.a, link.a_conn), (link.b, link.b_conn), up=not {link.a, link.b} & set(undocked))
        if image is not None:
            self._join((n, CABLE), entry, up=True)
        base = self.rng.uniform(0, PERIOD)
        phases = [base if aligned else self.rng.uniform(0, PERIOD) for _ in range(n)]
        self.modules = [
            Module(
                self,
                i,
                phases[i],
                (running_at or {}).get(i, running or images.v1),
                (trust_at or {}).get(i, images.trust),
            )
            for i in range(n)
        ]
        for i in faulty:
            self.modules[i].faulty = True
        for m in self.modules:
            m.hello_due = set(self.connectors(m.index))
            for connector in self.connectors(m.index):
                m.run(m.machine.attach(connector, m.local(0.0)))
            self._schedule_ticks(m)
        self.entry: Entry | None = None
        if image is not None:  # the entry point keeps time of its own, whatever the modules do
            self.entry = Entry(self, n, self.rng.uniform(PERIOD, 2 * PERIOD), image, settle_ticks, confirm=confirm)
            self._schedule_ticks(self.entry)

    # -- topology ------------------------------------------------------------------------------

    def _join(self, a: tuple[int, int], b: tuple[int, int], *, up: bool) -> None:
        self._peer[a], self._peer[b] = b, a
        self._up[self.link_key(a)] = up
        self._wires[a] = Wire(self, a, b)
        self._wires[b] = Wire(self, b, a)

    def link_key(self, end: tuple[int, int]) -> LinkKey:
        other = self._peer[end]
        return (end, other) if end < other else (other, end)

    def connectors(self, node: int) -> list[int]:
        return sorted(c for (n, c), _ in self._peer.items() if n == node and self.up((n, c)))

    def up(self, end: tuple[int, int]) -> bool:
        return self._up.get(self.link_key(end), False)

    def node(self, index: int) -> Node:
        return self.entry if index == self.entry_index and self.entry is not None else self.modules[index]

    # -- time ----------------------------------------------------------------------------------

    def schedule(self, at: float, fn: Callable[[], None]) -> None:
        heapq.heappush(self.events, (at, next(self.seq), fn))

    def _schedule_ticks(self, node: Node) -> None:
        generation = node.generation

        def tick() -> None:
            if not node.alive or node.generation != generation:
                return
            node.tick()
            self.schedule(self.t + PERIOD, tick)

        self.schedule(node.next_tick(self.t + 1e-9), tick)

    def run_until(self, t: float) -> None:
        while self.events and self.events[0][0] <= t:
            self.t, _, fn = heapq.heappop(self.events)
            fn()
        self.t = t

    def run(self, *, limit: float = 30.0, until: Callable[[], bool] | None = None) -> None:
        """Run until the entry point is done (or ``until`` holds), at most ``limit`` seconds."""
        stop = until or (lambda: self.entry is not None and self.entry.done_at is not None)
        while self.events and not stop():
            if self.events[0][0] > limit:
                raise AssertionError(f"not done after {limit} s: {self.summary()}")
            self.t, _, fn = heapq.heappop(self.events)
            fn()

    # -- frames --------------------------------------------------------------------------------

    def transmit(self, node: Node, connector: int, payload: bytes, *, link: bool) -> None:
        end = (node.index, connector)
        if end not in self._peer or not self.up(end):
            return
        frame = Frame(payload, link, self.t, end)
        if self.medium.shared:
            self.bus.send(frame, self._peer[end])
        else:
            self._wires[end].send(frame)

    def arrive(self, dst: tuple[int, int], frame: Frame) -> None:
        node = self.node(dst[0])
        if not node.alive or not self.up(dst):
            return
        if frame.link:
            idle = frame.sent_at + self.medium.seconds(len(frame.payload)) + self.latency
            self.hormone_delays.append((frame.sent_at, self.t - idle))
        if self.prompt or frame.link:
            node.take(self.t, dst[1], frame)
        else:
            node.buffer.append((self.t, dst[1], frame))

    # -- links and restarts --------------------------------------------------------------------

    def drop(self, end: tuple[int, int]) -> None:
        """Undock the link at ``end``: both ends hear nothing, and liveness says so later."""
        self._up[self.link_key(end)] = False
        for side in (end, self._peer[end]):
            self._later_down(side)

    def dock(self, end: tuple[int, int]) -> None:
        self._up[self.link_key(end)] = True
        for n, c in (end, self._peer[end]):
            node = self.node(n)
            if isinstance(node, Module) and node.alive:
                node.hello_due.add(c)
                node.run(node.machine.attach(c, node.local(self.t)))

    def _later_down(self, end: tuple[int, int]) -> None:
        node = self.node(end[0])
        generation = node.generation

        def down() -> None:
            if node.alive and node.generation == generation and not self.up(end):
                node.forget(end[1])
                node.run(node.machine.link_down(end[1], node.local(self.t)))

        self.schedule(self.t + SILENCE * PERIOD, down)

    def silence(self, index: int) -> None:
        """A module died: its neighbours find its links silent."""
        for (n, c), other in self._peer.items():
            if n == index and self.up((n, c)):
                node = self.node(other[0])
                generation = node.generation

                def down(node: Node = node, c: int = other[1], generation: int = generation) -> None:
                    if node.alive and node.generation == generation and not self.node(index).alive:
                        node.forget(c)
                        node.run(node.machine.link_down(c, node.local(self.t)))

                self.schedule(self.t + SILENCE * PERIOD, down)

    def announce(self, index: int) -> None:
        """A module (re)started: every neighbour owes it a Hello."""
        for (n, c), (m, d) in self._peer.items():
            if n == index and self.up((n, c)):
                node = self.node(m)
                if isinstance(node, Module):
                    node.hello_due.add(d)
        self._schedule_ticks(self.modules[index])

    # -- results -------------------------------------------------------------------------------

    @property
    def flasher(self) -> Flasher:
        assert self.entry is not None and isinstance(self.entry.machine, Flasher)
        return self.entry.machine

    def versions(self) -> list[int]:
        return [si.parse(m.running).version for m in self.modules]

    def summary(self) -> str:
        roles = [m.machine.role.value if isinstance(m.machine, Rollout) and m.machine.role else "-" for m in self]
        phase = self.flasher.phase.value if self.entry is not None else "-"
        return f"flasher {phase}; versions {self.versions()}; roles {roles}"

    def __iter__(self) -> Iterator[Module]:
        return iter(self.modules)

    def switch_spread(self) -> float:
        times = [m.switched_at for m in self if m.switched_at is not None]
        return max(times) - min(times)


def snake_path(k: int) -> tuple[tuple[int, int], ...]:
    """The name of module k of a snake whose module 0 has the cable on its front."""
    return ((CABLE, 1),) + ((2, 1),) * k


# ---------------------------------------------------------------------------------------------
# All modules stage, commit and switch together


SEEDS = range(3)
TOPOLOGIES = ["snake:8", "snake:20", "dragon"]


HOSTS = [
    pytest.param("serial", "prompt", id="serial-prompt"),
    pytest.param("serial", "cycle", id="serial-cycle"),
    pytest.param("can", "prompt", id="can-prompt"),
]


@pytest.mark.parametrize(("medium", "host"), HOSTS)
@pytest.mark.parametrize("spec", TOPOLOGIES)
@pytest.mark.parametrize("seed", SEEDS)
def test_every_module_stages_commits_and_switches_at_one_cycle(
    images: Images, medium: str, spec: str, host: str, seed: int
) -> None:
    """Modules whose cycles are in step (the entry point's are not) all switch at one
    cycle: hosts that handle transfer frames as they arrive, on either medium; on serial
    links, hosts that handle them at their cycle starts too (they know the link frames
    that go out ahead of a commit)."""
    world = World(spec, MEDIA[medium], images, seed=seed, image=images.v2, prompt=host == "prompt", aligned=True)
    world.run()
    flasher = world.flasher
    assert flasher.succeeded, world.summary()
    assert world.versions() == [2] * world.topology.size
    cycles = {m.switched_cycle for m in world}
    assert len(cycles) == 1, f"modules switched at cycles {sorted(Counter(m.switched_cycle for m in world).items())}"
    report = flasher.report()
    assert len(report) == world.topology.size
    assert {m.outcome for m in report} <= {Outcome.COMMITTED, Outcome.CONFIRMED}
    assert all(m.version == 2 for m in report)
    assert not any(m.refusals for m in world), "a neighbour was refused during the rollout"


def _neighbours_within_a_period(world: World) -> None:
    for link in world.topology.links:
        a, b = world.modules[link.a].switched_at, world.modules[link.b].switched_at
        assert a is not None and b is not None and abs(a - b) < PERIOD * 1.05, (link, a, b)


@pytest.mark.parametrize("spec", TOPOLOGIES)
@pytest.mark.parametrize("seed", SEEDS)
def test_hosts_that_read_a_bus_once_a_cycle(images: Images, spec: str, seed: int) -> None:
    """A host that hands transfer frames over only at its cycle start sends a commit on at
    the next cycle start, behind that cycle's burst of hormones on the bus, which no host
    can foresee: each hop adds up to a burst's length of error. Every module still commits,
    each within one period of its neighbours, and none refuses another: the spread over the
    whole robot grows with its depth (hence: hand transfer frames over as they arrive)."""
    world = World(spec, CAN, images, seed=seed, image=images.v2, prompt=False, aligned=True)
    world.run()
    assert world.flasher.succeeded, world.summary()
    _neighbours_within_a_period(world)
    assert not any(m.refusals for m in world)


@pytest.mark.parametrize("medium", ["serial", "can"])
@pytest.mark.parametrize("seed", range(6))
def test_unsynchronised_modules_switch_within_one_period(images: Images, medium: str, seed: int) -> None:
    """Cycles at random phases, clocks at random offsets: every module starts the new program
    at its first cycle at or after the agreed instant, so all within one period."""
    world = World("dragon", MEDIA[medium], images, seed=seed, image=images.v2, jitter=0.001)
    world.run()
    assert world.flasher.succeeded, world.summary()
    assert world.switch_spread() < PERIOD * 1.05
    _neighbours_within_a_period(world)
    assert not any(m.refusals for m in world)


def test_names_are_paths_from_the_entry_point(images: Images) -> None:
    world = World("snake:8", SERIAL, images, seed=1, image=images.v2)
    world.run()
    assert [m.path for m in world.flasher.report()] == [snake_path(k) for k in range(8)]
    assert describe_path(snake_path(2)) == "1>1 2>1 2>1"
    names = {1: "front", 2: "back"}
    assert world.flasher.report()[2].describe(names.__getitem__) == (
        "front>front back>front back>front: committed, runs version 2"
    )
    for k, m in enumerate(world):
        assert isinstance(m.machine, Rollout) and m.machine.name == snake_path(k)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("host", ["prompt", "cycle"])
def test_lossy_late_links(images: Images, seed: int, host: str) -> None:
    """5 % of frames lost, 2 ms latency and up to 3 ms of jitter: retransmissions and
    repeated commits still bring every module to the new program at one cycle."""
    world = World(
        "snake:8",
        SERIAL,
        images,
        seed=seed,
        image=images.v2,
        prompt=host == "prompt",
        aligned=True,
        loss=0.05,
        latency=0.002,
        jitter=0.003,
    )
    world.run()
    assert world.flasher.succeeded, world.summary()
    assert len({m.switched_cycle for m in world}) == 1
    assert world.lost > 0


def test_a_robot_running_the_image_already_reports_current(images: Images) -> None:
    world = World("snake:8", SERIAL, images, seed=2, image=images.v2, running=images.v2)
    world.run()
    assert world.flasher.succeeded
    assert {m.outcome for m in world.flasher.report()} == {Outcome.CURRENT}
    assert all(m.switched_at is None for m in world)


# ---------------------------------------------------------------------------------------------
# Restarts and link drops


def _when_receiving(world: World, index: int, fraction: float) -> Callable[[], bool]:
    def check() -> bool:
        m = world.modules[index]
        assert isinstance(m.machine, Rollout)
        return m.machine.role is Role.RECEIVING and m.machine.received >= fraction * world.flasher.info.length

    return check


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("medium", ["serial", "can"])
def test_a_module_killed_mid_staging_resumes_and_commits_with_the_others(
    images: Images, seed: int, medium: str
) -> None:
    """Module 4 dies with part of the image; it boots its old program 5 cycles later, takes
    up the transfer where its persisted bytes end, and switches with everyone else."""
    world = World("snake:8", MEDIA[medium], images, seed=seed, image=images.v2, aligned=True)
    world.run(until=_when_receiving(world, 4, 0.3))
    victim = world.modules[4]
    held = victim.partial
    assert held is not None and 0 < len(held[1]) < len(images.v2)
    victim.kill()
    world.run_until(world.t + 5 * PERIOD)
    victim.restart()
    assert world.versions()[4] == 1  # it boots its old program
    restarted = victim.machine
    assert isinstance(restarted, Rollout) and restarted.received == len(held[1])
    world.run()
    assert world.flasher.succeeded, world.summary()
    assert world.versions() == [2] * 8
    assert len({m.switched_cycle for m in world}) == 1
    assert restarted.received == len(images.v2)


@pytest.mark.parametrize("seed", range(3))
def test_a_module_dead_past_the_commit_catches_up_from_its_neighbours(images: Images, seed: int) -> None:
    """Module 4 stays dead long enough to be reported silent; the others commit without it.
    When it comes back it finishes the image from its neighbours (which now run it), switches
    at once, and passes it on to the modules behind it; the report, still open, names it
    committed. Had it stayed away, the report would name it silent, by its path."""
    world = World("snake:8", SERIAL, images, seed=seed, image=images.v2, settle_ticks=400)
    world.run(until=_when_receiving(world, 4, 0.3))
    victim = world.modules[4]
    victim.kill()
    world.run(until=lambda: world.flasher.phase is FlasherPhase.SETTLING)
    world.run_until(world.t + 3 * PERIOD)  # past every module's switch
    silent = {m.path: m.outcome for m in world.flasher.report()}
    assert silent[snake_path(4)] is Outcome.SILENT
    assert world.versions()[:4] == [2] * 4 and world.versions()[4:] == [1] * 4
    victim.restart()
    world.run()
    assert world.versions() == [2] * 8, world.summary()
    assert world.flasher.succeeded
    assert {m.path for m in world.flasher.report()} == {snake_path(k) for k in range(8)}
    first = world.modules[0].switched_at
    assert first is not None
    assert all(m.switched_at is not None and m.switched_at > first for m in world.modules[4:])


def test_a_module_that_never_returns_is_named_in_the_report(images: Images) -> None:
    world = World("snake:8", SERIAL, images, seed=4, image=images.v2, settle_ticks=60)
    world.run(until=_when_receiving(world, 4, 0.3))
    world.modules[4].kill()
    world.run()
    flasher = world.flasher
    assert flasher.done and not flasher.succeeded
    failed = [m for m in flasher.report() if not m.committed]
    assert [(m.path, m.outcome) for m in failed] == [(snake_path(4), Outcome.SILENT)]
    assert describe_path(failed[0].path) == "1>1 2>1 2>1 2>1 2>1"


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("cycles", [4, 40])
@pytest.mark.parametrize("medium", ["serial", "can"])
def test_a_link_dropped_mid_transfer_resumes(images: Images, seed: int, cycles: int, medium: str) -> None:
    """The link between modules 3 and 4 goes for ``cycles`` cycles (short: the transfer
    waits; long: it stalls and is taken up again from the bytes module 4 holds)."""
    world = World("snake:8", MEDIA[medium], images, seed=seed, image=images.v2, settle_ticks=300)
    world.run(until=_when_receiving(world, 4, 0.3))
    end = (3, 2)
    world.drop(end)
    world.run_until(world.t + cycles * PERIOD)
    world.dock(end)
    world.run()
    assert world.versions() == [2] * 8, world.summary()
    assert world.flasher.succeeded
    sent = world.modules[3].machine.counters.segments_sent
    count = -(-len(images.v2) // MEDIA[medium].segment_size)
    assert sent < 3 * count  # resumed, not started over each time


# ---------------------------------------------------------------------------------------------
# Refusals


@pytest.mark.parametrize(
    ("case", "at", "verdict"),
    [
        ("wrong key at module 3", 3, "wrong key"),
        ("tampered", 0, "tampered"),
        ("signed by a stranger", 0, "wrong key"),
        ("rollback", 0, "rollback"),
    ],
)
def test_a_refused_image_is_not_passed_on_and_nothing_switches(
    images: Images, case: str, at: int, verdict: str
) -> None:
    image = {"tampered": images.tampered, "signed by a stranger": images.other_key}.get(case, images.v2)
    running = images.v3 if case == "rollback" else images.v1
    trust = {3: [si.public_key(si.new_private_key())]} if case == "wrong key at module 3" else None
    world = World("snake:8", SERIAL, images, seed=5, image=image, running=running, trust_at=trust)
    world.run()
    flasher = world.flasher
    assert flasher.done and not flasher.succeeded
    assert flasher.failure is not None and "refused" in flasher.failure
    report = {m.path: m for m in flasher.report()}
    refused = report[snake_path(at)]
    assert (refused.outcome, refused.verdict) == (Outcome.REFUSED, verdict), refused
    assert refused.reason
    assert report[snake_path(at + 1)].outcome is Outcome.WITHHELD
    assert all(m.switched_at is None for m in world)  # no commit: nobody switched
    beyond = world.modules[at + 1 :]
    assert all(m.flash.pending is None for m in beyond)
    for m in beyond:  # the image was never complete beyond the module that refused it
        assert isinstance(m.machine, Rollout) and m.machine.received < len(image)


def test_flashing_again_after_fixing_the_trust_store(images: Images) -> None:
    """Module 3 refused the image; with its trust store fixed, the same image flashed again
    reaches every module: the staged ones report again to the new entry point."""
    stranger = [si.public_key(si.new_private_key())]
    world = World("snake:8", SERIAL, images, seed=6, image=images.v2, trust_at={3: stranger})
    world.run()
    assert not world.flasher.succeeded
    fixed = world.modules[3]
    fixed.kill()  # a new trust store is a new configuration: the module restarts with it
    fixed.flash.trust = images.trust
    fixed.restart()
    world.run_until(world.t + 10 * PERIOD)
    second = Entry(world, world.entry_index, world.rng.uniform(0, PERIOD), images.v2, 250)
    world.entry = second
    world._schedule_ticks(second)
    world.run()
    assert world.flasher.succeeded, world.summary()
    assert world.versions() == [2] * 8


def test_a_module_that_faults_on_trial_is_reported_reverted(images: Images) -> None:
    """Module 5 switches with the others and faults on trial: the host reverts it (the old
    program runs again), the entry point, waiting for confirmations, names it reverted with
    the reason; its neighbours offer it the image they run, and it declines it for good."""
    world = World("snake:8", SERIAL, images, seed=7, image=images.v2, confirm=True, faulty=[5])
    world.run()
    flasher = world.flasher
    assert flasher.done and not flasher.succeeded
    report = {m.path: m for m in flasher.report()}
    reverted = report[snake_path(5)]
    assert (reverted.outcome, reverted.version, reverted.verdict) == (Outcome.REVERTED, 1, "reverted")
    assert "faulted on trial" in reverted.reason
    assert all(report[snake_path(k)].outcome is Outcome.CONFIRMED for k in range(8) if k != 5)
    world.run_until(world.t + 2.0)  # neighbours keep offering it what they run
    assert world.versions() == [2] * 5 + [1] + [2] * 2
    assert world.modules[5].stages == 1  # declined ever since
    assert world.modules[5].machine.counters.garbage == 0


def _stage_alone(images: Images, module: Rollout, ticks: int) -> list[tuple[int, Action]]:
    """Feed ``module`` the whole image through connector 1 and tick it; its actions, each
    with the count of ticks it had when it took them."""
    info = ImageInfo(tw.image_id(images.v2), 2, len(images.v2), 80)
    out: list[tuple[int, Action]] = []
    module.tick(0.0)
    frames: list[tw.Message] = [tw.Offer(2, info.image, info.length, 80, info.count, False, ((1, 1),))]
    frames += [tw.Segment(info.tag, i, images.v2[slice(*info.span(i))]) for i in range(info.count)]
    for frame in frames:
        for action in module.receive(1, tw.encode(1, frame), 0.001):
            out.append((module.tick_count, action))
            if isinstance(action, Stage):
                out += [(module.tick_count, a) for a in module.staged(True, "ok", "", 0.001)]
    for tick in range(1, ticks):
        out += [(module.tick_count, a) for a in module.tick(tick * PERIOD)]
    return out


def _reported_at(actions: list[tuple[int, Action]]) -> int | None:
    for tick, action in actions:
        if isinstance(action, Send) and isinstance(tw.decode(action.data).message, tw.Report):
            return tick
    return None


def test_a_module_waits_for_the_hello_of_an_attached_neighbour(images: Images) -> None:
    """A connector attached but not yet heard from may have a neighbour that needs the image:
    the module reports itself staged only once it is heard (then offered the image), or after
    ``stall_ticks`` of silence, or at once if it is detached."""
    timing = Timing()
    alone = Rollout([1, 2], Program.from_image(images.v1), pacing=SERIAL.pacing, segment_size=80)
    assert _reported_at(_stage_alone(images, alone, 5)) == 2  # the next tick: the period is not known yet

    waiting = Rollout([1, 2], Program.from_image(images.v1), pacing=SERIAL.pacing, segment_size=80)
    waiting.attach(2, 0.0)
    assert _reported_at(_stage_alone(images, waiting, timing.stall_ticks + 3)) == timing.stall_ticks

    undocked = Rollout([1, 2], Program.from_image(images.v1), pacing=SERIAL.pacing, segment_size=80)
    undocked.attach(2, 0.0)
    undocked.detach(2, 0.0)
    assert _reported_at(_stage_alone(images, undocked, 5)) == 2


def test_progress_while_flashing(images: Images) -> None:
    world = World("snake:8", SERIAL, images, seed=8, image=images.v2)
    seen = []
    while not world.flasher.done:
        world.run_until(world.t + PERIOD)
        seen.append(world.flasher.progress())
    staged = [p.staged for p in seen]
    assert staged == sorted(staged) and staged[-1] == 8  # modules report as their subtrees finish
    assert [p.phase for p in seen][-1] is FlasherPhase.DONE
    final = seen[-1]
    assert (final.modules, final.committed, final.failed) == (8, 8, 0)
    assert final.bytes_acked == len(images.v2)
    assert 0 < final.rate < SERIAL.throughput * 8  # 8 images' bytes over the whole rollout


# ---------------------------------------------------------------------------------------------
# Modules behind


@pytest.mark.parametrize("seed", range(3))
def test_a_module_docked_later_is_offered_the_newer_image(images: Images, seed: int) -> None:
    """Module 7 runs version 1 and docks to a snake that runs version 2: module 6 sees the
    version in its Hello and offers its running image; module 7 stages it and switches at once."""
    world = World("snake:8", SERIAL, images, seed=seed, running=images.v2, running_at={7: images.v1}, undocked=[7])
    world.run_until(0.2)
    assert world.versions() == [2] * 7 + [1]
    world.dock((6, 2))
    world.run(until=lambda: world.versions()[7] == 2, limit=2.0)
    late = world.modules[7]
    assert late.staged_at is not None and late.switched_at is not None
    assert late.switched_at - late.staged_at <= PERIOD + 1e-9  # at its next cycle
    assert late.switched_at - 0.2 < 10 * PERIOD


def test_a_module_restarted_with_an_older_program_is_brought_up_to_date(images: Images) -> None:
    world = World("dragon", CAN, images, seed=3, running=images.v2)
    world.run_until(0.1)
    odd = world.modules[5]
    odd.kill()
    odd.flash = FakeFlash(images.trust, images.v1)  # replaced by a module on version 1
    odd.restart()
    assert world.versions()[5] == 1
    world.run(until=lambda: world.versions()[5] == 2, limit=2.0)
    world.run_until(world.t + 0.2)
    assert world.versions() == [2] * world.topology.size


# ---------------------------------------------------------------------------------------------
# Pacing


@pytest.mark.parametrize("host", ["prompt", "cycle"])
@pytest.mark.parametrize("seed", range(3))
def test_pacing_keeps_hormones_on_time_on_serial_links(images: Images, host: str, seed: int) -> None:
    """Per connector and cycle, transfer frames never cost more than the budget, and every
    hormone frame arrives as soon as it would on an idle link: no transfer byte is ever on
    the line when a cycle starts. Without pacing (a budget beyond the line's capacity) the
    same rollout delays hormones."""
    world = World("snake:8", SERIAL, images, seed=seed, image=images.v2, prompt=host == "prompt")
    world.run()
    assert world.flasher.succeeded
    for node in [*world.modules, world.entry]:
        assert node is not None and max(node.units.values()) <= SERIAL.budget
    assert max(delay for _, delay in world.hormone_delays) < 1e-9

    unpaced = World("snake:8", SERIAL, images, seed=seed, image=images.v2, pacing=Pacing(100_000, tw.serial_cost))
    unpaced.run()
    assert max(delay for _, delay in unpaced.hormone_delays) > 0.005


@pytest.mark.parametrize("seed", range(3))
def test_pacing_on_a_can_bus(images: Images, seed: int) -> None:
    """Per module and cycle at most the budget; hormones win arbitration, so a rollout delays
    one at most by the transfer frame its own node was sending (a node finishes a payload)."""
    quiet = World("snake:8", CAN, images, seed=seed)
    quiet.run_until(1.0)
    world = World("snake:8", CAN, images, seed=seed, image=images.v2)
    world.run()
    for node in [*world.modules, world.entry]:
        assert node is not None and max(node.units.values()) <= CAN.budget
    longest = CAN.seconds(CAN.segment_size + 6)
    baseline = max(delay for _, delay in quiet.hormone_delays)
    assert max(delay for _, delay in world.hormone_delays) <= baseline + longest


# ---------------------------------------------------------------------------------------------
# The figure: time to flash against the links' limits


def _flash_time(spec: str, medium: Medium, images: Images, seed: int, prompt: bool) -> tuple[float, float, int]:
    world = World(spec, medium, images, seed=seed, image=images.v2, prompt=prompt)
    world.run()
    assert world.flasher.succeeded, world.summary()
    assert world.entry is not None
    start = world.entry.phase  # the entry point's first cycle
    staged = max(m.staged_at or 0.0 for m in world) - start
    switched = max(m.switched_at or 0.0 for m in world) - start
    depth = max(len(m.path) for m in world.flasher.report())
    return staged, switched, depth


def test_figure_time_to_flash_against_the_link_limits(images: Images, capsys: pytest.CaptureFixture[str]) -> None:
    """Cycles (20 ms) from the entry point's first cycle until every module has staged the
    caterpillar's signed image (and until every one has switched, commit margin included),
    median of 5 seeds, against each medium's own limit for one hop (``throughput``): store
    and forward ``depth x image / throughput``; pipelined ``image / throughput + depth x
    segment / throughput``; on a bus every copy crosses the one bus: ``modules x image /
    throughput``. The target: within 2x of the pipelined limit on serial links, of the bus
    limit on CAN."""
    size = len(images.v2)
    lines = [
        f"\nrollout of a {size}-byte signed image, cycles of {PERIOD * 1000:.0f} ms, median of 5 seeds",
        f"{'medium':20} {'robot':9} {'host':7} {'depth':>5} {'staged':>7} {'switched':>8} "
        f"{'s&f':>6} {'pipe':>6} {'bus':>6} {'ratio':>6}",
    ]
    for medium in (SERIAL, CAN):
        for spec in ("snake:8", "snake:20"):
            for host in ("prompt", "cycle"):
                runs = [_flash_time(spec, medium, images, seed, host == "prompt") for seed in range(5)]
                staged = statistics.median(r[0] for r in runs) / PERIOD
                switched = statistics.median(r[1] for r in runs) / PERIOD
                depth = runs[0][2]
                hop = size / medium.throughput / PERIOD
                store_forward = depth * hop
                pipelined = hop + depth * medium.segment_size / medium.throughput / PERIOD
                bus = depth * hop if medium.shared else math.nan
                limit = bus if medium.shared else pipelined
                ratio = staged / limit
                shown = f"{bus:6.1f}" if medium.shared else f"{'-':>6}"
                lines.append(
                    f"{medium.name:20} {spec:9} {host:7} {depth:5d} {staged:7.1f} {switched:8.1f} "
                    f"{store_forward:6.1f} {pipelined:6.1f} {shown} {ratio:6.2f}"
                )
                if host == "prompt":
                    assert ratio <= 2.0, lines[-1]
    with capsys.disabled():
        sys.stdout.write("\n".join(lines) + "\n")


# ---------------------------------------------------------------------------------------------
# The parts on their own


def _info(length: int = 343, size: int = 80) -> ImageInfo:
    return ImageInfo(tw.image_id(bytes(length)), 2, length, size)


def test_a_store_holds_whole_segments_and_resumes_from_a_prefix() -> None:
    info = _info()
    data = bytes(range(256)) + bytes(87)
    store = _Store(info, data[:160])
    assert (store.contiguous, store.complete, store.available(True)) == (2, False, 2)
    assert store.add(3, data[240:320]) and not store.add(3, data[240:320])
    assert store.sack() == 0b1  # segment 3 held: bit 0 stands for contiguous + 1
    with pytest.raises(ValueError, match="expected 80"):
        store.add(2, data[160:200])
    with pytest.raises(ValueError, match="no run of whole segments"):
        _Store(info, data[:100])
    store.add(2, data[160:240])
    store.add(4, data[320:])
    assert store.complete and store.assemble() == data
    assert store.available(True) == 4  # the last one waits for the flash's verdict
    assert store.available(False) == 0
    store.released = True
    assert store.available(False) == 5


def test_a_partial_image_is_cut_again_for_a_source_that_segments_otherwise(images: Images) -> None:
    """A module restarted with 160 bytes held in 80-byte segments resumes from a neighbour
    that offers 56-byte segments: it keeps the 2 whole new segments (112 bytes), persists
    them anew, and asks for the third."""
    data = images.v2
    info = ImageInfo(tw.image_id(data), 2, len(data), 80)
    module = Rollout([1, 2], Program.from_image(images.v1), pacing=SERIAL.pacing, partial=Partial(info, data[:160]))
    module.tick(0.0)
    assert module.received == 160
    offer = tw.Offer(2, info.image, len(data), 56, 7, False, ((1, 1),))
    actions = module.receive(1, tw.encode(1, offer), 0.0) + module.tick(PERIOD)
    persisted = [a for a in actions if isinstance(a, Persist)]
    assert persisted == [Persist(ImageInfo(info.image, 2, len(data), 56), 0, data[:112])]
    requests = [m for a in actions if isinstance(a, Send) and isinstance(m := tw.decode(a.data).message, tw.Request)]
    assert requests[0] == tw.Request(info.image, 2, 8)
    assert module.received == 112


def test_a_sender_windows_retransmits_and_fast_retransmits() -> None:
    info = _info(800, 80)  # 10 segments
    offer = tw.Offer(2, info.image, 800, 80, 10)
    s = _Sender(info, offer, 1, 4, tick=0)
    pushed = []
    while (pick := s.next_index(0, 10, 3)) is not None:
        pushed.append(pick)
        s.sent(pick[0], 0)
    assert pushed == [(0, False), (1, False), (2, False), (3, False)]  # a window, pushed once
    assert s.next_index(5, 10, 3) is None  # unanswered offers push no more
    s.on_request(0, 4, tick=1)
    assert s.next_index(1, 10, 3) == (0, False)  # start over from what the peer holds
    for i in range(4):
        s.sent(i, 1)
    s.on_ack(0, 0b110, tick=2)  # segments 2 and 3 arrived, 0 and 1 did not
    assert s.fast == {0, 1}
    assert s.next_index(2, 10, 3) == (0, True)
    s.sent(0, 2)
    assert s.next_index(2, 10, 3) == (1, True)
    s.sent(1, 2)
    assert s.next_index(2, 10, 3) is None  # the window is full: base 0, 4 in flight
    s.on_ack(4, 0, tick=3)
    assert s.next_index(3, 10, 3) == (4, False)
    s.sent(4, 3)
    assert s.next_index(6, 10, 3) == (4, True)  # timed out after rto ticks
    s.on_ack(10, 0, tick=7)
    assert s.state is SenderState.DONE
    quiet = _Sender(info, offer, 1, 4, tick=0)
    assert not quiet.check_stall(24, 25) and quiet.check_stall(25, 25)


def test_settings_are_checked(images: Images) -> None:
    with pytest.raises(ValueError, match="stall_ticks"):
        Timing(rto_ticks=5, stall_ticks=10)
    with pytest.raises(ValueError, match="largest transfer frame"):
        Rollout([1, 2], Program.from_image(images.v1), pacing=Pacing(100, tw.serial_cost))
    assert tw.serial_cost(LARGEST_CONTROL) <= SERIAL.budget
    assert tw.can_cost(LARGEST_CONTROL) <= CAN.budget
    with pytest.raises(ValueError, match=r"connectors must be 1\.\.15"):
        Rollout([0], Program.from_image(images.v1), pacing=SERIAL.pacing)


def test_staged_without_a_stage_is_a_host_bug(images: Images) -> None:
    module = Rollout([1, 2], Program.from_image(images.v1), pacing=SERIAL.pacing)
    with pytest.raises(ValueError, match="answers a Stage action"):
        module.staged(True, "ok", "", 0.0)


def test_garbage_is_counted_and_ignored(images: Images) -> None:
    module = Rollout([1, 2], Program.from_image(images.v1), pacing=SERIAL.pacing)
    assert module.receive(1, b"\x00\x01\x02", 0.0) == []
    assert module.receive(1, tw.encode(2, tw.Segment(9, 0, b"x")), 0.0) == []
    assert (module.counters.garbage, module.counters.unwanted) == (1, 1)


def _exchange(a: Rollout | Flasher, b: Rollout, a_conn: int, b_conn: int, rounds: int) -> list[Action]:
    """Two state machines wired back to back, ticking in turn; b's non-Send actions."""
    other: list[Action] = []
    pending: list[tuple[Rollout | Flasher, int, bytes]] = []
    for r in range(rounds):
        now = r * PERIOD
        for machine, peer_conn, peer in ((a, b_conn, b), (b, a_conn, a)):
            for action in machine.tick(now):
                if isinstance(action, Send):
                    pending.append((peer, peer_conn, action.data))
                elif machine is b:
                    other.append(action)
        while pending:
            machine, conn, data = pending.pop(0)
            for action in machine.receive(conn, data, now + 0.001):
                if isinstance(action, Send):
                    target = b if machine is a else a
                    pending.append((target, b_conn if target is b else a_conn, action.data))
                elif machine is b:
                    other.append(action)
                    if isinstance(action, Stage):
                        for more in b.staged(True, "ok", "", now + 0.001):
                            if isinstance(more, Send):
                                pending.append((a, a_conn, more.data))
                            else:
                                other.append(more)
    return other


def test_a_corrupt_image_is_started_over(images: Images) -> None:
    """An image whose bytes do not hash to the offered id (a sender that garbled one) is
    dropped and requested again from the start, never staged."""
    good = images.v2
    info = ImageInfo(tw.image_id(good), 2, len(good), 80)
    module = Rollout([1, 2], Program.from_image(images.v1), pacing=SERIAL.pacing)
    module.tick(0.0)
    module.receive(1, tw.encode(1, tw.Offer(2, info.image, info.length, 80, info.count)), 0.0)
    actions: list[Action] = []
    for i in range(info.count):
        start, end = info.span(i)
        data = bytearray(good[start:end])
        if i == 1:
            data[0] ^= 0xFF
        actions += module.receive(1, tw.encode(1, tw.Segment(info.tag, i, bytes(data))), 0.0)
    assert not any(isinstance(a, Stage) for a in actions)
    assert module.counters.corrupt_images == 1 and module.received == 0
    requests = [tw.decode(a.data).message for a in actions if isinstance(a, Send)]
    assert tw.Request(info.image, 0, 8) in requests


def test_one_module_on_a_cable(images: Images) -> None:
    """The smallest robot: the whole sequence between an entry point and one module."""
    flasher = Flasher(images.v2, pacing=SERIAL.pacing, period=PERIOD, segment_size=80)
    module = Rollout([1, 2], Program.from_image(images.v1), pacing=SERIAL.pacing, segment_size=80)
    actions = _exchange(flasher, module, CABLE, 1, 40)
    kinds = [type(a).__name__ for a in actions]
    assert kinds[0] == "Persist" and "Stage" in kinds and kinds[-1] == "Switch"
    assert kinds.count("Switch") == 1
    assert flasher.phase in (FlasherPhase.SETTLING, FlasherPhase.DONE)
    assert flasher.report()[0].path == ((CABLE, 1),)
    assert {r.outcome for r in flasher.report()} <= COMMITTED | {Outcome.STAGED}
    switch = next(a for a in actions if isinstance(a, Switch))
    assert switch.program.version == 2
