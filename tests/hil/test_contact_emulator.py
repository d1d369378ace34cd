"""The contact emulator with module-side channels opened by real pyserial on its ptys."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterator

import pytest

from dh2rt.errors import ContactEmulatorError
from drivers.connector_channel import CONTACT, DEFAULT_SETTLE, LOST, LocalEvent, PtyConnectorChannel
from hil.contact_emulator import ContactEmulator, End

A: End = (0, 2)  # module 0's back connector
B: End = (1, 1)  # module 1's front connector
C: End = (2, 1)  # module 2's front connector, touching nothing


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


class Module:
    """One connector's channel, with every event it reported so far."""

    def __init__(self, em: ContactEmulator, end: End, settle: float = 0.0) -> None:
        self.channel = PtyConnectorChannel(em.add_connector(*end), settle=settle)
        self.events: list[LocalEvent] = []

    def poll(self) -> list[LocalEvent]:
        new = self.channel.poll()
        self.events += new
        return new

    @property
    def data(self) -> list[bytes]:
        return [e for e in self.events if isinstance(e, bytes)]


def poll_until(modules: list[Module], done: Callable[[], bool], timeout: float = 3.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        for m in modules:
            m.poll()
        if done():
            return
        assert time.monotonic() < deadline, [m.events for m in modules]
        time.sleep(0.002)


def poll_for(modules: list[Module], seconds: float) -> None:
    """Keep polling for ``seconds`` (to show that nothing more arrives)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        for m in modules:
            m.poll()
        time.sleep(0.005)


@pytest.fixture
def em() -> Iterator[ContactEmulator]:
    with ContactEmulator(seed=7) as emulator:
        yield emulator


def test_contact_lets_bytes_flow_both_ways_and_break_stops_them(em: ContactEmulator) -> None:
    a, b, c = Module(em, A), Module(em, B), Module(em, C)
    try:
        em.make_contact(A, B)
        poll_until([a, b, c], lambda: a.events == [CONTACT] and b.events == [CONTACT])
        assert a.channel.contact and b.channel.contact and em.partner(A) == B
        assert a.channel.send(b"\x00from-a") and b.channel.send(b"from-b")
        poll_until([a, b, c], lambda: a.data == [b"from-b"] and b.data == [b"\x00from-a"])
        em.break_contact(A, B)
        poll_until([a, b, c], lambda: a.events[-1] == LOST and b.events[-1] == LOST)
        assert not a.channel.contact and not b.channel.contact and em.partner(A) is None
        assert a.channel.send(b"gone") and b.channel.send(b"gone")  # sent, but into nothing
        poll_until([a, b, c], lambda: em.stats(A).discarded == 1 and em.stats(B).discarded == 1)
        poll_for([a, b, c], 0.1)
        assert a.events == [CONTACT, b"from-b", LOST] and b.events == [CONTACT, b"\x00from-a", LOST]
        assert c.events == [] and c.channel.counters.stray == 0  # the third heard nothing at all
        assert em.stats(A).relayed == 1 and em.stats(A).data_frames == 2
    finally:
        for m in (a, b, c):
            m.channel.close()


def test_only_aligned_faces_are_in_contact(em: ContactEmulator) -> None:
    a, b = Module(em, A), Module(em, B)
    try:
        em.make_contact(A, B, aligned=False)
        poll_until([a, b], lambda: em.stats(A).contact_frames >= 2)  # the answer to its query too
        a.channel.send(b"askew")
        poll_until([a, b], lambda: em.stats(A).discarded == 1)
        poll_for([a, b], 0.05)
        assert a.events == [] and b.events == []
        em.make_contact(A, B, aligned=True)  # they slide into line
        poll_until([a, b], lambda: a.events == [CONTACT] and b.events == [CONTACT])
        a.channel.send(b"aligned")
        poll_until([a, b], lambda: b.data == [b"aligned"])
    finally:
        a.channel.close()
        b.channel.close()


def test_a_module_that_opens_its_port_in_contact_learns_it_at_once(em: ContactEmulator) -> None:
    path_a, path_b = em.add_connector(*A), em.add_connector(*B)
    em.make_contact(A, B)  # before either module runs: the pty flush on opening loses this
    with PtyConnectorChannel(path_a, settle=0) as a, PtyConnectorChannel(path_b, settle=0) as b:
        deadline = time.monotonic() + 3.0
        got: dict[str, list[LocalEvent]] = {"a": [], "b": []}
        while not (got["a"] and got["b"]):
            got["a"] += a.poll()
            got["b"] += b.poll()
            assert time.monotonic() < deadline, got
            time.sleep(0.002)
        assert got == {"a": [CONTACT], "b": [CONTACT]}
    # a restart: the same module opens the same port again and asks again
    with PtyConnectorChannel(path_a, settle=DEFAULT_SETTLE) as again:
        deadline = time.monotonic() + 3.0
        while not again.contact:
            again.poll()
            assert time.monotonic() < deadline
            time.sleep(0.005)


def test_twenty_connectors_in_ten_pairs_at_once(em: ContactEmulator) -> None:
    pairs = [((2 * i, 2), (2 * i + 1, 1)) for i in range(10)]
    modules = {end: Module(em, end, settle=DEFAULT_SETTLE) for pair in pairs for end in pair}
    everyone = list(modules.values())
    try:
        for a, b in pairs:
            em.make_contact(a, b)
        poll_until(everyone, lambda: all(m.channel.contact for m in everyone))
        for end, m in modules.items():
            assert m.channel.send(bytes([end[0], end[1]]) + b"hi")
        poll_until(everyone, lambda: all(m.data for m in everyone))
        poll_for(everyone, 0.05)
        for a, b in pairs:
            assert modules[a].data == [bytes([b[0], b[1]]) + b"hi"]
            assert modules[b].data == [bytes([a[0], a[1]]) + b"hi"]
        for a, b in pairs[::2]:
            em.break_contact(a, b)
        poll_until(everyone, lambda: sum(m.channel.contact for m in everyone) == 10)
        assert [modules[a].channel.contact for a, _ in pairs] == [i % 2 == 1 for i in range(10)]
    finally:
        for m in everyone:
            m.channel.close()


def run_impaired(seed: int) -> tuple[list[bytes], int, int, int]:
    """200 messages from A to B over a lossy, noisy contact: what B got, and the counts."""
    with ContactEmulator(frame_loss=0.2, bit_error=0.005, seed=seed) as em:
        a, b = Module(em, A), Module(em, B)
        try:
            em.make_contact(A, B)
            poll_until([a, b], lambda: a.channel.contact and b.channel.contact)
            sent = [i.to_bytes(2, "big") + b"msg" for i in range(200)]
            for i, message in enumerate(sent):
                assert a.channel.send(message)
                if i % 20 == 19:
                    poll_for([a, b], 0.01)  # a pty holds only a few kB
            poll_until([a, b], lambda: em.stats(A).data_frames == len(sent))
            poll_for([a, b], 0.1)
            stats = em.stats(A)
            assert stats.lost + stats.relayed == len(sent)
            assert b.channel.counters.received + b.channel.counters.corrupted >= stats.relayed - stats.bits_flipped
            # nothing corrupted got in: every delivery is a message sent, in the order sent
            positions = [sent.index(m) for m in b.data]
            assert positions == sorted(set(positions))
            return b.data, stats.lost, stats.bits_flipped, b.channel.counters.corrupted
        finally:
            a.channel.close()
            b.channel.close()


def test_impairments_lose_and_garble_frames_the_same_way_for_the_same_seed() -> None:
    first = run_impaired(seed=42)
    got, lost, flipped, corrupted = first
    assert lost > 0 and flipped > 0 and corrupted > 0
    assert 0 < len(got) < 200 - lost
    # what the seed decides: which frames are lost and which bits flip, hence what gets
    # through; how many damaged frames the receiver has counted when the test looks also
    # depends on how far it has read (a frame whose delimiter flipped waits for the next)
    again = run_impaired(seed=42)
    assert again[:3] == first[:3]
    assert run_impaired(seed=43)[:3] != first[:3]


def test_misuse_is_refused(em: ContactEmulator) -> None:
    for end in (A, B, C):
        em.add_connector(*end)
    with pytest.raises(ContactEmulatorError, match="already exists"):
        em.add_connector(*A)
    with pytest.raises(ContactEmulatorError, match="no connector"):
        em.make_contact(A, (9, 9))
    with pytest.raises(ContactEmulatorError, match="itself"):
        em.make_contact(A, A)
    with pytest.raises(ContactEmulatorError, match="not in contact"):
        em.break_contact(A, B)
    em.make_contact(A, B)
    em.make_contact(A, B)  # the same contact again: nothing new
    assert em.stats(A).contact_frames == 1
    with pytest.raises(ContactEmulatorError, match=r"\(0, 2\) touches \(1, 1\)"):
        em.make_contact(C, A)
    with pytest.raises(ContactEmulatorError, match="not in contact"):
        em.break_contact(A, C)
    with pytest.raises(ValueError, match="frame_loss"):
        ContactEmulator(frame_loss=1.5)


def test_bad_frames_either_way_are_counted_and_dropped(em: ContactEmulator) -> None:
    a = Module(em, A)
    try:
        fd = os.open(em.path(A), os.O_WRONLY | os.O_NOCTTY)  # a second writer on the module's port
        try:
            os.write(fd, b"\x00" + b"\x05junk\x00" + bytes.fromhex("02430300"))
        finally:
            os.close(fd)
        poll_until([a], lambda: em.stats(A).malformed == 2)
        em.inject(A, b"\x01\x02\x00")  # and noise the other way, towards the module
        poll_until([a], lambda: a.channel.counters.corrupted == 1)
        assert a.events == []
    finally:
        a.channel.close()


def test_close_leaves_no_fd_and_no_thread() -> None:
    before = open_fds()
    em = ContactEmulator()
    modules = [Module(em, (m, c)) for m in range(3) for c in (1, 2)]
    em.make_contact((0, 1), (1, 2))
    for m in modules:
        m.channel.close()
    em.close()
    em.close()  # idempotent
    assert open_fds() == before
    assert not [t for t in threading.enumerate() if t.name == "dh2rt-contact-emulator"]
    with pytest.raises(ContactEmulatorError, match="closed"):
        em.add_connector(5, 1)
