"""Public testing helpers: the transport contract suite and the harnesses that run it, a fake
clock, chains of module runtimes on the in-process bus, and a watch on receptor faults.

Every transport must pass the same behaviours (:data:`CONTRACT_CHECKS`). A
:class:`TransportHarness` knows how to make endpoints (one per module), dock two of them by
connectors, and put raw garbage (and a CAN bus's management frames) on the medium; the
checks only use that and the public :class:`~dh2rt.transport.base.Transport` API. Use it from pytest::

    class TestMyTransport(TransportContract):
        def make_harness(self) -> TransportHarness:
            return MyHarness()

or without pytest: ``run_contract(MyHarness)`` returns ``{check name: "ok" | error text}``
(the udp_multicast test runs it in a subprocess inside a private network namespace).

Harnesses for ``inproc`` and the python-can transports live here; the serial harness needs
the link emulator from ``hil`` and so lives with the tests (``dh2rt`` never imports ``hil``).

:class:`FaultWatch` sees every receptor fault of every engine while it is active; the
project's test suite runs every test under it (``tests/conftest.py``) and fails a test that
faulted unless the test is marked ``expect_faults``.
"""

from __future__ import annotations

import itertools
import time
import traceback
from abc import ABC, abstractmethod
from collections.abc import Callable
from types import TracebackType
from typing import Any

from dh2rt.engine import Engine
from dh2rt.errors import TransportError
from dh2rt.hormone import Hormone, HormoneSpec, ParamSpec, Vocabulary
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.runtime import Driver, ModuleRuntime
from dh2rt.transport.base import OFF_LINK, BusEnd, FrameFamily, Inbound, Received, Transport
from dh2rt.transport.inproc import InprocBus, InprocTransport
from dh2rt.wire import operator, transfer
from dh2rt.wire.can_frames import MANAGEMENT_ID, SINGLE, make_arbitration_id
from dh2rt.wire.frame import Frame, FrameCodec, Hello, KeepAlive, program_digest

FRONT, BACK, LEFT, RIGHT = 1, 2, 3, 4

#: The vocabulary the contract uses: the caterpillar's ``X(A)``, a counter, a mixed one.
CONTRACT_VOCABULARY = Vocabulary(
    [
        HormoneSpec(0, "X", (ParamSpec("a", ("A", "B")),)),
        HormoneSpec(1, "N", (ParamSpec("n", None),)),
        HormoneSpec(2, "P", (ParamSpec("n", None), ParamSpec("m", None), ParamSpec("d", ("up", "down")))),
    ]
)

#: Garbage units: none decodes as a frame on any medium, none contains a zero byte, each
#: starts with the top bits of a link frame (1 or 3), so that it is garbage to the link codec
#: rather than a frame of a family handed to another consumer.
GARBAGE_UNITS = (b"\xff", b"\x7f\x01\x02", b"\x42\x05\x09\x09\x09", bytes(range(0x41, 0x68)))


def contract_codec() -> FrameCodec:
    return FrameCodec(CONTRACT_VOCABULARY, 4)


def long_hormone(hops: int = 40) -> Hormone:
    """A routed hormone long enough to need CAN segmentation."""
    path = tuple(((i % 4) + 1, ((i + 1) % 4) + 1) for i in range(hops))
    return Hormone("P", (-123456, 2**31 - 1, "down"), path, tuple((i % 4) + 1 for i in range(hops)))


class TransportHarness(ABC):
    """Makes endpoints of one transport and plays the physical world for them."""

    #: How long an absence check waits before concluding nothing arrived.
    settle: float = 0.25
    #: How long to wait for frames that must arrive.
    timeout: float = 5.0

    def __init__(self) -> None:
        self.codec = contract_codec()
        self.endpoints: list[Transport] = []
        self._link_ids = itertools.count(_next_link_base())

    def endpoint(self) -> Transport:
        """A new module's transport (closed by :meth:`close`)."""
        t = self._new_endpoint()
        self.endpoints.append(t)
        return t

    def link(self, a: Transport, a_conn: int, b: Transport, b_conn: int) -> int:
        """Dock ``a``'s connector ``a_conn`` (side 0) to ``b``'s ``b_conn`` (side 1)."""
        link_id = next(self._link_ids)
        self._link(link_id, a, a_conn, b, b_conn)
        return link_id

    @abstractmethod
    def _new_endpoint(self) -> Transport: ...

    @abstractmethod
    def _link(self, link_id: int, a: Transport, a_conn: int, b: Transport, b_conn: int) -> None: ...

    @abstractmethod
    def inject_garbage(self, link_id: int, to_side: int, units: tuple[bytes, ...]) -> None:
        """Put each unit on the medium as one would-be frame towards ``to_side``."""

    def inject_management(self, data: bytes) -> None:
        """Put a frame of the medium's own (``FrameFamily.MANAGEMENT``) on it, for every
        endpoint; only a medium whose transports carry that family has one."""
        raise NotImplementedError(f"{type(self).__name__}: this medium has no management frames")

    def close(self) -> None:
        for t in self.endpoints:
            t.close()


_link_base = itertools.count(1)


def _next_link_base() -> int:
    # Distinct link ids across harnesses, so a slow frame from one check never meets the next.
    return next(_link_base) * 1000


class InprocHarness(TransportHarness):
    """The in-process bus; each harness has its own :class:`InprocBus`."""

    settle = 0.05

    def __init__(self) -> None:
        super().__init__()
        from dh2rt.transport.inproc import InprocBus

        self.bus = InprocBus()

    def _new_endpoint(self) -> Transport:
        from dh2rt.transport.inproc import InprocTransport

        return InprocTransport(self.codec, bus=self.bus)

    def _link(self, link_id: int, a: Transport, a_conn: int, b: Transport, b_conn: int) -> None:
        a.attach(a_conn, BusEnd(link_id, 0))
        b.attach(b_conn, BusEnd(link_id, 1))

    def inject_garbage(self, link_id: int, to_side: int, units: tuple[bytes, ...]) -> None:
        for u in units:
            self.bus.inject(link_id, to_side, u)


class CanHarness(TransportHarness):
    """A python-can transport (``virtual``, ``udp``, ``socketcan``) plus a raw bus for garbage."""

    def __init__(self, name: str = "virtual", channel: str | None = None, **options: Any) -> None:
        super().__init__()
        from dh2rt.transport.registry import transport_class

        self.cls = transport_class(name)
        self.name = name
        self.channel = channel or (f"dh2rt-contract-{id(self)}" if name == "virtual" else None)
        self.options = options
        self._raw: Any = None

    def _new_endpoint(self) -> Transport:
        factory: Any = self.cls  # CAN transports take channel and bus options
        t: Transport = factory(self.codec, channel=self.channel, **self.options)
        return t

    def _link(self, link_id: int, a: Transport, a_conn: int, b: Transport, b_conn: int) -> None:
        a.attach(a_conn, BusEnd(link_id, 0))
        b.attach(b_conn, BusEnd(link_id, 1))

    def _raw_bus(self) -> Any:
        """A bus of its own on the same channel, to put raw frames on it."""
        if self._raw is None:
            import can

            from dh2rt.transport.can_bus import CanTransport

            cls = self.cls if issubclass(self.cls, CanTransport) else CanTransport
            self._raw = can.Bus(interface=cls.interface, channel=self.channel or cls.default_channel)
        return self._raw

    def inject_management(self, data: bytes) -> None:
        import can

        self._raw_bus().send(can.Message(arbitration_id=MANAGEMENT_ID, data=data, is_extended_id=True))

    def inject_garbage(self, link_id: int, to_side: int, units: tuple[bytes, ...]) -> None:
        import can

        raw = self._raw_bus()
        sender = 1 - to_side
        for u in units:
            for i in range(0, len(u), 8):  # units longer than 8 bytes go out as raw singles
                can_id = make_arbitration_id(0, SINGLE, 0, link_id, sender)
                raw.send(can.Message(arbitration_id=can_id, data=u[i : i + 8], is_extended_id=True))
        # A segment train that never completes, and a stray middle segment.
        raw.send(
            can.Message(
                arbitration_id=make_arbitration_id(0, 1, 0, link_id, sender),
                data=b"\x40\x00\x00\x00\x00\x00\x00\x00",
                is_extended_id=True,
            )
        )
        raw.send(
            can.Message(
                arbitration_id=make_arbitration_id(0, 2, 5, link_id, sender),
                data=b"\x01",
                is_extended_id=True,
            )
        )

    def close(self) -> None:
        super().close()
        if self._raw is not None:
            self._raw.shutdown()
            self._raw = None


# -- helpers --------------------------------------------------------------------------------


def collect(t: Transport, count: int, timeout: float) -> list[Received]:
    """Poll ``t`` until ``count`` frames arrived or ``timeout`` passed."""
    got: list[Received] = []
    deadline = time.monotonic() + timeout
    while len(got) < count:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        got += t.poll(min(left, 0.05))
    return got


def quiet(t: Transport, settle: float) -> list[Received]:
    """Everything ``t`` receives within ``settle`` seconds (expected: nothing)."""
    got: list[Received] = []
    deadline = time.monotonic() + settle
    while time.monotonic() < deadline:
        got += t.poll(0.02)
    return got


CAT = Hormone("X", ("A",))


# -- the checks -----------------------------------------------------------------------------


def check_delivers_to_linked_peer(h: TransportHarness) -> None:
    """A frame sent through a connector arrives at the linked peer's connector, remote set."""
    a, b, c, d = (h.endpoint() for _ in range(4))
    h.link(a, BACK, b, FRONT)
    h.link(b, BACK, c, FRONT)
    h.link(a, RIGHT, d, FRONT)
    assert a.send(BACK, CAT)
    got = collect(b, 1, h.timeout)
    assert got == [Received(FRONT, BACK, CAT)], got
    assert b.send(BACK, Hormone("X", ("B",)))
    assert collect(c, 1, h.timeout) == [Received(FRONT, BACK, Hormone("X", ("B",)))]
    assert c.send(FRONT, Hormone("N", (7,)))
    assert collect(b, 1, h.timeout) == [Received(BACK, FRONT, Hormone("N", (7,)))]
    assert a.send(RIGHT, Hormone("N", (4,)))
    assert collect(d, 1, h.timeout) == [Received(FRONT, RIGHT, Hormone("N", (4,)))]
    for t in (a, b, c, d):
        extra = quiet(t, h.settle)
        assert extra == [], f"unexpected extra frames: {extra}"


def check_nothing_reaches_unlinked(h: TransportHarness) -> None:
    """A module with no link to the sender hears nothing, even on a shared bus."""
    a, b, loner = h.endpoint(), h.endpoint(), h.endpoint()
    other = h.endpoint()
    h.link(a, BACK, b, FRONT)
    h.link(loner, BACK, other, FRONT)  # linked, but not to a or b
    for i in range(5):
        assert a.send(BACK, Hormone("N", (i,)))
        assert b.send(FRONT, Hormone("N", (-i,)))
    assert len(collect(b, 5, h.timeout)) == 5
    assert len(collect(a, 5, h.timeout)) == 5
    assert quiet(loner, h.settle) == []
    assert quiet(other, 0.0) == []
    assert loner.counters.received == 0 and other.counters.received == 0


def check_order_preserved(h: TransportHarness) -> None:
    """Frames on one link arrive in the order sent, long (segmented) ones included."""
    a, b = h.endpoint(), h.endpoint()
    h.link(a, BACK, b, FRONT)
    sent: list[Hormone] = []
    for i in range(60):
        hm = long_hormone(10 + i % 30) if i % 7 == 3 else Hormone("N", (i * 1000,))
        sent.append(hm)
        assert a.send(BACK, hm)
    got = collect(b, len(sent), h.timeout)
    assert [r.frame for r in got] == sent
    assert all(r.at == FRONT and r.remote == BACK for r in got)


def check_all_frame_kinds(h: TransportHarness) -> None:
    """Hormones (flooded and routed), keep-alives and hellos all cross a link intact."""
    a, b = h.endpoint(), h.endpoint()
    h.link(a, LEFT, b, FRONT)
    frames: list[Frame] = [
        CAT,
        Hormone("P", (-1, 2**31 - 1, "up"), ((1, 2), (3, 1)), None),
        Hormone("P", (0, 0, "down"), (), ()),
        long_hormone(255),
        KeepAlive(0),
        KeepAlive(255),
        Hello(program_digest(b"program")),
    ]
    for f in frames:
        assert a.send(LEFT, f)
    got = collect(b, len(frames), h.timeout)
    assert [r.frame for r in got] == frames
    assert {(r.at, r.remote) for r in got} == {(FRONT, LEFT)}


def check_full_duplex(h: TransportHarness) -> None:
    """Both ends may send at once; each receives the other's frames."""
    a, b = h.endpoint(), h.endpoint()
    h.link(a, BACK, b, FRONT)
    for i in range(20):
        assert a.send(BACK, Hormone("N", (i,)))
        assert b.send(FRONT, Hormone("N", (100 + i,)))
    got_b = collect(b, 20, h.timeout)
    got_a = collect(a, 20, h.timeout)
    assert [r.frame.args for r in got_b] == [(i,) for i in range(20)]  # type: ignore[union-attr]
    assert [r.frame.args for r in got_a] == [(100 + i,) for i in range(20)]  # type: ignore[union-attr]


def check_send_fails_when_detached(h: TransportHarness) -> None:
    """No link at a connector: send returns False and counts; detaching stops delivery."""
    a, b = h.endpoint(), h.endpoint()
    assert a.send(BACK, CAT) is False
    assert a.counters.send_failed == 1 and a.counters.sent == 0
    h.link(a, BACK, b, FRONT)
    assert a.send(BACK, CAT)
    assert len(collect(b, 1, h.timeout)) == 1
    assert a.detach(BACK) is True
    assert a.detach(BACK) is False
    assert a.send(BACK, CAT) is False
    assert a.counters.send_failed == 2
    assert BACK not in a.links
    # The far end detaches: sending still succeeds locally (a link cannot know) but the frame
    # goes nowhere; liveness is what notices a silent neighbour.
    h.link(a, LEFT, b, BACK)
    assert b.detach(BACK)
    assert a.send(LEFT, CAT) is True
    assert quiet(b, h.settle) == []
    assert b.counters.received == 1


def check_counters(h: TransportHarness) -> None:
    """sent/received count frames, not bytes or segments."""
    a, b = h.endpoint(), h.endpoint()
    h.link(a, BACK, b, FRONT)
    for i in range(10):
        assert a.send(BACK, long_hormone(50) if i == 5 else Hormone("N", (i,)))
    assert len(collect(b, 10, h.timeout)) == 10
    assert a.counters.sent == 10 and a.counters.received == 0
    assert b.counters.received == 10 and b.counters.sent == 0
    assert b.counters.corrupted == 0 and b.counters.dropped == 0


def check_close_idempotent(h: TransportHarness) -> None:
    """close() twice is fine; a closed transport sends nothing and delivers nothing."""
    a, b = h.endpoint(), h.endpoint()
    h.link(a, BACK, b, FRONT)
    with a:
        assert a.send(BACK, CAT)
    assert a.closed
    a.close()
    assert a.send(BACK, CAT) is False
    assert a.poll() == []
    assert a.links == {}
    try:
        a.attach(BACK, BusEnd(1, 0))
    except OSError:  # TransportError: attaching to a closed transport
        pass
    else:
        raise AssertionError("attach after close did not raise")
    assert len(collect(b, 1, h.timeout)) == 1
    b.close()
    b.close()


def check_garbage_counted_never_delivered(h: TransportHarness) -> None:
    """Bytes that are not a frame are counted as corrupted or dropped and never delivered."""
    a, b = h.endpoint(), h.endpoint()
    link = h.link(a, BACK, b, FRONT)
    h.inject_garbage(link, 1, GARBAGE_UNITS)
    assert a.send(BACK, CAT)  # a good frame after the garbage still gets through
    got = collect(b, 1, h.timeout)
    got += quiet(b, h.settle)
    assert [r.frame for r in got] == [CAT], got
    bad = b.counters.corrupted + b.counters.dropped
    assert bad >= len(GARBAGE_UNITS), b.counters
    assert b.counters.received == 1


#: Flashing's frames as a rollout sends them through BACK: one fits a classic CAN frame, one
#: needs segments. A transport reads no further than their first byte's family bits.
TRANSFER_FRAMES = (
    transfer.encode(BACK, transfer.Ack(tag=7, next=3)),
    transfer.encode(BACK, transfer.Segment(tag=7, index=0, data=bytes(range(60)))),
)
#: The 8 data bytes of a management frame (a transport hands them on without reading them).
MANAGEMENT_DATA = bytes((1, 0, 0, 5, 0, 0, 0, 9))


#: The operator's frames (the control family) as a module sends them through BACK: a
#: refusal fits a classic CAN frame, a status needs segments.
CONTROL_FRAMES = (
    operator.encode(BACK, operator.Refused(counter=5, left=0, path=(), reason=operator.RefusalReason.REPLAYED)),
    operator.encode(
        BACK,
        operator.StateReply(5, 0, (), operator.ModuleStatus(bytes(6), 1, False, 3, 40, (2, 0, 0, 0), (7,), (-1, 2))),
    ),
)


def _send_every_family(h: TransportHarness, a: Transport) -> None:
    """Through ``a``'s BACK, each transfer frame then a hormone, then each control frame;
    then a management frame on the medium, if it has them."""
    for payload in TRANSFER_FRAMES:
        assert a.send_raw(BACK, payload)
        assert a.send(BACK, CAT)
    for payload in CONTROL_FRAMES:
        assert a.send_raw(BACK, payload)
    if FrameFamily.MANAGEMENT in a.families:
        h.inject_management(MANAGEMENT_DATA)


def _poll_until(t: Transport, done: Callable[[list[Received]], bool], timeout: float) -> list[Received]:
    """Poll ``t`` until ``done(what poll returned so far)`` or ``timeout`` passed."""
    got: list[Received] = []
    deadline = time.monotonic() + timeout
    while not done(got):
        left = deadline - time.monotonic()
        if left <= 0:
            break
        got += t.poll(min(left, 0.05))
    return got


def check_dispatches_each_family(h: TransportHarness) -> None:
    """Hormone-family frames are what poll returns; every other family the medium carries
    goes to its handler as an Inbound (family, my connector or OFF_LINK, bytes, arrival)."""
    a, b = h.endpoint(), h.endpoint()
    h.link(a, BACK, b, FRONT)
    taken: dict[FrameFamily, list[Inbound]] = {f: [] for f in b.families if f is not FrameFamily.HORMONE}
    assert FrameFamily.TRANSFER in taken, b.families
    for family, frames in taken.items():
        b.listen(family, frames.append)
        assert b.listens(family)
    sent_at = b.clock()
    _send_every_family(h, a)
    expected = {
        FrameFamily.TRANSFER: [(FrameFamily.TRANSFER, FRONT, p) for p in TRANSFER_FRAMES],
        FrameFamily.CONTROL: [(FrameFamily.CONTROL, FRONT, p) for p in CONTROL_FRAMES],
        FrameFamily.MANAGEMENT: [(FrameFamily.MANAGEMENT, OFF_LINK, MANAGEMENT_DATA)],
    }

    def all_in(got: list[Received]) -> bool:
        return len(got) == len(TRANSFER_FRAMES) and all(len(taken[f]) == len(expected[f]) for f in taken)

    got = _poll_until(b, all_in, h.timeout)
    got += quiet(b, h.settle)
    assert got == [Received(FRONT, BACK, CAT)] * len(TRANSFER_FRAMES), got
    for family, frames in taken.items():
        assert [(f.family, f.connector, f.payload) for f in frames] == expected[family], frames
        assert all(sent_at - 1.0 <= f.arrived <= b.clock() for f in frames), (sent_at, frames)
    # frames on links are counted received, whichever family; the medium's own are not
    assert b.counters.received == 2 * len(TRANSFER_FRAMES) + len(CONTROL_FRAMES), b.counters
    assert b.counters.unhandled == 0 and b.counters.corrupted == 0, b.counters


def check_one_handler_a_family(h: TransportHarness) -> None:
    """A second handler for a family is refused until the first is closed; the hormone
    family and a family the medium does not carry take no handler at all."""
    t = h.endpoint()
    first = t.listen(FrameFamily.TRANSFER, lambda f: None)
    for family in FrameFamily:
        free = family in t.families and family not in (FrameFamily.HORMONE, FrameFamily.TRANSFER)
        try:
            t.listen(family, lambda f: None).close()
        except TransportError:
            assert not free, f"no handler for {family} was taken"
        else:
            assert free, f"a handler for {family} was taken ({t.families}, one for transfer already)"
    first.close()
    assert not t.listens(FrameFamily.TRANSFER)
    with t.listen(FrameFamily.TRANSFER, lambda f: None) as second:
        first.close()  # closing it again unregisters nothing
        assert t.listens(FrameFamily.TRANSFER) and second.family is FrameFamily.TRANSFER
    assert not t.listens(FrameFamily.TRANSFER)


def check_unhandled_counted(h: TransportHarness) -> None:
    """A frame of a family nobody listens for (any more) is counted in ``unhandled``, by
    family, and never returned by poll nor counted corrupted."""
    a, b = h.endpoint(), h.endpoint()
    h.link(a, BACK, b, FRONT)
    taken: list[Inbound] = []
    b.listen(FrameFamily.TRANSFER, taken.append).close()
    _send_every_family(h, a)
    expected = {FrameFamily.TRANSFER: len(TRANSFER_FRAMES), FrameFamily.CONTROL: len(CONTROL_FRAMES)}
    if FrameFamily.MANAGEMENT in b.families:
        expected[FrameFamily.MANAGEMENT] = 1
    got = _poll_until(b, lambda got: len(got) == len(TRANSFER_FRAMES) and b.unhandled == expected, h.timeout)
    got += quiet(b, h.settle)
    assert [r.frame for r in got] == [CAT] * len(TRANSFER_FRAMES), got
    assert b.unhandled == expected and taken == []
    assert b.counters.unhandled == sum(expected.values()), b.counters
    assert b.counters.corrupted == 0 and b.counters.received == len(TRANSFER_FRAMES), b.counters


#: Every behaviour a transport must have, by name.
CONTRACT_CHECKS: dict[str, Callable[[TransportHarness], None]] = {
    "delivers_to_linked_peer": check_delivers_to_linked_peer,
    "nothing_reaches_unlinked": check_nothing_reaches_unlinked,
    "order_preserved": check_order_preserved,
    "all_frame_kinds": check_all_frame_kinds,
    "full_duplex": check_full_duplex,
    "send_fails_when_detached": check_send_fails_when_detached,
    "counters": check_counters,
    "close_idempotent": check_close_idempotent,
    "garbage_counted_never_delivered": check_garbage_counted_never_delivered,
    "dispatches_each_family": check_dispatches_each_family,
    "one_handler_a_family": check_one_handler_a_family,
    "unhandled_counted": check_unhandled_counted,
}


def run_check(make_harness: Callable[[], TransportHarness], name: str) -> None:
    """Run one check on a fresh harness and close it, whatever happens."""
    harness = make_harness()
    try:
        CONTRACT_CHECKS[name](harness)
    finally:
        harness.close()


def run_contract(make_harness: Callable[[], TransportHarness]) -> dict[str, str]:
    """Run every check; ``{name: "ok"}`` or the failure's traceback text."""
    results: dict[str, str] = {}
    for name in CONTRACT_CHECKS:
        try:
            run_check(make_harness, name)
        except Exception:
            results[name] = traceback.format_exc()
        else:
            results[name] = "ok"
    return results


class TransportContract:
    """Mix into a pytest class (named ``Test...``) and define :meth:`make_harness`."""

    def make_harness(self) -> TransportHarness:
        raise NotImplementedError

    def test_delivers_to_linked_peer(self) -> None:
        run_check(self.make_harness, "delivers_to_linked_peer")

    def test_nothing_reaches_unlinked(self) -> None:
        run_check(self.make_harness, "nothing_reaches_unlinked")

    def test_order_preserved(self) -> None:
        run_check(self.make_harness, "order_preserved")

    def test_all_frame_kinds(self) -> None:
        run_check(self.make_harness, "all_frame_kinds")

    def test_full_duplex(self) -> None:
        run_check(self.make_harness, "full_duplex")

    def test_send_fails_when_detached(self) -> None:
        run_check(self.make_harness, "send_fails_when_detached")

    def test_counters(self) -> None:
        run_check(self.make_harness, "counters")

    def test_close_idempotent(self) -> None:
        run_check(self.make_harness, "close_idempotent")

    def test_garbage_counted_never_delivered(self) -> None:
        run_check(self.make_harness, "garbage_counted_never_delivered")

    def test_dispatches_each_family(self) -> None:
        run_check(self.make_harness, "dispatches_each_family")

    def test_one_handler_a_family(self) -> None:
        run_check(self.make_harness, "one_handler_a_family")

    def test_unhandled_counted(self) -> None:
        run_check(self.make_harness, "unhandled_counted")


# ---------------------------------------------------------------- clocks, runtimes, faults


class FakeClock:
    """An injectable clock (``clock=`` of the runtime, the servo emulator's joints...).

    Each reading advances it by ``step`` seconds (0: it moves only when told), so that loops
    waiting on it never stall; :meth:`sleep` is a ``sleep=`` that takes no real time.
    """

    def __init__(self, step: float = 0.0, start: float = 0.0) -> None:
        self.now = start
        self.step = step

    def __call__(self) -> float:
        self.now += self.step
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += max(0.0, seconds)


def runtime_chain(
    program: CompiledProgram,
    n: int,
    *,
    phases: list[int] | None = None,
    bus: InprocBus | None = None,
    driver: Callable[[int], Driver] | None = None,
    clock_step: float = 0.001,
    **options: Any,
) -> list[ModuleRuntime]:
    """``n`` module runtimes on one in-process bus, each one's ``back`` docked to the next
    one's ``front`` (a pair for n=2), links attached (the Hellos are on their way).

    Each runtime gets its own :class:`FakeClock` (``clock_step`` per reading), ``phases[i]``
    as its LocalTimer phase, ``driver(i)`` as its driver and ``options`` as further
    :class:`ModuleRuntime` arguments. Step them with :func:`step_all`; close each when done.
    """
    if phases is not None and len(phases) != n:
        raise ValueError(f"phases has {len(phases)} entries for {n} modules")
    bus = bus or InprocBus()
    codec_profile = program.profile
    front, back = codec_profile.connector_index("front"), codec_profile.connector_index("back")
    mods: list[ModuleRuntime] = []
    for i in range(n):
        codec = FrameCodec(program.vocabulary, codec_profile.connector_count)
        mods.append(
            ModuleRuntime(
                program,
                InprocTransport(codec, bus=bus),
                timer_phase=phases[i] if phases is not None else 0,
                clock=FakeClock(clock_step),
                module=i,
                driver=driver(i) if driver is not None else None,
                **options,
            )
        )
    for i in range(n - 1):
        mods[i].attach(back, BusEnd(i, 0))
        mods[i + 1].attach(front, BusEnd(i, 1))
    return mods


def robot_snapshot(robot: Robot) -> list[tuple[object, ...]]:
    """Every module's state (type, timer, DOF1/DOF2, ConnectorStatus, V, R, counters) in a
    form that compares equal exactly when two robots are in the same state."""
    out: list[tuple[object, ...]] = []
    for m in range(robot.size):
        if not robot.alive(m):
            out.append(("dead",))
            continue
        e = robot.engine(m)
        out.append(
            (
                e.topo_type.name,
                e.timer,
                tuple(e.dof),
                tuple(e.status),
                tuple(e.vars),
                tuple(e.rstatus),
                dict(e.counters),
            )
        )
    return out


def step_all(mods: list[ModuleRuntime], cycles: int = 1) -> None:
    """Step every runtime once per cycle, in list order (on the in-process bus a frame sent in
    one module's cycle n is in the next module's mailbox for its cycle n)."""
    for _ in range(cycles):
        for m in mods:
            m.step()


class FaultWatch:
    """While active, records every receptor fault of every engine (in this process) as
    ``(engine, "receptor NAME: message")``, as well as counting it in the engine as usual."""

    def __init__(self) -> None:
        self.faults: list[tuple[Engine, str]] = []
        self._original: Callable[[Engine, str, str], None] | None = None

    @property
    def messages(self) -> list[str]:
        return [message for _engine, message in self.faults]

    def __enter__(self) -> FaultWatch:
        original = self._original = Engine._fault
        faults = self.faults

        def watched(engine: Engine, source: str, message: str) -> None:
            faults.append((engine, f"{source}: {message}"))
            original(engine, source, message)

        setattr(Engine, "_fault", watched)  # noqa: B010  (every engine, including ones made later)
        return self

    def __exit__(
        self, _type: type[BaseException] | None, _exc: BaseException | None, _tb: TracebackType | None
    ) -> None:
        if self._original is not None:
            setattr(Engine, "_fault", self._original)  # noqa: B010
            self._original = None
