"""The CAN bus's witness (hil/bus_witness.py) and the spans a CAN transport holds its link
ends in (``Transport.held_ends``): every frame sent counted once by the end that sent it,
and those sent to an end while nobody held it told apart from those its holder was given.
Real parts: python-can's ``virtual`` bus, two module transports and the witness on one
channel."""

from __future__ import annotations

import time
from pathlib import Path

from dh2rt.compiler import compile_file
from dh2rt.transport.base import BusEnd
from dh2rt.transport.can_bus import VirtualCanTransport
from dh2rt.wire.frame import FrameCodec, KeepAlive
from hil.bus_witness import BusWitness, negotiated_end, spans_of

ROOT = Path(__file__).resolve().parents[2]
LINK = 4242


def _poll(transport: VirtualCanTransport, want: int) -> int:
    got = 0
    deadline = time.monotonic() + 2.0
    while got < want and time.monotonic() < deadline:
        got += len(transport.poll(0.05))
    return got


def test_the_witness_counts_each_frame_by_its_sender_and_the_spans_tell_lost_from_given() -> None:
    codec = FrameCodec(compile_file(str(ROOT / "examples" / "caterpillar.dh2")).vocabulary, 4)
    channel = f"witness-{id(codec):x}"
    witness = BusWitness("virtual", channel)
    a, b = VirtualCanTransport(codec, channel=channel), VirtualCanTransport(codec, channel=channel)
    try:
        a.attach(1, BusEnd(LINK, 0))
        a.send(1, KeepAlive(1))  # b does not hold its end yet: it reads this one before it attaches
        assert _poll(b, 1) == 0
        a.send(1, KeepAlive(2))  # waits in b's queue until b attached: b takes it, its span from then
        b.attach(2, BusEnd(LINK, 1))
        for seq in (3, 4):
            a.send(1, KeepAlive(seq))
        assert _poll(b, 3) == 3
        b.detach(2)
        a.send(1, KeepAlive(5))  # after b let go: lost
        (span,) = b.held_ends()
        assert (span.link_id, span.side) == (LINK, 1) and span.until is not None
        assert a.held_ends()[0].until is None  # a holds its end still
    finally:
        a.close()
        b.close()
        witness.close()
    assert witness.sent_from((LINK, 0)) == 5 == a.counters.sent
    assert witness.sent_to((LINK, 1), [(span.since, span.until)]) == 3 == b.counters.received
    assert witness.total() == 5 and witness.ends() == [(LINK, 0)]


def test_a_status_names_the_spans_and_a_log_line_the_end_negotiated() -> None:
    status = {"link_ends": [[7, 0, 1.0, 2.0], [8, 1, 1.5, None]], "link_ends_at": 3.0}
    assert spans_of(status) == [((7, 0), 1.0, 2.0), ((8, 1), 1.5, 3.0)]
    assert spans_of(status, until=1.8) == [((7, 0), 1.0, 1.8), ((8, 1), 1.5, 1.8)]  # killed at 1.8
    assert negotiated_end("link negotiated: connector 2 is link 8 side 1") == (8, 1)
    assert negotiated_end("link given up: connector 2") is None
