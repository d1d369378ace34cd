"""What a module's loop does between cycles (``Transport.read_between_cycles``).

On a shared bus with no filters in the kernel every module's frames reach every module, so
the loop sleeps to its next cycle and reads what waited in the socket then: one wake-up a
cycle, not one per frame on the bus. On point-to-point links (and SocketCAN, which filters in
the kernel) it takes frames in as they arrive. Either way no frame is lost. Real parts:
python-can's ``virtual`` bus with a second bus object chattering on the same channel, and a
real pty pair read through pyserial.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dh2rt.compiler import compile_file
from dh2rt.program import CompiledProgram
from dh2rt.runtime import ModuleRuntime
from dh2rt.transport.base import BusEnd, Transport
from dh2rt.transport.can_bus import SocketCanTransport, UdpCanTransport, VirtualCanTransport
from dh2rt.transport.inproc import InprocTransport
from dh2rt.transport.serial_link import SerialTransport
from dh2rt.wire.frame import FrameCodec, KeepAlive
from hil.ptys import close_fd, open_raw_pty

ROOT = Path(__file__).resolve().parents[2]
CYCLES = 15
PERIOD = 0.02


@pytest.fixture(scope="module")
def caterpillar() -> CompiledProgram:
    return compile_file(str(ROOT / "examples" / "caterpillar.dh2"))


class CountingPolls:
    """Records the timeout of every ``poll`` of one transport."""

    def __init__(self, transport: Transport) -> None:
        self.timeouts: list[float] = []
        inner = transport.poll

        def poll(timeout: float = 0.0) -> Any:
            self.timeouts.append(timeout)
            return inner(timeout)

        transport.poll = poll  # type: ignore[method-assign]


@pytest.fixture
def chatter() -> Iterator[threading.Event]:
    """Another node on the virtual channel ``between``: a keep-alive on link 3 (to the module
    under test) and a frame for nobody here, every millisecond, until the test ends."""
    can = pytest.importorskip("can")
    stop = threading.Event()
    codec = FrameCodec(compile_file(str(ROOT / "examples" / "caterpillar.dh2")).vocabulary, 4)
    peer = VirtualCanTransport(codec, channel="between")
    peer.attach(2, BusEnd(3, 1))
    other = can.Bus(interface="virtual", channel="between")
    noise = can.Message(arbitration_id=0x1ABCDE, data=b"12345678", is_extended_id=True)

    def run() -> None:
        seq = 0
        while not stop.is_set():
            peer.send(2, KeepAlive(seq % 256))
            other.send(noise)
            seq += 1
            time.sleep(0.001)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    yield stop
    stop.set()
    thread.join(2)
    peer.close()
    other.shutdown()


def test_the_transports_say_how_to_wait() -> None:
    assert not VirtualCanTransport.read_between_cycles and not UdpCanTransport.read_between_cycles
    assert SocketCanTransport.read_between_cycles  # kernel filters: only its own frames wake it
    assert SerialTransport.read_between_cycles and InprocTransport.read_between_cycles


def test_on_a_shared_bus_the_loop_sleeps_between_cycles_and_loses_nothing(
    caterpillar: CompiledProgram, chatter: threading.Event
) -> None:
    codec = FrameCodec(caterpillar.vocabulary, caterpillar.profile.connector_count)
    rt = ModuleRuntime(caterpillar, VirtualCanTransport(codec, channel="between"), cycle_period=PERIOD)
    try:
        rt.attach(1, BusEnd(3, 0))
        polls = CountingPolls(rt.transport)
        assert rt.run(CYCLES) == CYCLES
        # each cycle polled once, at its start, without waiting: no wake-up per frame
        assert len(polls.timeouts) == CYCLES and set(polls.timeouts) == {0.0}, polls.timeouts
        # and what came while it slept was read (about 20 keep-alives a cycle on link 3)
        assert rt.transport.counters.received >= 5 * (CYCLES - 1), rt.transport.counters
        assert rt.transport.counters.corrupted == 0
    finally:
        rt.close()


def test_on_point_to_point_links_the_loop_takes_frames_as_they_come(caterpillar: CompiledProgram) -> None:
    codec = FrameCodec(caterpillar.vocabulary, caterpillar.profile.connector_count)
    master, slave, path = open_raw_pty()
    rt = ModuleRuntime(caterpillar, SerialTransport(codec), cycle_period=PERIOD)
    try:
        rt.attach(1, path)
        polls = CountingPolls(rt.transport)
        assert rt.run(CYCLES) == CYCLES
        # between cycles it waits in poll, until the deadline or a frame (a cycle that started
        # late on a loaded machine may find its next deadline already past: no wait then)
        assert sum(1 for t in polls.timeouts if t > 0) >= CYCLES // 3, polls.timeouts
    finally:
        rt.close()
        close_fd(master)
        close_fd(slave)
