"""How the serial transport reads: in the module's own loop (poll on the ports' descriptors),
with pyserial's reader thread only for a port that has no descriptor."""

from __future__ import annotations

import os
import select
import threading
import time
from collections.abc import Iterator

import pytest

from dh2rt.hormone import Hormone
from dh2rt.testing import collect, contract_codec, quiet
from dh2rt.transport.serial_link import SerialTransport
from dh2rt.wire.frame import KeepAlive
from dh2rt.wire.serial_framing import encode_serial
from hil.ptys import close_fd, open_raw_pty


@pytest.fixture
def pty_port() -> Iterator[tuple[int, str]]:
    """A raw pty pair: the master (the test plays the peer) and the slave's path (the port)."""
    master, slave, path = open_raw_pty()
    yield master, path
    close_fd(master)
    close_fd(slave)


def test_a_pty_port_is_read_without_a_thread(pty_port: tuple[int, str]) -> None:
    master, path = pty_port
    codec = contract_codec()
    before = threading.active_count()
    with SerialTransport(codec) as t:
        t.attach(2, path)
        assert threading.active_count() == before
        payload = codec.encode(3, Hormone("N", (7,)))
        os.write(master, encode_serial(payload))
        got = collect(t, 1, 2.0)
        assert [(r.at, r.remote, r.frame) for r in got] == [(2, 3, Hormone("N", (7,)))]
        assert t.send(2, KeepAlive(5))


@pytest.mark.parametrize("cut", [1, 3, 7])
def test_poll_waits_for_the_rest_of_a_frame_written_in_parts(pty_port: tuple[int, str], cut: int) -> None:
    master, path = pty_port
    codec = contract_codec()
    with SerialTransport(codec) as t:
        t.attach(1, path)
        wire = encode_serial(codec.encode(2, Hormone("N", (123456,))))
        os.write(master, wire[:cut])
        assert t.poll(0.0) == []  # part of a frame is not a frame

        def rest() -> None:
            time.sleep(0.05)
            os.write(master, wire[cut:])

        writer = threading.Thread(target=rest)
        writer.start()
        start = time.monotonic()
        got = t.poll(5.0)
        writer.join()
        assert [r.frame for r in got] == [Hormone("N", (123456,))]
        assert time.monotonic() - start < 4.0  # woken by the rest, not by the timeout


class CountingPoll:
    """A real ``select.poll`` object that counts its waits."""

    def __init__(self) -> None:
        self.real = REAL_POLL()
        self.waits = 0

    def register(self, fd: int, events: int) -> None:
        self.real.register(fd, events)

    def unregister(self, fd: int) -> None:
        self.real.unregister(fd)

    def poll(self, timeout_ms: int | None = None) -> list[tuple[int, int]]:
        self.waits += 1
        return self.real.poll(timeout_ms)


REAL_POLL = select.poll


def test_a_port_whose_device_vanishes_is_lost_and_never_spins(monkeypatch: pytest.MonkeyPatch) -> None:
    master, slave, path = open_raw_pty()
    codec = contract_codec()
    pollers: list[CountingPoll] = []

    def counting_poll() -> CountingPoll:
        pollers.append(CountingPoll())
        return pollers[-1]

    monkeypatch.setattr(select, "poll", counting_poll)
    try:
        with SerialTransport(codec) as t:
            t.attach(1, path)
            close_fd(master)  # the device is gone: its descriptor is readable for ever (EIO)
            assert t.poll(0.02) == []  # one wake-up finds it gone ...
            # ... then nothing is polled: each poll of the transport waits in poll(2) at most
            # twice (what is ready now, then the rest of its timeout); a descriptor that stays
            # ready would make it spin (counted in waits, not in CPU time: the kernel's
            # hang-up of the pty costs system time on a slow machine whatever the loop does)
            (poller,) = pollers
            before, calls = poller.waits, 0
            deadline = time.monotonic() + 0.3
            while time.monotonic() < deadline:
                assert t.poll(0.02) == []
                calls += 1
            assert poller.waits - before <= 2 * calls, (poller.waits - before, calls)
            assert not t.send(1, KeepAlive(1))
            assert t.counters.send_failed == 1
    finally:
        close_fd(slave)


def test_a_port_without_a_descriptor_is_read_by_a_thread_and_wakes_poll() -> None:
    codec = contract_codec()
    before = threading.active_count()
    with SerialTransport(codec) as t:
        t.attach(4, "loop://")  # pyserial's loopback: what is written comes back; no fileno
        assert threading.active_count() == before + 1
        quiet(t, 0.1)  # the delimiter written at attach
        for seq in range(3):
            assert t.send(4, KeepAlive(seq))
        start = time.monotonic()
        got = collect(t, 3, 5.0)
        assert [(r.at, r.remote, r.frame) for r in got] == [(4, 4, KeepAlive(s)) for s in range(3)]
        assert time.monotonic() - start < 4.0
    deadline = time.monotonic() + 3
    while threading.active_count() > before and time.monotonic() < deadline:
        time.sleep(0.02)
    assert threading.active_count() == before
