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
* Frames of the other families are not returned: each goes, as it is polled, to the one
  handler registered for its family with ``listen(family, handler)`` (see :class:`FrameFamily`);
  a second registration for a family raises TransportError, and a frame of a family nobody
  listens for is counted in ``unhandled``. ``listen`` returns a :class:`Listening`: closing it
  unregisters the handler.
* ``detach(connector)`` stops both directions at once; sending through it then fails.
* ``close()`` detaches everything and is idempotent; every transport is a context manager.
  After close, send returns False and poll returns nothing.

A transport is driven by one thread (the module's loop). Backends may run reader threads
internally, but the public methods are not meant to be called concurrently.

Writing a backend: subclass :class:`Transport`, set ``name``, and override the small hooks
``_attach``, ``_detach``, ``_transmit``, ``_receive`` and ``_close`` (and ``_medium_counts``
if the medium counts bad frames itself, and ``families`` if it carries frames of its own, as
CAN's management channel). The base class owns validation, counting, decoding, dispatch by
family and the open/closed state; register the class in :mod:`dh2rt.transport.registry`.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import Enum
from typing import ClassVar, NamedTuple

from dh2rt.closing import Closing
from dh2rt.errors import CodecError, TransportError
from dh2rt.wire.frame import CONTROL_FAMILY, TRANSFER_FAMILY, Frame, FrameCodec


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


class FrameFamily(Enum):
    """The families one inbound stream splits into, each with its own consumer.

    :meth:`Transport.poll` splits the stream as python-can's ``Notifier`` hands messages to
    its listeners, but synchronously: a handler runs inside ``poll``, on the module's loop,
    so it needs no lock and sees its frames in the order they came. One handler a family,
    registered once (:meth:`Transport.listen`).

    * ``HORMONE``: the link frames (byte 0's top bits are the wire version: hormones, routed
      hormones, keep-alives, hellos). They stay what :meth:`Transport.poll` returns rather
      than a handler's: the module's cycle loop is their one consumer, it reads them when its
      cycle wants them, and a returned list keeps that pull (and its order with the cycle) in
      the loop's own code instead of a handler that would only append to a list.
    * ``TRANSFER``: flashing's frames (:mod:`dh2rt.wire.transfer`, top bits 2), for the rollout
      host or the cable's flasher, as they arrive.
    * ``CONTROL``: the operator's commands and the modules' answers (:mod:`dh2rt.wire.operator`,
      top bits 0), for the module's operator channel or the console's cable.
    * ``MANAGEMENT``: frames of the medium itself, on no link: CAN link negotiation's
      (:data:`dh2rt.wire.can_frames.MANAGEMENT_ID`), which only a CAN transport carries.
    """

    HORMONE = "hormone"
    TRANSFER = "transfer"
    CONTROL = "control"
    MANAGEMENT = "management"

    @classmethod
    def of_link_payload(cls, payload: bytes) -> FrameFamily:
        """The family of a payload that came in on a link, from byte 0's top two bits
        (anything else is read as a link frame, and counted corrupted if it does not decode
        as one: the old link version 1 among them)."""
        top = payload[0] >> 6 if payload else None
        if top == TRANSFER_FAMILY:
            return cls.TRANSFER
        return cls.CONTROL if top == CONTROL_FAMILY else cls.HORMONE


#: The connector of an :class:`Inbound` frame on no link (a management frame).
OFF_LINK = 0


class Inbound(NamedTuple):
    """A whole frame as it came off the medium, before decoding: its family, my connector it
    came in at (:data:`OFF_LINK` for a frame of the medium itself), its bytes, and when the
    medium had it whole, on :attr:`Transport.clock` (which may be well before it was polled:
    a loop that sleeps between cycles reads a frame at its next cycle)."""

    family: FrameFamily
    connector: int
    payload: bytes
    arrived: float

    @classmethod
    def on_link(cls, connector: int, payload: bytes, arrived: float) -> Inbound:
        """A frame that came in at ``connector``; its family read from its first byte."""
        return cls(FrameFamily.of_link_payload(payload), connector, payload, arrived)

    @property
    def on_a_link(self) -> bool:
        return self.connector != OFF_LINK


#: What takes the frames of one family, as they are polled.
Handler = Callable[[Inbound], None]


class Listening(Closing):
    """One handler's registration for one family (:meth:`Transport.listen`); closing it
    unregisters the handler, and closing it again does nothing."""

    def __init__(self, transport: Transport, family: FrameFamily, handler: Handler) -> None:
        self.transport = transport
        self.family = family
        self.handler = handler

    def close(self) -> None:
        self.transport._unlisten(self)

    def __repr__(self) -> str:
        return f"<Listening {self.family.value} -> {self.handler!r}>"


@dataclass(frozen=True, slots=True)
class LinkCounters:
    """Totals since the transport opened."""

    sent: int = 0
    received: int = 0
    dropped: int = 0
    corrupted: int = 0
    send_failed: int = 0
    #: frames of a family no handler listens for (:meth:`Transport.listen`), every family
    unhandled: int = 0


@dataclass(frozen=True, slots=True)
class HeldEnd:
    """One span in which a transport held a link end on a shared bus (wall-clock seconds, the
    clock python-can stamps frames with): from ``since`` (its attach, or the stamp of the
    first frame it took for it, if earlier) to ``until`` (its detach; None: held still).
    Frames sent to it within the span are this transport's to read; a witness on the bus
    counts those sent outside every span as lost (hil.bus_witness)."""

    link_id: int
    side: int
    since: float
    until: float | None


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
    #: The frame families the medium carries (:meth:`listen` refuses any other).
    families: ClassVar[frozenset[FrameFamily]] = frozenset(
        {FrameFamily.HORMONE, FrameFamily.TRANSFER, FrameFamily.CONTROL}
    )

    def __init__(self, codec: FrameCodec) -> None:
        self.codec = codec
        self._links: dict[int, LinkEnd] = {}
        self._closed = False
        self._sent = 0
        self._received = 0
        self._dropped = 0
        self._corrupted = 0
        self._send_failed = 0
        self._listening: dict[FrameFamily, Listening] = {}
        self._unhandled: Counter[FrameFamily] = Counter()
        #: The clock arrivals are stamped on (the module runtime sets its own): a handler is
        #: given the instant a frame arrived (:attr:`Inbound.arrived`).
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

    def listen(self, family: FrameFamily, handler: Handler) -> Listening:
        """From now on hand every frame of ``family`` to ``handler`` as it is polled (see
        :class:`FrameFamily`); close the returned :class:`Listening` to stop.

        Raises TransportError for a second handler of the same family (close the first one
        before), for the hormone family (:meth:`poll` returns those), and for a family this
        medium does not carry.
        """
        if family is FrameFamily.HORMONE:
            raise TransportError("hormone-family frames are what poll() returns; no handler takes them")
        if family not in self.families:
            raise TransportError(f"the {self.name} transport carries no {family.value} frames")
        holder = self._listening.get(family)
        if holder is not None:
            raise TransportError(f"{family.value} frames already go to {holder.handler!r}; close its Listening first")
        self._listening[family] = listening = Listening(self, family, handler)
        return listening

    def listens(self, family: FrameFamily) -> bool:
        """Whether a handler takes ``family``'s frames now."""
        return family in self._listening

    @property
    def unhandled(self) -> Mapping[FrameFamily, int]:
        """Frames of each family that came in while no handler listened for it."""
        return dict(self._unhandled)

    def _unlisten(self, listening: Listening) -> None:
        if self._listening.get(listening.family) is listening:
            del self._listening[listening.family]

    def poll(self, timeout: float = 0.0) -> list[Received]:
        """Link frames received since the last call; waits up to ``timeout`` s for the first
        frame. Frames of the other families go to their handlers meanwhile, in order."""
        if self._closed:
            return []
        out: list[Received] = []
        for inbound in self._receive(max(0.0, timeout)):
            if inbound.on_a_link and inbound.connector not in self._links:
                self._dropped += 1  # raced with a detach
                continue
            if inbound.family is FrameFamily.HORMONE:
                try:
                    sender, frame = self.codec.decode(inbound.payload)
                except CodecError:
                    self._corrupted += 1
                    continue
                self._received += 1
                out.append(Received(inbound.connector, sender, frame))
                continue
            listening = self._listening.get(inbound.family)
            if listening is None:
                self._unhandled[inbound.family] += 1
                continue
            if inbound.on_a_link:  # the medium's own frames are no link's traffic
                self._received += 1
            listening.handler(inbound)
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
            unhandled=self._unhandled.total(),
        )

    def held_ends(self) -> list[HeldEnd]:
        """The link ends this transport held on a shared bus, and when; [] elsewhere (a
        point-to-point medium has its own witness: the link emulator)."""
        return []

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
    def _receive(self, timeout: float) -> list[Inbound]:
        """Whole frames received (:meth:`Inbound.on_link` for a link's); wait up to
        ``timeout`` s."""

    @abstractmethod
    def _close(self) -> None:
        """Release the medium (all connectors are already detached)."""

    def _medium_counts(self) -> tuple[int, int]:
        """``(dropped, corrupted)`` counted by the medium's own framing (CRC, segments)."""
        return 0, 0
