"""Serial transport through pyserial: one point-to-point port per connector (infrared pairs).

Each attached connector opens its port (a device path such as a pty slave, or any pyserial
URL: ``loop://``, ``socket://host:port``, ``rfc2217://...``) and feeds what it reads to a
:class:`~dh2rt.wire.serial_framing.SerialDecoder`. Frames on the wire are
``COBS(payload + CRC16) + 0x00``; corrupted frames are counted by the decoder and never
delivered. pyserial is imported lazily, when a port opens.

Reading takes no thread of its own: a port with a file descriptor (every POSIX device, and
``socket://``; pyserial's ``fileno()``) is read by the module's loop itself, in
:meth:`SerialTransport.poll`, which waits on the ports' descriptors with ``poll(2)``; what
arrived between two polls waits in the kernel's buffer (a tty holds 4 kB, 350 ms of a 115200
baud line, against a 20 ms cycle). Only a port without a descriptor (``loop://``,
``rfc2217://``) gets pyserial's ``ReaderThread``, which wakes the loop's wait through a pipe.
"""

from __future__ import annotations

import contextlib
import errno
import io
import math
import os
import queue
import select
import threading
import time
from typing import Any

from dh2rt.errors import TransportError, TransportUnavailable
from dh2rt.transport.base import Inbound, LinkEnd, PortEnd, Transport
from dh2rt.wire.frame import FrameCodec
from dh2rt.wire.serial_framing import SerialDecoder, encode_serial

#: Bytes one read takes from a port (a tty's whole buffer).
READ_CHUNK = 4096


class _Port:
    """One open port: the pyserial object and its decoder; read by the loop (``fd``) or, for
    a port with no descriptor, by a pyserial reader thread."""

    def __init__(self, connector: int, end: PortEnd, write_timeout: float) -> None:
        try:
            import serial
        except ImportError as exc:
            raise TransportUnavailable(
                f"the serial transport needs pyserial: pip install 'dh2rt[serial]' ({exc})"
            ) from None
        self.connector = connector
        self.decoder = SerialDecoder()
        self.lost: BaseException | None = None
        self._serial_error: type[BaseException] = serial.SerialException
        try:
            # timeout 0: a read takes what is there (the loop reads only what poll says is ready)
            self.serial: Any = serial.serial_for_url(
                end.url, baudrate=end.baudrate, timeout=0, write_timeout=write_timeout
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportError(f"connector {connector}: cannot open serial port {end.url!r}: {exc}") from exc
        self.fd: int | None = None
        with contextlib.suppress(AttributeError, OSError, ValueError, io.UnsupportedOperation):
            self.fd = int(self.serial.fileno())
        #: a plain POSIX port (a UART, a pty): read with os.read, no second select in pyserial
        self._raw = self.fd is not None and type(self.serial) is serial.Serial
        self.reader: Any = None
        self._lock = threading.Lock()

    def start_reader(self, inbox: queue.SimpleQueue[tuple[int, bytes]], wake: int) -> None:
        """For a port with no descriptor: pyserial's reader thread decodes what it reads into
        ``inbox`` and writes a byte to ``wake`` (the write end of the transport's pipe)."""
        import serial.threaded

        port = self

        class _Protocol(serial.threaded.Protocol):  # type: ignore[misc]
            def data_received(self, data: bytes) -> None:
                with port._lock:
                    payloads = port.decoder.feed(data)
                for p in payloads:
                    inbox.put((port.connector, p))
                if payloads:
                    with contextlib.suppress(OSError):  # full: the loop is awake anyway
                        os.write(wake, b"\0")

            def connection_lost(self, exc: BaseException | None) -> None:
                port.lost = exc if exc is not None else EOFError("reader stopped")

        self.serial.timeout = None  # the thread blocks in read (ReaderThread may set 1 s)
        self.reader = serial.threaded.ReaderThread(self.serial, _Protocol)
        self.reader.name = f"dh2rt-serial-{self.connector}"
        self.reader.start()

    def read(self) -> list[bytes]:
        """What the port holds now, decoded (the loop's read; the descriptor is ready)."""
        try:
            data = os.read(self.fd, READ_CHUNK) if self._raw else self.serial.read(READ_CHUNK)  # type: ignore[arg-type]
        except BlockingIOError:
            return []
        except (self._serial_error, OSError) as exc:
            # EIO: the device is gone (a pty whose master closed, an unplugged adapter)
            self.lost = exc
            return []
        if not data:
            if self._raw:  # ready but nothing to read: end of file
                self.lost = OSError(errno.EIO, "end of file")
            return []
        return self.decoder.feed(data)

    def write(self, data: bytes) -> bool:
        if self.lost is not None or (self.reader is not None and not self.reader.alive):
            return False
        try:
            # the reader thread's write takes its lock (it may be closing the port)
            n = self.reader.write(data) if self.reader is not None else self.serial.write(data)
        except (self._serial_error, OSError):
            return False
        return n is None or n == len(data)

    def counts(self) -> tuple[int, int]:
        with self._lock:
            return self.decoder.dropped, self.decoder.corrupted

    def close(self) -> None:
        try:
            if self.reader is not None:
                self.reader.close()
            else:
                self.serial.close()
        except Exception:  # closing a port whose device vanished must not raise
            with contextlib.suppress(Exception):
                self.serial.close()


class SerialTransport(Transport):
    """A module's links over serial ports; link ends are :class:`PortEnd` (or a URL string)."""

    name = "serial"

    def __init__(self, codec: FrameCodec, *, write_timeout: float = 0.5) -> None:
        super().__init__(codec)
        self.write_timeout = write_timeout
        self._ports: dict[int, _Port] = {}
        self._by_fd: dict[int, _Port] = {}
        self._poller = select.poll()
        #: ports read by a thread (no descriptor): their frames and the pipe that wakes poll
        self._inbox: queue.SimpleQueue[tuple[int, bytes]] = queue.SimpleQueue()
        self._wake: tuple[int, int] | None = None
        self._gone_dropped = 0
        self._gone_corrupted = 0

    def attach(self, connector: int, end: LinkEnd | str) -> None:
        """Attach ``connector`` to a port; ``end`` may be a :class:`PortEnd` or a URL/path."""
        super().attach(connector, PortEnd(end) if isinstance(end, str) else end)

    def _attach(self, connector: int, end: LinkEnd) -> None:
        if not isinstance(end, PortEnd):
            raise TransportError(f"serial connector {connector}: expected a PortEnd or a port URL, got {end!r}")
        port = _Port(connector, end, self.write_timeout)
        if port.fd is not None:
            self._by_fd[port.fd] = port
            self._poller.register(port.fd, select.POLLIN)
        else:
            if self._wake is None:
                self._wake = os.pipe()
                for fd in self._wake:
                    os.set_blocking(fd, False)
                self._poller.register(self._wake[0], select.POLLIN)
            port.start_reader(self._inbox, self._wake[1])
        # A delimiter first: it ends whatever partial frame the peer's decoder holds.
        port.write(b"\x00")
        self._ports[connector] = port

    def _detach(self, connector: int, end: LinkEnd) -> None:
        port = self._ports.pop(connector, None)
        if port is not None:
            self._forget_fd(port)
            port.close()
            dropped, corrupted = port.counts()
            self._gone_dropped += dropped
            self._gone_corrupted += corrupted

    def _forget_fd(self, port: _Port) -> None:
        if port.fd is not None and self._by_fd.get(port.fd) is port:
            del self._by_fd[port.fd]
            with contextlib.suppress(KeyError, ValueError):
                self._poller.unregister(port.fd)

    def _transmit(self, connector: int, end: LinkEnd, payload: bytes) -> bool:
        return self._ports[connector].write(encode_serial(payload))

    def _receive(self, timeout: float) -> list[Inbound]:
        out: list[Inbound] = []
        deadline: float | None = None
        wait_ms = 0
        while True:
            for fd, _events in self._poller.poll(wait_ms):
                port = self._by_fd.get(fd)
                if port is None:  # the wake pipe: the reader threads' frames are in the inbox
                    assert self._wake is not None
                    with contextlib.suppress(BlockingIOError):
                        os.read(self._wake[0], READ_CHUNK)
                    continue
                connector = port.connector
                arrived = self.clock()  # read as it came (read_between_cycles)
                out.extend(Inbound.on_link(connector, p, arrived) for p in port.read())
                if port.lost is not None:
                    self._forget_fd(port)  # a dead descriptor stays ready: never poll it again
            if self._wake is not None:
                with contextlib.suppress(queue.Empty):
                    while True:
                        connector, p = self._inbox.get_nowait()
                        out.append(Inbound.on_link(connector, p, self.clock()))
            if out or timeout <= 0:
                return out
            # nothing whole yet (or only part of a frame): wait for the rest of the timeout
            now = time.monotonic()
            if deadline is None:
                deadline = now + timeout
            elif now >= deadline:
                return out
            wait_ms = math.ceil((deadline - now) * 1000)

    def _medium_counts(self) -> tuple[int, int]:
        dropped, corrupted = self._gone_dropped, self._gone_corrupted
        for port in self._ports.values():
            d, c = port.counts()
            dropped += d
            corrupted += c
        return dropped, corrupted

    def _close(self) -> None:
        with contextlib.suppress(queue.Empty):
            while True:
                self._inbox.get_nowait()
        if self._wake is not None:
            for fd in self._wake:
                with contextlib.suppress(OSError):
                    os.close(fd)
            self._wake = None
