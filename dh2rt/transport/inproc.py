"""The in-process bus: a real transport with no dependencies, for tests and single-process runs.

An :class:`InprocBus` is the medium: it maps each link end ``(link_id, side)`` to the
transport listening there and hands encoded bytes across, in order. Buses are found by
channel name (like python-can's ``virtual``), or passed explicitly. The world can
``undock`` a link on the bus: frames on it then go nowhere, as on a real undocked pair.

The bus counts what no transport can: frames carried into nothing (``lost``: an undocked
link, or no transport at the other end, e.g. a stopped module's) and frames still in a
transport's inbox when it closed (``unread``), so that every frame sent is counted once.
"""

from __future__ import annotations

import threading
from collections import deque

from dh2rt.errors import TransportError
from dh2rt.transport.base import BusEnd, Inbound, LinkEnd, Transport
from dh2rt.wire.frame import FrameCodec


class InprocBus:
    """A shared in-process medium carrying encoded frames between link ends."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._listeners: dict[tuple[int, int], tuple[InprocTransport, int]] = {}
        self._undocked: set[int] = set()
        #: frames carried into nothing (undocked, or nobody at the other end)
        self.lost = 0
        #: frames left in a transport's inbox when it closed
        self.unread = 0

    def _join(self, end: BusEnd, transport: InprocTransport, connector: int) -> None:
        key = (end.link_id, end.side)
        with self._lock:
            holder = self._listeners.get(key)
            if holder is not None and holder[0] is not transport:
                raise TransportError(f"link {end.link_id} side {end.side} is already attached by another module")
            self._listeners[key] = (transport, connector)

    def _leave(self, end: BusEnd, transport: InprocTransport) -> None:
        key = (end.link_id, end.side)
        with self._lock:
            holder = self._listeners.get(key)
            if holder is not None and holder[0] is transport:
                del self._listeners[key]

    def carry(self, link_id: int, from_side: int, payload: bytes) -> None:
        """Deliver ``payload`` sent by ``from_side`` to the other end, if docked and listening."""
        with self._lock:  # delivered under the lock: a transport that left gets nothing more
            holder = None if link_id in self._undocked else self._listeners.get((link_id, 1 - from_side))
            if holder is None:
                self.lost += 1
                return
            holder[0]._deliver(holder[1], payload)

    def inject(self, link_id: int, to_side: int, data: bytes) -> None:
        """Put raw bytes on the medium towards ``to_side`` (tests: garbage, foreign frames)."""
        self.carry(link_id, 1 - to_side, bytes(data))

    def _unread(self, frames: int) -> None:
        with self._lock:
            self.unread += frames

    def undock(self, link_id: int) -> None:
        """Stop carrying frames on ``link_id`` (both directions)."""
        with self._lock:
            self._undocked.add(link_id)

    def dock(self, link_id: int) -> None:
        """Carry frames on ``link_id`` again."""
        with self._lock:
            self._undocked.discard(link_id)


_channels: dict[str, InprocBus] = {}
_channels_lock = threading.Lock()


def inproc_bus(channel: str) -> InprocBus:
    """The bus named ``channel`` in this process, created on first use."""
    with _channels_lock:
        bus = _channels.get(channel)
        if bus is None:
            bus = _channels[channel] = InprocBus()
        return bus


class InprocTransport(Transport):
    """A module's links on an :class:`InprocBus`; link ends are :class:`BusEnd`."""

    name = "inproc"

    def __init__(self, codec: FrameCodec, *, channel: str = "default", bus: InprocBus | None = None) -> None:
        super().__init__(codec)
        self.bus = bus if bus is not None else inproc_bus(channel)
        self._inbox: deque[Inbound] = deque()
        self._ready = threading.Condition()

    def _deliver(self, connector: int, payload: bytes) -> None:
        with self._ready:
            self._inbox.append(Inbound.on_link(connector, payload, self.clock()))
            self._ready.notify_all()

    def _attach(self, connector: int, end: LinkEnd) -> None:
        if not isinstance(end, BusEnd):
            raise TransportError(f"inproc connector {connector}: expected a BusEnd, got {end!r}")
        self.bus._join(end, self, connector)

    def _detach(self, connector: int, end: LinkEnd) -> None:
        if isinstance(end, BusEnd):
            self.bus._leave(end, self)

    def _transmit(self, connector: int, end: LinkEnd, payload: bytes) -> bool:
        assert isinstance(end, BusEnd)
        self.bus.carry(end.link_id, end.side, payload)
        return True

    def _receive(self, timeout: float) -> list[Inbound]:
        with self._ready:
            if not self._inbox and timeout > 0:
                self._ready.wait(timeout)
            out = list(self._inbox)
            self._inbox.clear()
        return out

    def _close(self) -> None:
        with self._ready:  # (the bus's lock is taken outside this one: carry() takes them the other way)
            left = len(self._inbox)
            self._inbox.clear()
        self.bus._unread(left)
