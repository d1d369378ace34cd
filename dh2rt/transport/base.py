"""The transport abstraction: one module's view of its links.

A :class:`Transport` belongs to one module. It knows which of the module's connectors are
*attached* to a link end and moves encoded frames (:mod:`dh2rt.wire.frame`) across them. It
never names a module: it speaks connectors, and the medium-specific link end (a CAN link id
and side, a serial port) is set by whoever plays the physical world.

Using one (the module runtime's loop)::

    codec = FrameCodec(program.vocabulary, CONRO.connector_count)
    with open_transport("virtual", codec, channel="robot") as t:   # dh2rt.transport.registry
        t.attach(2, BusEnd(link_id=7, side=0))       # my back is docked on link 7
        while running:
            received = t.poll()      # hormones and beacons: dh2rt.runtime sorts them out
            for e in engine.step([Arrival(r.at, r.remote, r.frame) for r in received if isinstance(r.frame, Hormone)]):
                if not t.send(e.through, e.hormone):        # False: nothing attached there
                    status[e.through] = 0
            t.send(2, KeepAlive(seq))                       # liveness beacon

The contract (``dh2rt.testing`` checks it on every backend):

* ``send(through, frame)`` returns False, and counts ``send_failed``, when ``through`` is not
  attached or the medium refuses the write; otherwise it returns True and counts ``sent``.
  True does not mean the peer got it: an undocked or silent peer is found by liveness
  (keep-alives), not by the send.
* ``poll(timeout)`` returns every frame received since the last call as
  :class:`Received` ``(at, remote, frame)``: ``at`` is my connector, ``remote`` the
  connector the neighbour sent through (from the frame header). It waits up to ``timeout``
  seconds for the first frame, never longer. Frames on one link keep their order.
* Bytes that do not decode are counted in ``corrupted`` and never delivered; frames lost
  inside the transport (broken segment trains, oversize, arriving at a detached connector)
  are counted in ``dropped``.
* ``detach(connector)`` stops both directions at once; sending through it then fails.
* ``close()`` detaches everything and is idempotent; every transport is a context manager.
  After close, send returns False and poll returns nothing.

A transport is driven by one thread (the module's loop). Backends may run reader threads
internally, but the public methods are not meant to be called concurrently.

Writing a backend: subclass :class:`Transport`, set ``name``, and override the small hooks
``_attach``, ``_detach``, ``_transmit``, ``_receive`` and ``_close`` (and ``_medium_counts``
if the medium counts bad frames itself). The base class owns validation, counting, decoding
and the open/closed state; register the class in :mod:`dh2rt.transport.registry`.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import ClassVar, NamedTuple

from dh2rt.closing import Closing
from dh2rt.errors import CodecError, TransportError
from dh2rt.wire.frame import TRANSFER_FAMILY, Frame, FrameCodec


@dataclass(frozen=True, slots=True)
class BusEnd:
    """One end of a link on a shared medium (in-process bus, CAN): link id and side 0 or 1.

    The world numbers links; the two modules of a docked pair take opposite sides.
    """

    link_id: int
    side: int

    def __post_init__(self) -> None:
        if self.side not in (0, 1):
            raise TransportError(f"link end side {self.side!r} must be 0 or 1")
        if isinstance(self.link_id, bool) or not isinstance(self.link_id, int) or self.link_id < 0:
            raise TransportError(f"link id {self.link_id!r} must be a non-negative integer")


@dataclass(frozen=True, slots=True)
class PortEnd:
    """One end of a point-to-point serial link: a device path or any pyserial URL."""

    url: str
    baudrate: int = 115200


#: What a connector is attached to.
LinkEnd = BusEnd | PortEnd


class Received(NamedTuple):
    """A frame as a transport delivers it: my connector, the sender's connector, the frame."""

    at: int
    remote: int
    frame: Frame


@dataclass(frozen=True, slots=True)
class LinkCounters:
    """Totals since the transport opened."""

    sent: int = 0
    received: int = 0
    dropped: int = 0
    corrupted: int = 0
    send_failed: int = 0


class Transport(Closing, ABC):
    """A module's links over one medium. See the module docstring for the contract."""

    #: The registry name of the backend.
    name: ClassVar[str] = "abstract"
    #: Whether a module should take frames in as they arrive between its cycles (True), or
    #: sleep to its next cycle and read them all then (False). Reading as they come keeps
    #: arrival times exact; it costs a wake-up per frame, which is cheap on point-to-point
    #: links (a module's own few frames a cycle) and dear on a shared bus with no filter in
    #: the kernel, where every module's frames wake every module.
    read_between_cycles: ClassVar[bool] = True

    def __init__(self, codec: FrameCodec) -> None:
        self.codec = codec
        self._links: dict[int, LinkEnd] = {}
        self._closed = False
        self._sent = 0
        self._received = 0
        self._dropped = 0
        self._corrupted = 0
        self._send_failed = 0
        #: Where transfer frames (:mod:`dh2rt.wire.transfer`, a second frame family: byte 0's
        #: top bits 2) go as they are polled: ``(connector, payload)``, before any link-frame
        #: decoding (None: they are counted corrupted, as any frame this codec cannot read).
        self.on_transfer: Callable[[int, bytes, float], None] | None = None
        #: The clock arrivals are stamped on (the module runtime sets its own): a transfer
        #: frame goes to ``on_transfer`` with the instant it arrived, which may be well before
        #: it was polled (a loop that sleeps between cycles, a frame read at the next cycle).
        self.clock: Callable[[], float] = time.monotonic

    # -- public API -------------------------------------------------------------------------

    @property
    def links(self) -> Mapping[int, LinkEnd]:
        """Attached connectors and their link ends."""
        return dict(self._links)

    @property
    def closed(self) -> bool:
        return self._closed

    def attach(self, connector: int, end: LinkEnd) -> None:
        """Attach ``connector`` to a link end, replacing whatever it was attached to."""
        self._check_open()
        if (
            isinstance(connector, bool)
            or not isinstance(connector, int)
            or not (1 <= connector <= self.codec.connector_count)
        ):
            raise TransportError(f"connector {connector!r} is outside 1..{self.codec.connector_count}")
        if connector in self._links:
            self.detach(connector)
        self._attach(connector, end)
        self._links[connector] = end

    def detach(self, connector: int) -> bool:
        """Detach ``connector``; returns whether it was attached."""
        end = self._links.pop(connector, None)
        if end is None:
            return False
        self._detach(connector, end)
        return True

    def send(self, through: int, frame: Frame) -> bool:
        """Send ``frame`` through connector ``through``; False if nothing is attached there.

        Raises HormoneError/FrameEncodeError for a frame that cannot be encoded (a local bug,
        not a link failure).
        """
        end = self._links.get(through)
        if self._closed or end is None:
            self._send_failed += 1
            return False
        payload = self.codec.encode(through, frame)
        if self._transmit(through, end, payload):
            self._sent += 1
            return True
        self._send_failed += 1
        return False

    def send_raw(self, through: int, payload: bytes) -> bool:
        """Send an already encoded frame (a transfer frame) through ``through``; counted as
        ``send`` counts. False if nothing is attached there or the medium refused it."""
        end = self._links.get(through)
        if self._closed or end is None:
            self._send_failed += 1
            return False
        if self._transmit(through, end, payload):
            self._sent += 1
            return True
        self._send_failed += 1
        return False

    def poll(self, timeout: float = 0.0) -> list[Received]:
        """Frames received since the last call; waits up to ``timeout`` s for the first one."""
        if self._closed:
            return []
        out: list[Received] = []
        for connector, payload, arrived in self._receive(max(0.0, timeout)):
            if connector not in self._links:
                self._dropped += 1  # raced with a detach
                continue
            if payload and payload[0] >> 6 == TRANSFER_FAMILY and self.on_transfer is not None:
                self._received += 1
                self.on_transfer(connector, payload, arrived)
                continue
            try:
                sender, frame = self.codec.decode(payload)
            except CodecError:
                self._corrupted += 1
                continue
            self._received += 1
            out.append(Received(connector, sender, frame))
        return out

    @property
    def counters(self) -> LinkCounters:
        """A snapshot of the frame counters."""
        dropped, corrupted = self._medium_counts()
        return LinkCounters(
            sent=self._sent,
            received=self._received,
            dropped=self._dropped + dropped,
            corrupted=self._corrupted + corrupted,
            send_failed=self._send_failed,
        )

    def close(self) -> None:
        """Detach every connector and release the medium; calling it again does nothing."""
        if self._closed:
            return
        for connector in list(self._links):
            self.detach(connector)
        self._closed = True
        self._close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else f"links={self._links}"
        return f"<{type(self).__name__} {state}>"

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError(f"{self.name} transport is closed")

    # -- backend hooks ----------------------------------------------------------------------

    @abstractmethod
    def _attach(self, connector: int, end: LinkEnd) -> None:
        """Start listening on ``end`` for ``connector``; raise TransportError if impossible."""

    @abstractmethod
    def _detach(self, connector: int, end: LinkEnd) -> None:
        """Stop listening and sending on ``end``; must not raise."""

    @abstractmethod
    def _transmit(self, connector: int, end: LinkEnd, payload: bytes) -> bool:
        """Put one encoded frame on the medium; False if the medium refused it."""

    @abstractmethod
    def _receive(self, timeout: float) -> list[tuple[int, bytes, float]]:
        """Whole payloads received, as ``(connector, payload, arrived)``; wait up to
        ``timeout`` s. ``arrived``: when the medium had it whole, on :attr:`clock`."""

    @abstractmethod
    def _close(self) -> None:
        """Release the medium (all connectors are already detached)."""

    def _medium_counts(self) -> tuple[int, int]:
        """``(dropped, corrupted)`` counted by the medium's own framing (CRC, segments)."""
        return 0, 0
