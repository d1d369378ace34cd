"""The module's operator channel (firmware.operator) on a chain (or a ring) of real module
runtimes over the in-process bus, with a cable (a transport of its own) plugged into the head's
free front: signed commands carried out, routed, flooded, answered; forged, untrusted and
replayed ones refused and counted by every module they reach, answered once, and passed on
once per module however many copies come around; the counter surviving a restart."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import pytest
from nacl.signing import SigningKey

from dh2rt.bundled import compile_bundled
from dh2rt.hormone import Hormone
from dh2rt.runtime import ModuleRuntime
from dh2rt.transport.base import BusEnd, FrameFamily, Inbound
from dh2rt.transport.inproc import InprocBus, InprocTransport
from dh2rt.wire import operator as op
from dh2rt.wire.frame import FrameCodec
from firmware.operator import COUNTER_FILE, MAX_HOPS, REFUSED_MEMORY_CYCLES, REFUSED_PER_CYCLE, OperatorChannel

FRONT, BACK, LEFT, RIGHT = 1, 2, 3, 4
KEY = bytes(range(32))
PUBLIC = bytes(SigningKey(KEY).verify_key)
STRANGER = bytes(range(100, 132))
PROGRAM = compile_bundled("legs_to_snake.dh2")
#: links between modules: (module, connector, module, connector) each
Links = tuple[tuple[int, int, int, int], ...]


class Chain:
    """Modules m0..m(n-1), each one's back on the next one's front; the cable on m0's front;
    with ``ring``, the last one's back on m0's left too; ``extra`` links (module, connector,
    module, connector) besides (or alone, not ``chained``)."""

    def __init__(
        self,
        n: int,
        flash: Path,
        trust: tuple[bytes, ...] = (PUBLIC,),
        *,
        ring: bool = False,
        extra: Links = (),
        chained: bool = True,
    ) -> None:
        self.bus = InprocBus()
        codec = FrameCodec(PROGRAM.vocabulary, PROGRAM.profile.connector_count)
        self.modules = [ModuleRuntime(PROGRAM, InprocTransport(codec, bus=self.bus), module=i) for i in range(n)]
        self.channels = []
        for i, rt in enumerate(self.modules):
            (flash / f"m{i}").mkdir(exist_ok=True)
            self.channels.append(OperatorChannel(rt, trust, flash / f"m{i}"))
        for i in range(n - 1 if chained else 0):
            self.modules[i].attach(BACK, BusEnd(i, 0))
            self.modules[i + 1].attach(FRONT, BusEnd(i, 1))
        if ring:
            extra = ((n - 1, BACK, 0, LEFT), *extra)
        for link, (a, ca, b, cb) in enumerate(extra, start=n):
            self.modules[a].attach(ca, BusEnd(link, 0))
            self.modules[b].attach(cb, BusEnd(link, 1))
        self.cable = InprocTransport(codec, bus=self.bus)
        self.cable.attach(BACK, BusEnd(1000, 0))
        self.modules[0].attach(FRONT, BusEnd(1000, 1))
        self.answers: list[op.Message] = []
        self.cable.listen(FrameFamily.CONTROL, self._answer)
        self.counter = 0

    def _answer(self, frame: Inbound) -> None:
        self.answers.append(op.decode(frame.payload).message)

    def send(self, command: op.Command, key: bytes = KEY, counter: int | None = None) -> op.Signed:
        self.counter = self.counter + 1 if counter is None else counter
        signed = op.sign(command, self.counter, key)
        self.send_signed(signed)
        return signed

    def send_signed(self, signed: op.Signed) -> None:
        assert self.cable.send_raw(BACK, op.encode(BACK, signed))

    def cycles(self, n: int = 1) -> None:
        """n cycles of every module, frames between them carried at once (inproc)."""
        for _ in range(n):
            for rt in self.modules:
                rt.step()
            for _ in range(len(self.modules) + 1):  # control frames pass a hop a poll
                for rt in self.modules:
                    rt.take_in()
            self.cable.poll()

    def close(self) -> None:
        for rt in self.modules:
            rt.close()
        self.cable.close()


@pytest.fixture
def chain(tmp_path: Path) -> Iterator[Chain]:
    c = Chain(3, tmp_path)
    c.cycles(3)
    yield c
    c.close()


def route_to(i: int) -> op.Path:
    return ((BACK, FRONT),) * i


def test_state_is_routed_to_each_module_and_back(chain: Chain) -> None:
    for i, rt in enumerate(chain.modules):
        chain.answers.clear()
        chain.send(op.StateRequest(route_to(i)))
        chain.cycles(1)
        (reply,) = chain.answers
        assert isinstance(reply, op.StateReply) and reply.path == route_to(i) and reply.left == 0
        s = reply.status
        assert s.digest == rt.digest and s.type_index == rt.engine.type_index
        assert s.connectors == tuple(rt.engine.status) and s.variables == tuple(rt.engine.vars)
        assert s.receptors == tuple(rt.engine.rstatus) and not s.paused
    assert [ch.core.accepted for ch in chain.channels] == [3, 2, 1]
    assert chain.channels[0].core.relayed == 2 and chain.channels[1].core.relayed == 1


def test_inject_reaches_the_module_its_route_names(chain: Chain) -> None:
    injected: list[tuple[int, Hormone]] = []

    def recorder(i: int) -> Callable[[Hormone], None]:
        return lambda h: injected.append((i, h))

    for i, rt in enumerate(chain.modules):
        rt.inject = recorder(i)  # type: ignore[method-assign, assignment]
    content = PROGRAM.vocabulary.encode_content(Hormone("LTS", ()))
    chain.send(op.Inject(chain.modules[0].digest, content, route_to(2)))
    chain.cycles(1)
    assert injected == [(2, Hormone("LTS", ()))] and chain.answers == []


def test_pause_floods_holds_every_engine_and_resume_goes_on_where_it_stopped(chain: Chain) -> None:
    chain.send(op.Pause())
    chain.cycles(1)
    assert all(rt.paused for rt in chain.modules)
    timers = [rt.engine.timer for rt in chain.modules]
    chain.cycles(5)
    assert [rt.engine.timer for rt in chain.modules] == timers
    assert all(rt.verified(FRONT) for rt in chain.modules[1:])  # links kept alive meanwhile
    chain.send(op.Resume())
    chain.cycles(2)  # the head takes the RESUME in as its cycle starts: two steps each
    assert not any(rt.paused for rt in chain.modules)
    clock = PROGRAM.clock_cycle
    assert [rt.engine.timer for rt in chain.modules] == [(t + 2) % clock for t in timers]
    assert [ch.core.accepted for ch in chain.channels] == [2, 2, 2]


def test_wrong_key_forgery_and_replay_are_refused_answered_and_counted(chain: Chain) -> None:
    chain.send(op.Pause(), key=STRANGER)
    good = op.sign(op.Pause(), 50, KEY)
    chain.send_signed(op.Signed(good.command, 50, good.key_id, bytes(64)))  # forged signature
    chain.send_signed(op.Signed(op.Resume(), 50, good.key_id, good.signature))  # PAUSE's signature on a RESUME
    chain.cycles(1)
    assert not any(rt.paused for rt in chain.modules)
    chain.send_signed(good)
    chain.cycles(1)
    assert all(rt.paused for rt in chain.modules)
    chain.send_signed(good)  # the same again, from the cable: a replay
    chain.send(op.Resume(), counter=49)  # an older counter
    chain.cycles(1)
    assert all(rt.paused for rt in chain.modules)
    reasons = [a.reason for a in chain.answers if isinstance(a, op.Refused)]
    why = op.RefusalReason
    # the module at the cable answers for the flood, once a command
    assert reasons == [why.UNTRUSTED_KEY, why.BAD_SIGNATURE, why.BAD_SIGNATURE, why.REPLAYED, why.REPLAYED]
    for i, ch in enumerate(chain.channels):  # every module judged each for itself
        counted = ch.core.counters
        assert counted["refused_untrusted_key"] == 1 and counted["refused_bad_signature"] == 2, (i, counted)
        assert counted["refused_replayed"] == 2 and counted["accepted"] == 1 and counted["duplicates"] == 0, i
        assert any(f"refused PAUSE 50 at connector {FRONT}: REPLAYED" in line for line in chain.modules[i].log)


def test_a_refused_routed_command_travels_its_route_and_its_end_answers(chain: Chain) -> None:
    chain.send(op.StateRequest(route_to(2)), key=STRANGER)
    chain.cycles(1)
    assert chain.answers == [op.Refused(chain.counter, 0, route_to(2), op.RefusalReason.UNTRUSTED_KEY)]
    assert [ch.core.refused[op.RefusalReason.UNTRUSTED_KEY] for ch in chain.channels] == [1, 1, 1]
    chain.answers.clear()
    good = chain.send(op.StateRequest(route_to(1)))
    chain.cycles(1)
    assert [type(a) for a in chain.answers] == [op.StateReply]
    chain.answers.clear()
    chain.send_signed(good)  # replayed: refused by the modules on its way, answered by its end
    chain.cycles(1)
    assert chain.answers == [op.Refused(good.counter, 0, route_to(1), op.RefusalReason.REPLAYED)]
    assert [ch.core.refused[op.RefusalReason.REPLAYED] for ch in chain.channels] == [1, 1, 0]
    assert [ch.core.accepted for ch in chain.channels] == [1, 1, 0]


def test_the_same_refused_frame_again_from_the_cable_is_answered_but_not_passed_on_again(chain: Chain) -> None:
    stranger = chain.send(op.Pause(), key=STRANGER)
    chain.cycles(1)
    chain.send_signed(stranger)
    chain.cycles(1)
    assert [ch.core.refused[op.RefusalReason.UNTRUSTED_KEY] for ch in chain.channels] == [2, 1, 1]
    assert [a.reason for a in chain.answers if isinstance(a, op.Refused)] == [op.RefusalReason.UNTRUSTED_KEY] * 2


class SentCommands:
    """The signed commands each module sends, by connector (its answers are not counted)."""

    def __init__(self, chain: Chain) -> None:
        self.sent: list[Counter[tuple[int, op.Signed]]] = [Counter() for _ in chain.modules]
        for i, rt in enumerate(chain.modules):
            rt.transport.send_raw = self._wrap(i, rt.transport.send_raw)  # type: ignore[method-assign, assignment]

    def _wrap(self, i: int, send_raw: Callable[[int, bytes], bool]) -> Callable[[int, bytes], bool]:
        def sent(connector: int, frame: bytes) -> bool:
            if op.is_control(frame) and isinstance(message := op.decode(frame).message, op.Signed):
                self.sent[i][connector, replace(message, hops=0)] += 1
            return send_raw(connector, frame)

        return sent

    def total(self) -> int:
        return sum(sum(c.values()) for c in self.sent)

    def once_a_connector(self) -> None:
        """Each module sent each command through each connector at most once (since the
        last check); then count afresh."""
        for i, by_module in enumerate(self.sent):
            assert max(by_module.values(), default=1) == 1, (i, by_module)
        self.sent = [Counter() for _ in self.sent]


def test_in_a_ring_a_refused_flood_is_counted_by_every_module_and_its_copies_die(tmp_path: Path) -> None:
    """Four modules in a ring (m3's back on m0's left), the cable at m0's front: a PAUSE
    signed with another key, and a replay of an accepted one, reach every module once and
    are refused and counted there; their copies that come back around are duplicates; each
    module passes each frame on once, through each other connector, and then all is quiet."""
    ring = Chain(4, tmp_path, ring=True)
    ring.cycles(3)
    sent = SentCommands(ring)
    ring.send(op.Pause(), key=STRANGER)
    ring.cycles(2)
    why = op.RefusalReason
    assert [ch.core.refused[why.UNTRUSTED_KEY] for ch in ring.channels] == [1, 1, 1, 1]
    assert not any(rt.paused for rt in ring.modules)
    # five copies went round (m0 sent both ways, the others one each): three were a module's
    # first, two the duplicates where the two waves met
    assert sent.total() == 5 and sum(ch.core.duplicates for ch in ring.channels) == 2
    assert ring.answers == [op.Refused(ring.counter, 0, (), why.UNTRUSTED_KEY)]
    sent.once_a_connector()
    good = ring.send(op.Pause())
    ring.cycles(1)
    assert all(rt.paused for rt in ring.modules) and [ch.core.accepted for ch in ring.channels] == [1] * 4
    sent.once_a_connector()  # the PAUSE carried out went round once (and is forgotten here)
    ring.send_signed(good)  # the same PAUSE again: a replay, everywhere
    ring.cycles(2)
    assert [ch.core.refused[why.REPLAYED] for ch in ring.channels] == [1, 1, 1, 1]
    assert sum(ch.core.duplicates for ch in ring.channels) == 2 + 2 + 2
    assert [a.reason for a in ring.answers if isinstance(a, op.Refused)] == [why.UNTRUSTED_KEY, why.REPLAYED]
    sent.once_a_connector()
    ring.cycles(5)
    assert sent.total() == 0  # nothing circles
    ring.close()


#: m0..m3 a ring, m4 on m2's left and on m0's right: two rings sharing m0 and m2
TWO_RINGS: Links = ((0, BACK, 1, FRONT), (1, BACK, 2, FRONT), (2, BACK, 3, FRONT), (3, BACK, 0, LEFT))
TWO_RINGS += ((2, LEFT, 4, FRONT), (4, BACK, 0, RIGHT))
#: a body (m0) with three legs (m1..m3) linked to each other, and m4 between two legs
BODY: Links = ((0, BACK, 1, FRONT), (0, LEFT, 2, FRONT), (0, RIGHT, 3, FRONT), (1, BACK, 2, BACK))
BODY += ((2, LEFT, 3, BACK), (3, LEFT, 4, FRONT), (4, BACK, 1, LEFT))


@pytest.mark.parametrize("links", [TWO_RINGS, BODY], ids=["two-rings", "body-and-linked-legs"])
def test_refused_floods_in_loopy_bodies_reach_every_module_once(tmp_path: Path, links: Links) -> None:
    """In bodies with several loops, a PAUSE signed with another key and a replayed one are
    refused once by every module, answered once, passed on once a connector, and die out."""
    n = 5
    body = Chain(n, tmp_path, extra=links, chained=False)
    body.cycles(3)
    sent = SentCommands(body)
    why = op.RefusalReason
    body.send(op.Pause(), key=STRANGER)
    body.cycles(2)
    sent.once_a_connector()
    good = body.send(op.Pause())
    body.cycles(1)
    assert all(rt.paused for rt in body.modules)
    sent.once_a_connector()
    body.send_signed(good)
    body.cycles(2)
    sent.once_a_connector()
    body.cycles(5)
    assert sent.total() == 0
    assert [ch.core.refused[why.UNTRUSTED_KEY] for ch in body.channels] == [1] * n
    assert [ch.core.refused[why.REPLAYED] for ch in body.channels] == [1] * n
    assert [ch.core.accepted for ch in body.channels] == [1] * n
    assert [a.reason for a in body.answers if isinstance(a, op.Refused)] == [why.UNTRUSTED_KEY, why.REPLAYED]
    body.close()


def test_a_refused_command_is_passed_on_again_once_forgotten_and_never_past_255_hops(chain: Chain) -> None:
    stranger = chain.send(op.Pause(), key=STRANGER)
    chain.cycles(1)
    chain.cycles(REFUSED_MEMORY_CYCLES + 1)
    chain.send_signed(stranger)  # forgotten by now: judged and passed on again, as new
    chain.cycles(1)
    assert [ch.core.refused[op.RefusalReason.UNTRUSTED_KEY] for ch in chain.channels] == [2, 2, 2]
    far = op.sign(op.Pause(), 7, STRANGER)
    chain.send_signed(replace(far, hops=MAX_HOPS - 1))  # m0 passes it on with 255 hops; m1 no further
    chain.cycles(1)
    assert [ch.core.refused[op.RefusalReason.UNTRUSTED_KEY] for ch in chain.channels] == [3, 3, 2]


def test_a_flood_of_made_up_frames_costs_a_module_one_relay_each_and_a_few_a_cycle(tmp_path: Path) -> None:
    """Twenty distinct frames with made-up signatures in one cycle, into a ring: the module
    at the cable passes on as many as a cycle allows and counts the rest; each other module
    refuses each one it got once, passes it on once, and takes the copy from its other side
    as a duplicate."""
    ring = Chain(4, tmp_path, ring=True)
    ring.cycles(3)
    sent = SentCommands(ring)
    kid = op.key_id(PUBLIC)
    for n in range(20):
        ring.send_signed(op.Signed(op.Pause(), 1000 + n, kid, bytes([n]) * 64))
    ring.cycles(1)
    head = ring.channels[0].core.counters
    assert head["refused_bad_signature"] == 20 and head["not_passed_on"] == 20 - REFUSED_PER_CYCLE
    refused = [ch.core.refused[op.RefusalReason.BAD_SIGNATURE] for ch in ring.channels[1:]]
    assert refused == [REFUSED_PER_CYCLE] * 3
    for i, by_module in enumerate(sent.sent):
        assert len({seen for _, seen in by_module}) == REFUSED_PER_CYCLE, i
    sent.once_a_connector()
    ring.cycles(5)
    assert sent.total() == 0
    ring.close()


def test_a_route_through_nothing_is_refused_along_the_way_back(chain: Chain) -> None:
    chain.send(op.StateRequest((*route_to(2), (3, FRONT))))  # m2 has nothing at its right
    chain.cycles(1)
    assert chain.answers == [op.Refused(chain.counter, 0, route_to(2), op.RefusalReason.NO_ROUTE)]


def test_the_last_counter_survives_a_restart(tmp_path: Path) -> None:
    first = Chain(1, tmp_path)
    first.send(op.Pause(), counter=77)
    first.cycles(1)
    first.close()
    assert (tmp_path / "m0" / COUNTER_FILE).read_text() == '{"last_counter": 77}'
    again = Chain(1, tmp_path)
    again.send(op.Pause(), counter=77)
    again.send(op.Pause(), counter=78)
    again.cycles(1)
    assert [a.reason for a in again.answers if isinstance(a, op.Refused)] == [op.RefusalReason.REPLAYED]
    assert again.modules[0].paused
    again.close()


def test_a_flood_is_passed_on_before_the_counter_is_written(tmp_path: Path) -> None:
    """A PAUSE's copies leave before the module's flash write (an fsync per hop once spread a
    PAUSE over 8 modules past 2 cycles on a busy machine); the write still comes before the
    module's next cycle, and a restart after it refuses the replay."""
    c = Chain(2, tmp_path)
    order: list[str] = []
    head = c.channels[0]
    send_raw = c.modules[0].transport.send_raw
    write = head.core.persist

    def sent(connector: int, frame: bytes) -> bool:
        order.append(f"send {connector}")
        return send_raw(connector, frame)

    def written(counter: int) -> None:
        order.append(f"write {counter}")
        write(counter)

    c.modules[0].transport.send_raw = sent  # type: ignore[method-assign, assignment]
    head.core.persist = written
    c.send(op.Pause(), counter=9)
    c.cycles(1)
    assert order[:2] == [f"send {BACK}", "write 9"], order
    assert (tmp_path / "m0" / COUNTER_FILE).read_text() == '{"last_counter": 9}'
    assert all(rt.paused for rt in c.modules) and head.core.unsaved is None
    c.close()


def test_a_module_that_trusts_no_key_takes_no_command(tmp_path: Path) -> None:
    c = Chain(1, tmp_path, trust=())
    c.send(op.Pause())
    c.cycles(1)
    assert c.answers == [op.Refused(1, 0, (), op.RefusalReason.NO_CONTROL)] and not c.modules[0].paused
    c.close()


def test_garbage_is_counted_malformed(chain: Chain) -> None:
    chain.cable.send_raw(BACK, bytes((0x21, 64, 0)))  # the reserved docking range
    chain.cycles(1)
    assert chain.channels[0].core.malformed == 1
    assert any("reserved" in line for line in chain.modules[0].log)


def test_a_state_request_writes_no_flash(tmp_path: Path) -> None:
    c = Chain(1, tmp_path)
    c.send(op.StateRequest(), counter=5)
    c.cycles(1)
    assert not (tmp_path / "m0" / COUNTER_FILE).exists() and c.channels[0].core.last_counter == 5
    c.send(op.Pause(), counter=6)
    c.cycles(1)
    assert (tmp_path / "m0" / COUNTER_FILE).read_text() == '{"last_counter": 6}'
    c.close()


def test_watch_sends_the_cable_what_its_module_receives_then_ends(chain: Chain) -> None:
    lts = PROGRAM.vocabulary.encode_content(Hormone("LTS", ()))
    index = PROGRAM.vocabulary.by_name["RCT"].index
    chain.send(op.Watch(3, index))  # RCT only: the LTS below is not shown
    chain.send(op.Inject(chain.modules[0].digest, lts))
    chain.cycles(1)
    assert not [a for a in chain.answers if isinstance(a, op.Watched)]
    chain.send(op.Watch(2))
    chain.send(op.Inject(chain.modules[0].digest, lts))
    chain.cycles(1)
    (watched,) = [a for a in chain.answers if isinstance(a, op.Watched)]
    assert watched.counter == chain.counter - 1 and watched.at == 0  # injected at the cable's module
    codec = chain.modules[0].transport.codec
    assert codec.decode(watched.frame).frame == Hormone("LTS", ())
    chain.cycles(3)
    chain.send(op.Inject(chain.modules[0].digest, lts))
    chain.cycles(1)
    assert len([a for a in chain.answers if isinstance(a, op.Watched)]) == 1  # the watch ended by itself
    assert chain.channels[0].core.watch is None and chain.channels[0].core.counters["accepted"] == 5


def test_a_watch_from_beyond_the_cables_module_is_refused(chain: Chain) -> None:
    signed = op.sign(op.Watch(5), 99, KEY)
    chain.send_signed(op.Signed(signed.command, 99, signed.key_id, signed.signature, hops=1))
    chain.cycles(1)
    assert chain.channels[0].core.refused[op.RefusalReason.NO_ROUTE] == 1 and chain.channels[0].core.watch is None
