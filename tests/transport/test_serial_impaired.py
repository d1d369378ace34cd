"""Serial links through the link emulator with loss, bit errors, latency and undocking."""

from __future__ import annotations

import threading
import time

import pytest

from dh2rt.hormone import Hormone
from dh2rt.testing import collect, contract_codec, long_hormone, quiet
from dh2rt.transport.base import PortEnd, Received
from dh2rt.transport.serial_link import SerialTransport
from dh2rt.wire.frame import KeepAlive
from hil.link_emulator import LinkEmulator

COUNT = 600


def _long(i: int) -> Hormone:
    h = long_hormone(5 + i % 20)
    return Hormone(h.name, (i, -i, "up"), h.path, h.route)


def test_loss_and_bit_errors_never_deliver_a_corrupted_frame() -> None:
    codec = contract_codec()
    with (
        LinkEmulator(frame_loss=0.05, bit_error=0.002, seed=1234) as em,
        # the relay is a thread of this process: on a slow machine it may take seconds to
        # drain what the sender wrote, and this test is about corruption, not throughput
        SerialTransport(codec, write_timeout=10.0) as a,
        SerialTransport(codec) as b,
    ):
        link = em.add_link()
        a.attach(2, PortEnd(link.paths[0]))
        b.attach(1, PortEnd(link.paths[1]))
        sent = [_long(i) if i % 10 == 0 else Hormone("N", (i * 7919,)) for i in range(COUNT)]
        got: list[Received] = []
        for i, h in enumerate(sent):
            assert a.send(2, h)
            if i % 10 == 9:
                # let the relay keep up, and read as a module does each cycle: with no reader
                # thread, a pty's few kB are all that holds what nobody has read yet
                time.sleep(0.01)
                got += b.poll(0.0)
        got += collect(b, COUNT - len(got), 5.0)
        got += quiet(b, 0.2)
        stats = em.stats(link.link_id)
    frames = [r.frame for r in got]
    # Every delivered frame is one that was sent, in the order sent: nothing corrupted got in.
    positions = [sent.index(f) for f in frames if isinstance(f, Hormone)]
    assert len(positions) == len(frames)
    assert positions == sorted(positions)
    assert all(r.at == 1 and r.remote == 2 for r in got)
    lost = COUNT - len(frames)
    assert stats.frames_lost > 0 and stats.bits_flipped > 0
    # The medium lost whole frames; the rest of the losses are bit errors the receiver caught
    # and counted. A flip can damage two frames at most (a delimiter turned into data merges
    # two frames into one corrupted one; data turned into a delimiter splits one in two).
    assert b.counters.corrupted > 0 and b.counters.dropped == 0
    assert lost - stats.frames_lost <= 2 * b.counters.corrupted
    assert b.counters.corrupted <= 2 * stats.bits_flipped
    assert lost <= stats.frames_lost + 2 * stats.bits_flipped
    assert b.counters.received == len(frames)


def test_undock_stops_relaying_and_dock_resumes() -> None:
    codec = contract_codec()
    with (
        LinkEmulator(latency=0.02, seed=5) as em,
        SerialTransport(codec) as a,
        SerialTransport(codec) as b,
    ):
        link = em.add_link(42)
        a.attach(4, link.paths[0])
        b.attach(1, link.paths[1])
        t0 = time.monotonic()
        assert a.send(4, KeepAlive(1))
        assert [r.frame for r in collect(b, 1, 5.0)] == [KeepAlive(1)]
        assert time.monotonic() - t0 >= 0.02  # latency applied
        em.undock(42)
        assert a.send(4, KeepAlive(2)) is True  # the send succeeds; the bytes go nowhere
        assert b.send(1, KeepAlive(3)) is True
        assert quiet(b, 0.2) == [] and quiet(a, 0.05) == []
        assert em.stats(42).bytes_discarded > 0
        em.dock(42)
        assert a.send(4, KeepAlive(4))
        assert [r.frame for r in collect(b, 1, 5.0)] == [KeepAlive(4)]


def test_for_topology_and_clean_shutdown() -> None:
    from dh2rt.topology import parse_spec

    before = threading.active_count()
    topo = parse_spec("snake:3")
    codec = contract_codec()
    em = LinkEmulator(seed=0)
    ports = em.for_topology(topo)
    assert len(ports) == 2 * len(topo.links)
    mods = [SerialTransport(codec) for _ in range(topo.size)]
    for (module, conn), path in ports.items():
        mods[module].attach(conn, path)
    assert mods[0].send(2, Hormone("X", ("A",)))
    got = collect(mods[1], 1, 5.0)
    assert [(r.at, r.remote) for r in got] == [(1, 2)]
    for m in mods:
        m.close()
    em.close()
    em.close()
    deadline = time.monotonic() + 2
    while threading.active_count() > before and time.monotonic() < deadline:
        time.sleep(0.02)
    assert threading.active_count() == before


@pytest.mark.parametrize("baud", [9600, 57600, 115200])
def test_a_paced_link_carries_bytes_at_its_baud_rate(baud: int) -> None:
    """Frames written at once cross one byte after another: the last arrives no sooner than
    the line could carry them all (10 bits a byte), and not much later."""
    codec = contract_codec()
    frames = [_long(i) for i in range(40)]
    with LinkEmulator(baudrate=baud, seed=3) as em, SerialTransport(codec) as a, SerialTransport(codec) as b:
        link = em.add_link(7)
        a.attach(1, link.paths[0])
        b.attach(1, link.paths[1])
        t0 = time.monotonic()
        for h in frames:
            assert a.send(1, h)
        got = collect(b, len(frames), 30.0)
        took = time.monotonic() - t0
        line = em.stats(7).bytes_relayed * 10 / baud
    assert [r.frame for r in got] == frames
    assert took >= 0.95 * line, (took, line)
    assert took <= line + 0.5, (took, line)
