"""The connector-local channel: contact sensed and a few bytes exchanged, connector to connector.

On a bus, which connector is docked to which is not visible on the wire, and DH2 allows no
global names. Each CONRO connector therefore has a local signal of its own (CONRO's had an
infrared pair): enough to sense contact and to exchange a few bytes with the connector it
touches. A :class:`ConnectorChannel` is that signal for one connector:

* :attr:`~ConnectorChannel.contact`: whether the connector is mated, debounced;
* :meth:`~ConnectorChannel.send`: one message of 1 to :data:`MAX_MESSAGE` bytes, best effort,
  never blocking (a message longer than that is refused with :class:`EncodeError`);
* :meth:`~ConnectorChannel.poll`: what happened since the last poll, in order: ``"contact"``,
  ``"lost"`` and the messages (``bytes``) the touching connector sent;
  :meth:`~ConnectorChannel.receive` returns only the messages;
* :attr:`~ConnectorChannel.counters`: messages sent, received, corrupted and stray.

The events of one channel keep one promise: a message is delivered only between a
``"contact"`` and the next ``"lost"``. A message heard while the contact is still settling is
held and delivered right after the ``"contact"``; one heard out of contact (infrared noise,
a neighbour's light) is dropped and counted as ``stray``.

:class:`ConnectorChannels` groups a module's channels by connector number and polls them all
at once, for a cycle loop that feeds a negotiator (``contact(connector, made)``,
``local_received(connector, bytes)``).

Two implementations share one framing (:func:`encode_local`, :func:`decode_local`: dh2rt's
serial framing, ``COBS(kind + body + CRC-32) + 0x00``, see ``docs/firmware.md``):

* :class:`PtyConnectorChannel`, the emulation: one pty (or pyserial URL) per connector whose
  other end the HIL world's contact emulator (``hil.contact_emulator``) drives from its
  physics, telling the module of contact in CONTACT frames and relaying DATA frames between
  touching connectors;
* :class:`UartGpioConnectorChannel`, the hardware: contact sensed on a GPIO input
  (:class:`ContactPin`), bytes over a UART wired to the connector's infrared pair.

pyserial is imported lazily, when a port opens.
"""

from __future__ import annotations

import abc
import contextlib
import math
import os
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, replace
from typing import Any, Final, Literal

from dh2rt.closing import Closing
from dh2rt.errors import (
    DriverConfigError,
    DriverError,
    EncodeError,
    FrameCorrupted,
    TransportError,
    TransportUnavailable,
)
from dh2rt.wire.serial_framing import SerialDecoder, encode_serial

# -- the framing ----------------------------------------------------------------------------

#: Largest message a connector sends to the one it touches.
MAX_MESSAGE: Final = 8
#: Frame kinds (first payload byte), ASCII so that a hex dump reads them.
KIND_CONTACT: Final = 0x43  # "C": world -> module, emulation only
KIND_DATA: Final = 0x44  # "D": either way
KIND_QUERY: Final = 0x51  # "Q": module -> world, emulation only
#: Bits of a CONTACT frame's flags byte.
FLAG_MADE: Final = 0x01
FLAG_ALIGNED: Final = 0x02
#: Longest encoded frame (without its delimiter): COBS(kind + 8 bytes + CRC-32).
MAX_ENCODED_FRAME: Final = len(encode_serial(bytes(1 + MAX_MESSAGE))) - 1
#: How long a contact reading must hold before it counts (seconds), unless told otherwise.
DEFAULT_SETTLE: Final = 0.02
#: Messages held while a contact settles; more are dropped as stray.
MAX_HELD: Final = 16
#: Bytes read from a port per poll at most (about 270 frames).
READ_CHUNK: Final = 4096

CONTACT: Final = "contact"
LOST: Final = "lost"
#: One thing a channel reports: contact made, contact lost, or a message from the touching connector.
LocalEvent = Literal["contact", "lost"] | bytes
#: One thing a module's channels report: ``(connector, event)``.
ConnectorEvent = tuple[int, LocalEvent]


@dataclass(frozen=True, slots=True)
class ContactFrame:
    """World -> module (emulation): the connector touches another (``made``) and lines up with it
    (``aligned``). Only both together are a contact: faces that touch out of line do not mate."""

    made: bool
    aligned: bool

    @property
    def mated(self) -> bool:
        return self.made and self.aligned


@dataclass(frozen=True, slots=True)
class DataFrame:
    """A message for (or from) the touching connector."""

    data: bytes


@dataclass(frozen=True, slots=True)
class QueryFrame:
    """Module -> world (emulation): "tell me my contact", sent when the port opens."""


LocalFrame = ContactFrame | DataFrame | QueryFrame


def check_message(data: bytes) -> bytes:
    """``data`` as bytes if it is a message a connector can send, else :class:`EncodeError`."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise EncodeError(f"connector message must be bytes, not {type(data).__name__}")
    data = bytes(data)
    if not 1 <= len(data) <= MAX_MESSAGE:
        raise EncodeError(f"connector message of {len(data)} bytes: a message has 1 to {MAX_MESSAGE} bytes")
    return data


def encode_local(frame: LocalFrame) -> bytes:
    """The wire bytes of ``frame``, delimiter included."""
    if isinstance(frame, DataFrame):
        payload = bytes([KIND_DATA]) + check_message(frame.data)
    elif isinstance(frame, ContactFrame):
        flags = (FLAG_MADE if frame.made else 0) | (FLAG_ALIGNED if frame.aligned else 0)
        payload = bytes([KIND_CONTACT, flags])
    else:
        payload = bytes([KIND_QUERY])
    return encode_serial(payload)


def decode_local(payload: bytes) -> LocalFrame:
    """The frame a decoded payload carries; :class:`FrameCorrupted` for an unknown kind or a
    body of the wrong length (the CRC held, so the sender is broken or speaks another version)."""
    kind, body = payload[0], payload[1:]
    if kind == KIND_DATA and 1 <= len(body) <= MAX_MESSAGE:
        return DataFrame(body)
    if kind == KIND_CONTACT and len(body) == 1 and not body[0] & ~(FLAG_MADE | FLAG_ALIGNED):
        return ContactFrame(bool(body[0] & FLAG_MADE), bool(body[0] & FLAG_ALIGNED))
    if kind == KIND_QUERY and not body:
        return QueryFrame()
    raise FrameCorrupted(f"connector frame of kind 0x{kind:02x} with {len(body)} body bytes")


def local_decoder() -> SerialDecoder:
    """An incremental decoder for connector frames: anything longer than the longest frame is
    dropped early (a line of noise never grows a buffer)."""
    return SerialDecoder(max_encoded=MAX_ENCODED_FRAME)


# -- the interface --------------------------------------------------------------------------


@dataclass(slots=True)
class ChannelCounters:
    """What one channel has done since it opened."""

    sent: int = 0  # messages written whole
    send_failed: int = 0  # messages the port refused or cut (full, failed, closed)
    received: int = 0  # messages delivered by poll() or receive()
    corrupted: int = 0  # frames dropped: bad COBS or CRC, over-long, unknown kind, wrong length
    stray: int = 0  # messages heard out of contact, or beyond MAX_HELD while it settled


class ConnectorChannel(Closing, abc.ABC):
    """One connector's local channel (see the module docs). Not thread-safe: one loop owns it."""

    counters: ChannelCounters
    #: Why the channel stopped working (port or pin failed), or None. A failed channel reports
    #: "lost" once if it was in contact, then nothing; its sends return False.
    failure: str | None = None

    @property
    @abc.abstractmethod
    def contact(self) -> bool:
        """Whether the connector is mated, debounced, as of the last :meth:`poll`."""

    @abc.abstractmethod
    def send(self, data: bytes) -> bool:
        """Send one message (1 to MAX_MESSAGE bytes, else :class:`EncodeError`) to the touching
        connector, without blocking; True if the port took the whole frame."""

    @abc.abstractmethod
    def poll(self, now: float | None = None) -> list[LocalEvent]:
        """Read what arrived and sample the contact, without blocking; the events in order.
        ``now`` is a ``time.monotonic()`` reading (taken when None)."""

    def receive(self) -> list[bytes]:
        """The messages that arrived, whole ones only (contact changes update :attr:`contact`)."""
        return [e for e in self.poll() if isinstance(e, bytes)]

    @abc.abstractmethod
    def close(self) -> None:
        """Release the port (and pin); idempotent."""


class ContactDebouncer:
    """A contact reading becomes the contact once it has held for ``settle`` seconds.

    ``raw`` is the last reading, ``stable`` the debounced state; :meth:`update` feeds a reading
    at a time and returns the new stable state when it changes (None otherwise). Call it with
    the last reading again to let time pass.
    """

    __slots__ = ("_since", "raw", "settle", "stable")

    def __init__(self, settle: float = DEFAULT_SETTLE) -> None:
        if not settle >= 0:
            raise DriverConfigError(f"contact settle time {settle} must be a non-negative number of seconds")
        self.settle = settle
        self.raw = False
        self.stable = False
        self._since = -math.inf

    def update(self, raw: bool, now: float) -> bool | None:
        if raw != self.raw:
            self.raw, self._since = raw, now
        if self.raw != self.stable and now - self._since >= self.settle:
            self.stable = self.raw
            return self.stable
        return None

    def force(self, raw: bool) -> bool | None:
        """Take ``raw`` at once (a failed port is no bounce); the change, if any."""
        self.raw = raw
        if self.stable == raw:
            return None
        self.stable = raw
        return raw


# -- the port -------------------------------------------------------------------------------


class _Port:
    """A pyserial port used without blocking: reads with ``timeout=0``; on a POSIX device the
    writes go to its non-blocking fd (pyserial's own write spins while the device is full),
    elsewhere (``loop://``, ``socket://``) through pyserial."""

    def __init__(self, url: str, baudrate: int) -> None:
        try:
            import serial
        except ImportError as exc:
            raise TransportUnavailable(
                f"the connector channel needs pyserial: pip install 'dh2rt[serial]' ({exc})"
            ) from None
        try:
            self._serial: Any = serial.serial_for_url(url, baudrate=baudrate, timeout=0, write_timeout=None)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportError(f"cannot open connector port {url!r}: {exc}") from exc
        self.url = url
        self.errors: tuple[type[BaseException], ...] = (serial.SerialException, OSError)
        self._fd: int | None = self._serial.fd if isinstance(self._serial, serial.Serial) else None

    def read(self) -> bytes:
        return bytes(self._serial.read(READ_CHUNK))

    def write(self, data: bytes) -> int:
        """Bytes written (0 when the device is full)."""
        if self._fd is None:
            n = self._serial.write(data)
            return len(data) if n is None else int(n)
        try:
            return os.write(self._fd, data)
        except BlockingIOError:
            return 0

    def close(self) -> None:
        with contextlib.suppress(Exception):  # closing a port whose device vanished must not raise
            self._serial.close()


class _SerialChannel(ConnectorChannel):
    """The framed channel over a port: decoding, debouncing, holding and counting. Subclasses
    say where the contact reading comes from (:meth:`_sample`, :meth:`_on_contact_frame`)."""

    def __init__(self, port: _Port, settle: float) -> None:
        self.counters = ChannelCounters()
        self.failure = None
        self._port = port
        self._decoder = local_decoder()
        self._debouncer = ContactDebouncer(settle)
        self._held: list[bytes] = []
        self._malformed = 0
        self._resync = True  # a delimiter before the first frame ends any noise the peer holds
        self._closed = False

    @property
    def contact(self) -> bool:
        return self._debouncer.stable

    @property
    def url(self) -> str:
        return self._port.url

    def send(self, data: bytes) -> bool:
        frame = encode_local(DataFrame(check_message(data)))
        if self._write(frame):
            self.counters.sent += 1
            return True
        self.counters.send_failed += 1
        return False

    def poll(self, now: float | None = None) -> list[LocalEvent]:
        now = time.monotonic() if now is None else now
        events: list[LocalEvent] = []
        if self.failure is None and not self._closed:
            self._sample(now, events)
            for payload in self._read_payloads():
                self._on_payload(payload, now, events)
            self._changed(self._debouncer.update(self._debouncer.raw, now), events)
        if self.failure is not None:
            self._changed(self._debouncer.force(False), events)
        return events

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._port.close()

    # -- hooks ---------------------------------------------------------------------------------

    def _sample(self, now: float, events: list[LocalEvent]) -> None:
        """Take a contact reading from outside the port, if this channel has one."""

    @abc.abstractmethod
    def _on_contact_frame(self, frame: ContactFrame, now: float, events: list[LocalEvent]) -> None:
        """A CONTACT frame arrived."""

    # -- shared machinery ----------------------------------------------------------------------

    def _contact_reading(self, raw: bool, now: float, events: list[LocalEvent]) -> None:
        self._changed(self._debouncer.update(raw, now), events)

    def _changed(self, change: bool | None, events: list[LocalEvent]) -> None:
        """Report a change of the debounced contact; release or drop the held messages."""
        if change is True:
            events.append(CONTACT)
            events.extend(self._held)
            self.counters.received += len(self._held)
            self._held.clear()
        elif change is False:
            events.append(LOST)
        if not self._debouncer.raw and self._held:  # the contact that was settling went away
            self.counters.stray += len(self._held)
            self._held.clear()

    def _read_payloads(self) -> Iterator[bytes]:
        try:
            data = self._port.read()
        except self._port.errors as exc:
            self._fail(f"read from {self._port.url}: {exc}")
            return
        yield from self._decoder.feed(data)
        self._count_corrupted()

    def _on_payload(self, payload: bytes, now: float, events: list[LocalEvent]) -> None:
        try:
            frame = decode_local(payload)
        except FrameCorrupted:
            frame = None
        if isinstance(frame, DataFrame):
            self._on_data(frame.data, events)
        elif isinstance(frame, ContactFrame):
            self._on_contact_frame(frame, now, events)
        else:  # undecodable, or a query (only the world answers those)
            self._malformed += 1
            self._count_corrupted()

    def _on_data(self, data: bytes, events: list[LocalEvent]) -> None:
        if self._debouncer.stable:
            events.append(data)
            self.counters.received += 1
        elif self._debouncer.raw and len(self._held) < MAX_HELD:
            self._held.append(data)
        else:
            self.counters.stray += 1

    def _count_corrupted(self) -> None:
        self.counters.corrupted = self._decoder.corrupted + self._decoder.dropped + self._malformed

    def _write(self, frame: bytes) -> bool:
        """Write one frame whole, or count it lost; after a frame cut short, the next one is
        preceded by a delimiter so that the peer's decoder drops only the cut one."""
        if self.failure is not None or self._closed:
            return False
        wire = b"\x00" + frame if self._resync else frame
        try:
            written = self._port.write(wire)
        except self._port.errors as exc:
            self._fail(f"write to {self._port.url}: {exc}")
            return False
        self._resync = written != len(wire)
        return not self._resync

    def _fail(self, reason: str) -> None:
        if self.failure is None:
            self.failure = reason
            self.counters.stray += len(self._held)
            self._held.clear()


class PtyConnectorChannel(_SerialChannel):
    """The emulated channel: a pty from the HIL world's contact emulator (or any pyserial URL).

    The world tells the module of its contact in CONTACT frames and relays DATA frames to and
    from the touching connector. On opening, the channel asks for its contact (a QUERY frame),
    so a module (re)started while docked learns it at once. A contact counts once its CONTACT
    frame has held ``settle`` seconds, as a pin's reading would.
    """

    def __init__(self, url: str, *, settle: float = DEFAULT_SETTLE, baudrate: int = 115200) -> None:
        port = _Port(url, baudrate)
        try:
            super().__init__(port, settle)
        except BaseException:
            port.close()
            raise
        self._write(encode_local(QueryFrame()))

    def _on_contact_frame(self, frame: ContactFrame, now: float, events: list[LocalEvent]) -> None:
        self._contact_reading(frame.mated, now, events)


# -- the hardware ---------------------------------------------------------------------------


class ContactPin(Closing):
    """A contact-sense input: a GPIO value file (sysfs ``/sys/class/gpio/gpioN/value``, or any
    file holding ``0`` or ``1``), or a callable returning the level (True = high), such as
    ``lambda: request.get_value(17) == gpiod.line.Value.ACTIVE`` with libgpiod v2 (a line
    configured ``active_low=True`` already says "mated": then pass ``active_low=False``).

    :meth:`read` gives whether the connector is mated: with ``active_low`` (the documented
    wiring: a pull-up that the mating connector pulls to ground), a low level is contact.
    """

    def __init__(self, source: str | os.PathLike[str] | Callable[[], bool], *, active_low: bool = True) -> None:
        self.active_low = active_low
        self._fd: int | None = None
        self._level_of: Callable[[], bool]
        if callable(source):
            self._level_of = source
            self.name = getattr(source, "__name__", repr(source))
            return
        self.name = os.fspath(source)
        try:
            self._fd = os.open(self.name, os.O_RDONLY)
        except OSError as exc:
            raise DriverConfigError(f"contact pin {self.name!r} cannot be opened: {exc}") from exc
        self._level_of = self._file_level

    def read(self) -> bool:
        """Whether the pin says "mated"; :class:`DriverError` if it cannot be read."""
        try:
            level = bool(self._level_of())
        except OSError as exc:
            raise DriverError(f"contact pin {self.name!r} cannot be read: {exc}") from exc
        return level != self.active_low

    def _file_level(self) -> bool:
        assert self._fd is not None
        text = os.pread(self._fd, 16, 0).strip()
        if text not in (b"0", b"1"):
            raise DriverError(f"contact pin {self.name!r} reads {text!r}, not 0 or 1")
        return text == b"1"

    def close(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None


class UartGpioConnectorChannel(_SerialChannel):
    """The hardware channel: contact on a GPIO input, bytes over a UART (``docs/firmware.md``,
    "The connector-local channel", has the wiring and the framing).

    The wiring, per connector of a Raspberry Pi-class board: the UART's TX drives the
    connector's IR LED through a transistor (lit for a 0 bit, dark when idle), its RX comes
    from a phototransistor facing the mating connector through a Schmitt trigger (high when
    dark), with an opaque wall so that the receiver never sees its own LED; the contact pin has
    a pull-up, and a pad that the mating connector's grounded pad pulls low when the faces are
    mated (hence ``active_low=True`` by default). A Pi 4 has four spare UARTs (``uart2`` ..
    ``uart5`` overlays), one per CONRO connector.

    ``uart`` is the UART's device (``/dev/ttyAMA1``, say; 8N1 at ``baudrate``); ``pin`` the
    contact-sense input: a :class:`ContactPin`, or what makes one (a value file path or a
    callable, with ``active_low``). The pin is sampled at each :meth:`poll` and the contact
    counts once a reading has held ``settle`` seconds, so the poll period (a module's cycle) is
    the sampling period. Only DATA frames cross the UART; anything else is counted as
    corrupted. The channel owns the pin and closes it.
    """

    def __init__(
        self,
        uart: str,
        pin: ContactPin | str | os.PathLike[str] | Callable[[], bool],
        *,
        active_low: bool = True,
        baudrate: int = 115200,
        settle: float = DEFAULT_SETTLE,
    ) -> None:
        self.pin = pin if isinstance(pin, ContactPin) else ContactPin(pin, active_low=active_low)
        try:
            super().__init__(_Port(uart, baudrate), settle)
        except BaseException:
            self.pin.close()
            raise

    def _sample(self, now: float, events: list[LocalEvent]) -> None:
        try:
            mated = self.pin.read()
        except DriverError as exc:
            self._fail(str(exc))
            return
        self._contact_reading(mated, now, events)

    def _on_contact_frame(self, frame: ContactFrame, now: float, events: list[LocalEvent]) -> None:
        self._malformed += 1  # the pin says contact here; a peer never sends CONTACT frames
        self._count_corrupted()

    def close(self) -> None:
        super().close()
        self.pin.close()


# -- a module's channels --------------------------------------------------------------------


class ConnectorChannels(Closing):
    """A module's channels by connector number, polled together by its cycle loop."""

    def __init__(self, channels: Mapping[int, ConnectorChannel]) -> None:
        self._channels = dict(sorted(channels.items()))

    @classmethod
    def open_emulated(cls, ports: Mapping[int, str], *, settle: float = DEFAULT_SETTLE) -> ConnectorChannels:
        """A :class:`PtyConnectorChannel` per ``connector -> port path`` (the contact emulator's
        paths); if one cannot open, those already open are closed again."""
        opened: dict[int, ConnectorChannel] = {}
        try:
            for connector, path in sorted(ports.items()):
                opened[connector] = PtyConnectorChannel(path, settle=settle)
        except BaseException:
            for channel in opened.values():
                channel.close()
            raise
        return cls(opened)

    @property
    def connectors(self) -> tuple[int, ...]:
        return tuple(self._channels)

    def __getitem__(self, connector: int) -> ConnectorChannel:
        try:
            return self._channels[connector]
        except KeyError:
            raise DriverConfigError(f"no connector channel {connector} (have {list(self._channels)})") from None

    def poll(self, now: float | None = None) -> list[ConnectorEvent]:
        """Every channel's events, connector by connector, each channel's in order."""
        now = time.monotonic() if now is None else now
        return [(c, event) for c, channel in self._channels.items() for event in channel.poll(now)]

    def send(self, connector: int, data: bytes) -> bool:
        return self[connector].send(data)

    def contacts(self) -> dict[int, bool]:
        return {c: channel.contact for c, channel in self._channels.items()}

    def counters(self) -> dict[int, ChannelCounters]:
        return {c: replace(channel.counters) for c, channel in self._channels.items()}

    def failures(self) -> dict[int, str]:
        return {c: ch.failure for c, ch in self._channels.items() if ch.failure is not None}

    def close(self) -> None:
        for channel in self._channels.values():
            channel.close()
