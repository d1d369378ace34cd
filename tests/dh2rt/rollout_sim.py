"""The simulated robot the rollout tests and bench_flash run :mod:`dh2rt.flash` in (see
tests/dh2rt/test_rollout.py's docs for what it models)."""

from __future__ import annotations

import functools
import heapq
import itertools
import math
import random
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

from dh2rt import signed_image as si
from dh2rt.compiler import compile_source
from dh2rt.flash.flasher import Flasher
from dh2rt.flash.pacing import SERIAL_TIMING, Pacing
from dh2rt.flash.rollout import Rollout
from dh2rt.flash.values import Action, DropPartial, ImageInfo, Partial, Persist, Program, Send, Stage, Switch, Timing
from dh2rt.topology import Topology, parse_spec
from dh2rt.wire import transfer as tw
from dh2rt.wire.can_frames import CLASSIC_DATA
from dh2rt.wire.frame import NO_PROGRAM
from firmware.flash.cable import HELLO_TICKS

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


def make_images(source: str) -> Images:
    """The caterpillar's images for the rollout: v1 (ClockCycle 40) running, v2 (20) the
    new one, v3, v2 signed by a stranger's key, and v2 with one bit flipped."""
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
        # the line's own rate times frames on a link of their own (not on the shared bus)
        return Pacing(self.budget, self.cost, self.shared, 0.0 if self.shared else self.rate * SERIAL_TIMING)

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
    """A module's A/B flash in memory: what ``firmware.flash.slots.Flash`` decides, with the
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
        self.leaves = -math.inf  # a busy host: when its last held-up frame leaves
        self.ticked_at: float | None = None  # when its last cycle began

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
        w = self.world
        key = 0 if w.medium.shared else action.connector
        self.units[(self.machine.tick_count, key)] += w.medium.cost(len(action.data))
        if not w.send_delay:
            self.transmit(action)
            return
        # a busy host: held up a while before it sends, its frames still in order
        self.leaves = max(w.t + w.rng.uniform(0, w.send_delay), self.leaves)
        w.schedule(self.leaves, functools.partial(self.transmit, action, self.generation))

    def transmit(self, action: Send, generation: int | None = None) -> None:
        if generation is not None and (generation != self.generation or not self.alive):
            return  # killed (or restarted) while held up: the frame never left
        frame = action.frame(self.local(self.world.t))  # a COMMIT stamped as it leaves
        self.world.transmit(self, action.connector, frame, link=False)

    def tick(self) -> None:
        """A cycle: the state machine's tick (a switch takes effect at once), the link
        frames (hormones, beacons: the new program's Hello after a switch), then the
        transfer frames the tick let out."""
        w = self.world
        self.ticked_at = w.t
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
        self.hellos: dict[int, tuple[float, bytes]] = {}  # connector -> its last Hello: (when, frame)
        self.opened = not world.opened_by_frame
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
        self.hellos.pop(connector, None)

    def take(self, at: float, connector: int, frame: Frame) -> None:
        if not frame.link and not self.opened:
            self.open()
        super().take(at, connector, frame)

    def open(self) -> None:
        """A host that loads its Rollout at the first transfer frame (firmware.flash.door):
        a new one, the links attached, the Hellos kept handed on, and (``joins_cycle``) the
        cycle under way and the period told (``Rollout.join_cycle``)."""
        w = self.world
        self.opened = True
        self.machine = self.boot()
        if w.joins_cycle and self.ticked_at is not None:
            self.machine.join_cycle(self.local(self.ticked_at), PERIOD)
        for connector in w.connectors(self.index):
            self.run(self.machine.attach(connector, self.local(w.t)))
        for connector, (at, payload) in sorted(self.hellos.items()):
            hello = tw.decode_hello(payload)
            self.run(self.machine.hello(connector, hello.sender, hello.version, hello.digest, self.local(at)))

    def take_link_frame(self, at: float, connector: int, frame: Frame) -> None:
        digest = tw.decode_hello(frame.payload).digest if len(frame.payload) > LINK_FRAME else None
        if digest is not None and digest != NO_PROGRAM:  # a cable (NO_PROGRAM) is a tool: neither verified nor refused
            self.hellos[connector] = (at, frame.payload)
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
        self.opened = not self.world.opened_by_frame or self.partial is not None or self.flash.pending is not None
        self.hellos = {}
        self.ticked_at = None
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
            expect=world.topology.size,
        )
        self.done_at: float | None = None

    def send_link_frames(self) -> None:
        """Every HELLO_TICKS ticks, from the first, the cable says it runs no program, as
        FlashCable does (the 7-byte Hello, no version): the module there hears the cable again
        after a silence."""
        if (self.machine.tick_count - 1) % HELLO_TICKS == 0:
            payload = tw.encode_hello(CABLE, NO_PROGRAM, 0)[: 1 + len(NO_PROGRAM)]
            self.world.transmit(self, CABLE, payload, link=True)

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
        send_delay: float = 0.0,
        cut_through: bool = True,
        pacing: Pacing | None = None,
        timing: Timing | None = None,
        entry: tuple[int, int] = (0, 1),
        undocked: Iterable[int] = (),
        settle_ticks: int = 250,
        confirm: bool = False,
        faulty: Iterable[int] = (),
        opened_by_frame: bool = False,
        joins_cycle: bool = True,
    ) -> None:
        self.topology = parse_spec(spec) if isinstance(spec, str) else spec
        #: modules load their Rollout at the first transfer frame (firmware.flash.door),
        #: telling it the cycle under way (``joins_cycle``), rather than at boot
        self.opened_by_frame = opened_by_frame
        self.joins_cycle = joins_cycle
        self.medium = medium
        self.rng = random.Random(seed)
        self.t = 0.0
        self.prompt = prompt
        self.loss, self.latency, self.jitter = loss, latency, jitter
        #: a busy host: a transfer frame leaves up to this long after its state machine
        #: decided to send it (as a module's thread held up by the others of its process)
        self.send_delay = send_delay
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
            self.schedule_ticks(m)
        self.entry: Entry | None = None
        if image is not None:  # the entry point keeps time of its own, whatever the modules do
            self.entry = Entry(self, n, self.rng.uniform(PERIOD, 2 * PERIOD), image, settle_ticks, confirm=confirm)
            self.schedule_ticks(self.entry)

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

    def schedule_ticks(self, node: Node) -> None:
        """Tick ``node`` every period from now on, while this life of it lasts (a new entry point too)."""
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
        self.schedule_ticks(self.modules[index])

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


def flash_time(spec: str, medium: Medium, images: Images, seed: int, prompt: bool) -> tuple[float, float, int]:
    world = World(spec, medium, images, seed=seed, image=images.v2, prompt=prompt)
    world.run()
    assert world.flasher.succeeded, world.summary()
    assert world.entry is not None
    start = world.entry.phase  # the entry point's first cycle
    staged = max(m.staged_at or 0.0 for m in world) - start
    switched = max(m.switched_at or 0.0 for m in world) - start
    depth = max(len(m.path) for m in world.flasher.report())
    return staged, switched, depth


def staged_hops(
    spec: str, medium: Medium, images: Images, seed: int, *, opened_by_frame: bool = False, joins_cycle: bool = True
) -> list[float]:
    """Cycles between the stagings of successive modules of a snake flashed from its head
    (module k to k + 1, prompt hosts): what each further hop adds (see World for the options)."""
    world = World(
        spec, medium, images, seed=seed, image=images.v2, opened_by_frame=opened_by_frame, joins_cycle=joins_cycle
    )
    world.run()
    assert world.flasher.succeeded, world.summary()
    staged = [m.staged_at for m in world]
    assert all(t is not None for t in staged), world.summary()
    return [(b - a) / PERIOD for a, b in itertools.pairwise(t for t in staged if t is not None)]
