"""The connector-local channel: its framing, the emulated channel against a pty the test plays
the world on, and the UART/GPIO channel against a pty (the peer's infrared) and a value file
(the contact pin)."""

from __future__ import annotations

import fcntl
import os
import struct
import termios
import time
import tty
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dh2rt.errors import DriverConfigError, EncodeError, FrameCorrupted, TransportError
from dh2rt.wire.serial_framing import encode_serial
from drivers.connector_channel import (
    CONTACT,
    LOST,
    MAX_ENCODED_FRAME,
    MAX_HELD,
    MAX_MESSAGE,
    ConnectorChannels,
    ContactDebouncer,
    ContactFrame,
    ContactPin,
    DataFrame,
    LocalFrame,
    PtyConnectorChannel,
    QueryFrame,
    UartGpioConnectorChannel,
    decode_local,
    encode_local,
    local_decoder,
)

MATED = encode_local(ContactFrame(made=True, aligned=True))
APART = encode_local(ContactFrame(made=False, aligned=False))


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


class Pty:
    """A pty pair: the channel opens ``path``; the test writes and reads at ``master``."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)

    def waiting(self) -> int:
        """Bytes the channel's side has to read (the slave's input queue)."""
        raw = fcntl.ioctl(self.slave, termios.FIONREAD, b"\0\0\0\0")
        return int(struct.unpack("i", raw)[0])

    def to_channel(self, data: bytes) -> None:
        """Write ``data`` towards the channel and wait until it can be read there."""
        before = self.waiting()
        os.write(self.master, data)
        deadline = time.monotonic() + 2.0
        while self.waiting() < before + len(data):
            assert time.monotonic() < deadline, "the pty never delivered the bytes"
            time.sleep(0.001)

    def from_channel(self, size: int, timeout: float = 2.0) -> bytes:
        """At least ``size`` bytes the channel wrote, or what came within ``timeout``."""
        out = b""
        deadline = time.monotonic() + timeout
        while len(out) < size and time.monotonic() < deadline:
            try:
                out += os.read(self.master, 4096)
            except BlockingIOError:
                time.sleep(0.001)
        return out

    def frames_from_channel(self, count: int, timeout: float = 2.0) -> list[object]:
        """The next ``count`` frames the channel wrote (fewer if they do not come in time)."""
        decoder = local_decoder()
        out: list[object] = []
        deadline = time.monotonic() + timeout
        while len(out) < count and time.monotonic() < deadline:
            out += [decode_local(p) for p in decoder.feed(self.from_channel(1, timeout=0.01))]
        return out

    def close(self) -> None:
        for fd in (self.master, self.slave):
            os.close(fd)


@pytest.fixture
def pty() -> Iterator[Pty]:
    p = Pty()
    yield p
    p.close()


def frames(wire: bytes) -> list[object]:
    return [decode_local(p) for p in local_decoder().feed(wire)]


# -- framing --------------------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(st.binary(min_size=1, max_size=MAX_MESSAGE), st.integers(1, 5))
def test_data_frames_round_trip_in_any_chunks(data: bytes, chunk: int) -> None:
    wire = encode_local(DataFrame(data))
    assert wire.count(0) == 1 and wire[-1] == 0 and len(wire) - 1 <= MAX_ENCODED_FRAME
    decoder = local_decoder()
    got = [p for i in range(0, len(wire), chunk) for p in decoder.feed(wire[i : i + chunk])]
    assert [decode_local(p) for p in got] == [DataFrame(data)]


def test_contact_and_query_frames_round_trip() -> None:
    contacts = [ContactFrame(m, a) for m in (False, True) for a in (False, True)]
    every: list[LocalFrame] = [*contacts, QueryFrame()]
    assert frames(b"".join(encode_local(f) for f in every)) == every
    assert [f.mated for f in contacts] == [False, False, False, True]
    assert encode_serial(b"C\x03") == MATED  # kind "C", flags made|aligned: the documented bytes


def test_the_longest_frame_is_fifteen_bytes_on_the_wire() -> None:
    assert len(encode_local(DataFrame(b"\xff" * MAX_MESSAGE))) == MAX_ENCODED_FRAME + 1 == 15


@pytest.mark.parametrize(
    "payload",
    [b"D", b"D" + bytes(9), b"C", b"C\x04", b"C\x01\x02", b"Q\x00", b"X\x01", b"\x00"],
    ids=["data-empty", "data-9", "contact-empty", "contact-bit-2", "contact-long", "query-body", "kind-X", "kind-0"],
)
def test_malformed_payloads_are_refused(payload: bytes) -> None:
    with pytest.raises(FrameCorrupted):
        decode_local(payload)


@pytest.mark.parametrize("data", [b"", b"123456789", bytes(64)])
def test_messages_of_0_or_more_than_8_bytes_cannot_be_encoded(data: bytes) -> None:
    with pytest.raises(EncodeError, match="1 to 8 bytes"):
        encode_local(DataFrame(data))


# -- the debouncer --------------------------------------------------------------------------


def test_a_reading_counts_once_it_has_held_for_the_settle_time() -> None:
    d = ContactDebouncer(settle=0.02)
    assert d.update(True, 0.000) is None
    assert d.update(True, 0.019) is None and not d.stable
    assert d.update(True, 0.020) is True and d.stable
    assert d.update(False, 0.030) is None  # a bounce...
    assert d.update(True, 0.035) is None  # ...that ends before it settles changes nothing
    assert d.update(True, 0.100) is None and d.stable
    assert d.update(False, 0.200) is None
    assert d.update(False, 0.221) is False and not d.stable
    assert d.force(False) is None and d.force(True) is True


def test_a_zero_settle_time_takes_every_reading_and_a_negative_one_is_refused() -> None:
    d = ContactDebouncer(settle=0)
    assert [d.update(r, 1.0) for r in (True, False, True)] == [True, False, True]
    with pytest.raises(DriverConfigError, match="settle"):
        ContactDebouncer(settle=-0.1)
    with pytest.raises(DriverConfigError, match="settle"):
        ContactDebouncer(settle=float("nan"))


# -- the emulated channel, with the test as the world ----------------------------------------


def test_the_channel_asks_for_its_contact_then_follows_contact_and_data(pty: Pty) -> None:
    with PtyConnectorChannel(pty.path, settle=0) as ch:
        assert pty.frames_from_channel(1) == [QueryFrame()]  # asked on opening
        assert not ch.contact and ch.poll() == []
        pty.to_channel(MATED + encode_local(DataFrame(b"\x00hi\x00")))
        assert ch.poll() == [CONTACT, b"\x00hi\x00"] and ch.contact
        assert ch.send(b"\x01\x02") is True
        assert pty.frames_from_channel(1) == [DataFrame(b"\x01\x02")]
        pty.to_channel(encode_local(DataFrame(b"a")) + APART + encode_local(DataFrame(b"b")))
        assert ch.receive() == [b"a"] and not ch.contact  # "b" came after the contact ended
        assert ch.counters.sent == 1 and ch.counters.received == 2 and ch.counters.stray == 1
        assert ch.counters.corrupted == 0 and ch.failure is None


def test_more_than_8_bytes_are_refused_and_nothing_is_written(pty: Pty) -> None:
    with PtyConnectorChannel(pty.path, settle=0) as ch:
        assert pty.frames_from_channel(1) == [QueryFrame()]
        with pytest.raises(EncodeError, match="9 bytes"):
            ch.send(b"123456789")
        with pytest.raises(EncodeError, match="must be bytes"):
            ch.send("text")  # type: ignore[arg-type]
        assert pty.from_channel(1, timeout=0.1) == b""
        assert ch.counters.sent == 0 and ch.counters.send_failed == 0


def test_garbage_and_corrupt_frames_are_dropped_counted_and_resynchronised(pty: Pty) -> None:
    good = encode_local(DataFrame(b"ok"))
    bad_crc = bytearray(good)
    bad_crc[2] ^= 0x10
    with PtyConnectorChannel(pty.path, settle=0) as ch:
        pty.to_channel(MATED)
        assert ch.poll() == [CONTACT]
        pty.to_channel(b"\x01\x02\x03\x00")  # noise ending in a delimiter
        pty.to_channel(bytes(bad_crc))  # a bit flipped
        pty.to_channel(b"\x55" * 40 + b"\x00")  # a long run without delimiter: over-long
        pty.to_channel(encode_serial(b"X12"))  # a valid CRC around an unknown kind
        pty.to_channel(encode_local(QueryFrame()))  # only the world answers queries
        pty.to_channel(b"\x7f\x7f" + good)  # noise glued in front of a good frame spoils it...
        pty.to_channel(good)  # ...and the next one gets through
        assert ch.poll() == [b"ok"]
        assert ch.counters.corrupted == 6 and ch.counters.received == 1 and ch.contact


def test_a_contact_settles_before_it_counts_and_holds_the_data_heard_meanwhile(pty: Pty) -> None:
    with PtyConnectorChannel(pty.path, settle=0.05) as ch:
        pty.to_channel(MATED + encode_local(DataFrame(b"early")))
        assert ch.poll(now=10.00) == [] and not ch.contact
        assert ch.poll(now=10.04) == []
        assert ch.poll(now=10.06) == [CONTACT, b"early"] and ch.contact  # the contact first
        pty.to_channel(APART + encode_local(DataFrame(b"late")))
        assert ch.poll(now=10.07) == [b"late"] and ch.contact  # still in contact while it settles
        assert ch.poll(now=10.11) == []
        assert ch.poll(now=10.13) == [LOST]
        # a touch that does not last: its data is never delivered
        pty.to_channel(MATED + encode_local(DataFrame(b"brief")) + APART)
        assert ch.poll(now=10.14) == [] and ch.poll(now=10.30) == []
        assert ch.counters.received == 2 and ch.counters.stray == 1


def test_no_more_than_max_held_messages_wait_for_a_settling_contact(pty: Pty) -> None:
    burst = [bytes([i]) for i in range(MAX_HELD + 4)]
    with PtyConnectorChannel(pty.path, settle=0.05) as ch:
        pty.to_channel(MATED + b"".join(encode_local(DataFrame(m)) for m in burst))
        assert ch.poll(now=5.0) == []
        assert ch.poll(now=5.1) == [CONTACT, *burst[:MAX_HELD]]
        assert ch.counters.received == MAX_HELD and ch.counters.stray == 4


def test_faces_that_touch_out_of_line_are_no_contact(pty: Pty) -> None:
    with PtyConnectorChannel(pty.path, settle=0) as ch:
        pty.to_channel(encode_local(ContactFrame(made=True, aligned=False)) + encode_local(DataFrame(b"x")))
        assert ch.poll() == [] and not ch.contact and ch.counters.stray == 1
        pty.to_channel(MATED)
        assert ch.poll() == [CONTACT]


def test_a_port_that_fails_reports_lost_once_and_refuses_sends() -> None:
    p = Pty()
    with PtyConnectorChannel(p.path, settle=0) as ch:
        p.to_channel(MATED)
        assert ch.poll() == [CONTACT]
        p.close()  # the world is gone: the slave reads EIO
        assert ch.poll() == [LOST] and not ch.contact
        assert ch.failure is not None and "read from" in ch.failure
        assert ch.poll() == []
        assert ch.send(b"x") is False and ch.counters.send_failed == 1


def test_a_pyserial_url_works_too_loop_hears_its_own_frames() -> None:
    with PtyConnectorChannel("loop://", settle=0) as ch:
        assert ch.send(b"echo") is True
        assert ch.poll() == []  # its own query (corrupted: a module never gets one) and its
        assert ch.counters.corrupted == 1 and ch.counters.stray == 1  # data, out of contact


def test_a_port_that_does_not_exist_is_a_transport_error() -> None:
    before = open_fds()
    with pytest.raises(TransportError, match="/nonexistent/tty"):
        PtyConnectorChannel("/nonexistent/tty")
    assert open_fds() == before


# -- a module's channels --------------------------------------------------------------------


def test_channels_poll_all_connectors_and_close_every_fd() -> None:
    ptys = {c: Pty() for c in (1, 2, 4)}
    before = open_fds()
    with ConnectorChannels.open_emulated({c: p.path for c, p in ptys.items()}, settle=0) as chans:
        assert chans.connectors == (1, 2, 4)
        ptys[4].to_channel(MATED + encode_local(DataFrame(b"four")))
        ptys[1].to_channel(MATED)
        assert chans.poll() == [(1, CONTACT), (4, CONTACT), (4, b"four")]
        assert chans.contacts() == {1: True, 2: False, 4: True}
        assert chans.send(1, b"one") is True
        assert ptys[1].frames_from_channel(2) == [QueryFrame(), DataFrame(b"one")]
        assert chans.counters()[4].received == 1 and chans.counters()[1].sent == 1
        assert chans.failures() == {}
        with pytest.raises(DriverConfigError, match="no connector channel 3"):
            chans.send(3, b"x")
    assert open_fds() == before
    for p in ptys.values():
        p.close()


def test_opening_channels_closes_those_opened_when_one_fails(pty: Pty) -> None:
    before = open_fds()
    with pytest.raises(TransportError):
        ConnectorChannels.open_emulated({1: pty.path, 2: "/nonexistent/tty"})
    assert open_fds() == before


# -- the hardware sketch: a UART (a pty: the peer's infrared) and a contact pin (a file) ----


@pytest.fixture
def pin(tmp_path: Path) -> Path:
    value = tmp_path / "value"
    value.write_text("1\n")  # pulled up: not mated
    return value


def test_uart_gpio_channel_senses_contact_on_the_pin_and_talks_over_the_uart(pty: Pty, pin: Path) -> None:
    with UartGpioConnectorChannel(pty.path, str(pin), settle=0.02) as ch:
        assert pty.from_channel(1, timeout=0.05) == b""  # no query on hardware
        pty.to_channel(encode_local(DataFrame(b"noise")))  # light from a neighbour, no contact
        assert ch.poll(now=1.0) == [] and ch.counters.stray == 1
        pin.write_text("0\n")  # the mating connector pulls the pin low
        assert ch.poll(now=1.01) == []
        pty.to_channel(encode_local(DataFrame(b"hello")))
        assert ch.poll(now=1.02) == []  # held while the contact settles
        assert ch.poll(now=1.04) == [CONTACT, b"hello"] and ch.contact
        assert ch.send(b"\x00\xff") is True
        assert pty.frames_from_channel(1) == [DataFrame(b"\x00\xff")]
        pty.to_channel(MATED)  # a CONTACT frame has no business on a UART
        assert ch.poll(now=1.05) == [] and ch.counters.corrupted == 1
        pin.write_text("1\n")
        assert ch.poll(now=1.06) == [] and ch.poll(now=1.09) == [LOST]


def test_uart_gpio_channel_with_an_active_high_callable_pin(pty: Pty) -> None:
    level = [False]
    with UartGpioConnectorChannel(pty.path, lambda: level[0], active_low=False, settle=0) as ch:
        assert ch.poll() == []
        level[0] = True
        assert ch.poll() == [CONTACT]


def test_a_pin_that_reads_nonsense_fails_the_channel(pty: Pty, pin: Path) -> None:
    with UartGpioConnectorChannel(pty.path, pin, settle=0) as ch:
        pin.write_text("0\n")
        assert ch.poll() == [CONTACT]
        pin.write_text("x\n")
        assert ch.poll() == [LOST] and ch.failure is not None and "not 0 or 1" in ch.failure
        assert ch.send(b"x") is False


def test_a_missing_pin_is_a_config_error_and_leaves_no_fd(pty: Pty, tmp_path: Path) -> None:
    before = open_fds()
    with pytest.raises(DriverConfigError, match="contact pin"):
        UartGpioConnectorChannel(pty.path, tmp_path / "absent")
    with pytest.raises(TransportError):
        UartGpioConnectorChannel("/nonexistent/tty", ContactPin(lambda: True))
    assert open_fds() == before


def test_close_releases_the_uart_and_the_pin(pty: Pty, pin: Path) -> None:
    before = open_fds()
    ch = UartGpioConnectorChannel(pty.path, pin)
    assert open_fds() > before
    ch.close()
    ch.close()
    assert open_fds() == before
    assert ch.poll() == [] and ch.send(b"x") is False
