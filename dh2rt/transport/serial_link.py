"""Serial transport through pyserial: one point-to-point port per connector (infrared pairs).

Each attached connector opens its port (a device path such as a pty slave, or any pyserial
URL: ``loop://``, ``socket://host:port``, ``rfc2217://...``) and runs a
``serial.threaded.ReaderThread`` that feeds a :class:`~dh2rt.wire.serial_framing.SerialDecoder`.
Frames on the wire are ``COBS(payload + CRC16) + 0x00``; corrupted frames are counted by the
decoder and never delivered. pyserial is imported lazily, when a port opens.
"""

from __future__ import annotations

import contextlib
import queue
import threading
from typing import Any

from dh2rt.errors import TransportError, TransportUnavailable
from dh2rt.transport.base import LinkEnd, PortEnd, Transport
from dh2rt.wire.frame import FrameCodec
from dh2rt.wire.serial_framing import SerialDecoder, encode_serial


class _Port:
    """One open port: the pyserial object, its reader thread and its decoder."""

    def __init__(
        self,
        connector: int,
        end: PortEnd,
        inbox: queue.SimpleQueue[tuple[int, bytes]],
        write_timeout: float,
    ) -> None:
        try:
            import serial
            import serial.threaded
        except ImportError as exc:
            raise TransportUnavailable(
                f"the serial transport needs pyserial: pip install 'dh2rt[serial]' ({exc})"
            ) from None
        self.connector = connector
        self.decoder = SerialDecoder()
        self.lost: BaseException | None = None
        self._lock = threading.Lock()
        try:
            self.serial: Any = serial.serial_for_url(
                end.url, baudrate=end.baudrate, timeout=None, write_timeout=write_timeout
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportError(f"connector {connector}: cannot open serial port {end.url!r}: {exc}") from exc
        port = self

        class _Protocol(serial.threaded.Protocol):  # type: ignore[misc]
            def data_received(self, data: bytes) -> None:
                with port._lock:
                    payloads = port.decoder.feed(data)
                for p in payloads:
                    inbox.put((connector, p))

            def connection_lost(self, exc: BaseException | None) -> None:
                port.lost = exc

        self.reader: Any = serial.threaded.ReaderThread(self.serial, _Protocol)
        self.reader.name = f"dh2rt-serial-{connector}"
        self.reader.start()
        self._serial_error: type[BaseException] = serial.SerialException

    def write(self, data: bytes) -> bool:
        if self.lost is not None or not self.reader.alive:
            return False
        try:
            n = self.reader.write(data)
        except (self._serial_error, OSError):
            return False
        return n is None or n == len(data)

    def counts(self) -> tuple[int, int]:
        with self._lock:
            return self.decoder.dropped, self.decoder.corrupted

    def close(self) -> None:
        try:
            self.reader.close()
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
        self._inbox: queue.SimpleQueue[tuple[int, bytes]] = queue.SimpleQueue()
        self._gone_dropped = 0
        self._gone_corrupted = 0

    def attach(self, connector: int, end: LinkEnd | str) -> None:
        """Attach ``connector`` to a port; ``end`` may be a :class:`PortEnd` or a URL/path."""
        super().attach(connector, PortEnd(end) if isinstance(end, str) else end)

    def _attach(self, connector: int, end: LinkEnd) -> None:
        if not isinstance(end, PortEnd):
            raise TransportError(f"serial connector {connector}: expected a PortEnd or a port URL, got {end!r}")
        port = _Port(connector, end, self._inbox, self.write_timeout)
        # A delimiter first: it ends whatever partial frame the peer's decoder holds.
        port.write(b"\x00")
        self._ports[connector] = port

    def _detach(self, connector: int, end: LinkEnd) -> None:
        port = self._ports.pop(connector, None)
        if port is not None:
            port.close()
            dropped, corrupted = port.counts()
            self._gone_dropped += dropped
            self._gone_corrupted += corrupted

    def _transmit(self, connector: int, end: LinkEnd, payload: bytes) -> bool:
        return self._ports[connector].write(encode_serial(payload))

    def _receive(self, timeout: float) -> list[tuple[int, bytes]]:
        out: list[tuple[int, bytes]] = []
        try:
            out.append(self._inbox.get(timeout=timeout) if timeout > 0 else self._inbox.get_nowait())
        except queue.Empty:
            return out
        while True:
            try:
                out.append(self._inbox.get_nowait())
            except queue.Empty:
                return out

    def _medium_counts(self) -> tuple[int, int]:
        dropped, corrupted = self._gone_dropped, self._gone_corrupted
        for port in self._ports.values():
            d, c = port.counts()
            dropped += d
            corrupted += c
        return dropped, corrupted

    def _close(self) -> None:
        while True:
            try:
                self._inbox.get_nowait()
            except queue.Empty:
                return
