"""CAN transports through python-can: ``socketcan``, ``virtual`` and ``udp_multicast``.

One python-can bus per module; link ends are :class:`~dh2rt.transport.base.BusEnd`. The
arbitration id carries kind, segment marker, link id and the sending side
(:mod:`dh2rt.wire.can_frames`); the module listens only for the far side of its own links,
which also discards the module's own frames that ``udp_multicast`` echoes back. The frames
on the management channel (:data:`~dh2rt.wire.can_frames.MANAGEMENT_ID`, link negotiation's)
are on no link: they go to the transport's :attr:`~dh2rt.transport.base.FrameFamily.MANAGEMENT`
handler (``listen``), or are counted unhandled.

python-can is imported lazily, when a bus opens. Every ``can.Message`` is built with
``is_extended_id=True`` explicitly (python-can's default is not a contract to lean on).
"""

from __future__ import annotations

import socket
import time
from dataclasses import dataclass
from typing import Any, ClassVar

from dh2rt.errors import TransportError, TransportUnavailable
from dh2rt.transport.base import OFF_LINK, BusEnd, FrameFamily, HeldEnd, Inbound, LinkEnd, Transport
from dh2rt.wire.can_frames import (
    CLASSIC_DATA,
    FD_DATA,
    LINK_END_MASK,
    MANAGEMENT_ID,
    MAX_LINK_ID,
    Reassembler,
    Segmenter,
    listen_filter,
    make_arbitration_id,
)
from dh2rt.wire.frame import FrameCodec

#: The commands that create a virtual SocketCAN interface on a Linux host that has AF_CAN.
VCAN_SETUP = "sudo modprobe vcan; sudo ip link add dev vcan0 type vcan; sudo ip link set up vcan0"
#: Transports that need no SocketCAN.
FALLBACKS = (
    "inproc (one process), virtual (python-can, one process), "
    "udp (python-can udp_multicast, across processes), serial (pyserial ports)"
)


def socketcan_problem(channel: str) -> str | None:
    """Why SocketCAN interface ``channel`` cannot be opened here, or None if it can."""
    family = getattr(socket, "AF_CAN", None)
    if family is None:
        return "this Python has no socket.AF_CAN (SocketCAN exists only on Linux)"
    try:
        probe = socket.socket(family, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as exc:
        reason = exc.strerror or exc
        return f"the kernel has no AF_CAN sockets ({reason}; the can/can-raw modules are missing)"
    probe.close()
    try:
        socket.if_nametoindex(channel)
    except OSError:
        return f"there is no network interface named {channel!r}"
    return None


@dataclass(slots=True)
class _Span:
    """A span in which a transport held one of its link ends (see HeldEnd)."""

    since: float
    until: float | None = None


class CanTransport(Transport):
    """A module's links on one python-can bus, on any python-can ``interface`` (``slcan``,
    ``pcan``, ``kvaser``, ``gs_usb``, ...; the registry's ``can``); subclasses fix it
    (``virtual``, ``udp``, ``socketcan``). ``bus_options`` go to ``can.Bus`` as they are
    (``bitrate``, ``data_bitrate``, ...)."""

    name = "can"
    interface: str = "virtual"
    #: whether the interface filters in the kernel (set_filters costs nothing per frame)
    kernel_filters: ClassVar[bool] = False
    #: Without kernel filters every module's frames would wake every module between cycles.
    read_between_cycles: ClassVar[bool] = False
    default_channel: ClassVar[str] = "dh2rt"
    families = frozenset(FrameFamily)

    def __init__(
        self,
        codec: FrameCodec,
        *,
        channel: str | None = None,
        fd: bool = False,
        send_timeout: float = 0.2,
        interface: str | None = None,
        **bus_options: Any,
    ) -> None:
        super().__init__(codec)
        if interface is not None:
            if type(self) is not CanTransport and interface != self.interface:
                raise TransportError(f"the {self.name} transport is python-can's {self.interface}, not {interface!r}")
            self.interface = interface
        self.channel = channel or self.default_channel
        self.fd = fd
        self.send_timeout = send_timeout
        self.max_data = FD_DATA if fd else CLASSIC_DATA
        self._listen: dict[int, int] = {}  # low 19 bits of the far end's id -> my connector
        self._reassembler = Reassembler()
        #: my link ends (link id, side) and the spans I held them: [since, until] (see held_ends)
        self._held: dict[tuple[int, int], list[_Span]] = {}
        self._segmenter = Segmenter(self.max_data)  # numbers each link end's segment trains
        self._bus: Any = self._open_bus(bus_options)
        import can  # already imported by _open_bus; kept for exception and Message types

        self._can: Any = can
        self._apply_filters()

    def _open_bus(self, options: dict[str, Any]) -> Any:
        try:
            import can
        except ImportError as exc:
            raise TransportUnavailable(
                f"the {self.name} transport needs python-can: pip install 'dh2rt[can]' ({exc})"
            ) from None
        try:
            return can.Bus(interface=self.interface, channel=self.channel, fd=self.fd, **options)
        except (can.CanError, OSError, ImportError, ValueError) as exc:
            raise TransportUnavailable(
                f"cannot open python-can {self.interface} bus on channel {self.channel!r}: {exc}"
            ) from exc

    @property
    def bus(self) -> Any:
        """The underlying python-can bus (for tools; do not read from it)."""
        return self._bus

    def _apply_filters(self) -> None:
        # Only a kernel (SocketCAN) filters before python-can sees a frame. Elsewhere python-can
        # filters in software, and recv(timeout=0) then returns None at the first frame it
        # drops, leaving the frames behind it unread until the next wait: take every frame
        # and let _receive keep this module's (it checks every frame against _listen anyway).
        if not self.kernel_filters:
            return
        ends = [(k >> 1, k & 1) for k in self._listen]
        filters: list[dict[str, Any]] = [listen_filter(link, 1 - far_side) for link, far_side in ends]
        # the management channel always (its frames are rare): nobody listening, they are counted
        filters.append({"can_id": MANAGEMENT_ID, "can_mask": 0x1FFFFFFF, "extended": True})
        self._bus.set_filters(filters)

    # -- link negotiation's management frames (dh2rt.wire.negotiation) -------------------

    def send_management(self, arbitration_id: int, data: bytes) -> bool:
        """Send one management frame; False when the bus refused it."""
        can = self._can
        msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=True)
        try:
            self._bus.send(msg, timeout=self.send_timeout)
        except (can.CanError, OSError):
            return False
        return True

    def _attach(self, connector: int, end: LinkEnd) -> None:
        if not isinstance(end, BusEnd):
            raise TransportError(f"{self.name} connector {connector}: expected a BusEnd, got {end!r}")
        make_arbitration_id(0, 0, 0, end.link_id, end.side)  # validates the link id range
        far = (end.link_id << 1) | (1 - end.side)
        if far in self._listen:
            raise TransportError(
                f"link {end.link_id} side {end.side} is already attached to connector {self._listen[far]}"
            )
        self._listen[far] = connector
        self._held.setdefault((end.link_id, end.side), []).append(_Span(time.time()))
        self._apply_filters()

    def _detach(self, connector: int, end: LinkEnd) -> None:
        if isinstance(end, BusEnd):
            self._listen.pop((end.link_id << 1) | (1 - end.side), None)
            self._reassembler.forget(end.link_id, 1 - end.side)
            spans = self._held.get((end.link_id, end.side))
            if spans and spans[-1].until is None:
                spans[-1].until = time.time()
            if not self._closed:
                self._apply_filters()

    def _transmit(self, connector: int, end: LinkEnd, payload: bytes) -> bool:
        assert isinstance(end, BusEnd)
        can = self._can
        for fr in self._segmenter.segment(payload, end.link_id, end.side):
            msg = can.Message(
                arbitration_id=fr.arbitration_id,
                data=fr.data,
                is_extended_id=True,
                is_fd=self.fd,
                bitrate_switch=self.fd,
            )
            try:
                self._bus.send(msg, timeout=self.send_timeout)
            except (can.CanError, OSError):
                return False
        return True

    def _receive(self, timeout: float) -> list[Inbound]:
        can = self._can
        out: list[Inbound] = []
        wait: float = timeout
        deadline = time.monotonic() + timeout if timeout > 0 else 0.0
        first = True
        on_links = False  # a frame of ours on a link came in (management frames are everyone's)
        while True:
            if not first:
                # after a frame of ours, take what else is there; after only other modules'
                # frames (on a shared bus, most of them), wait on for the rest of the timeout
                wait = 0.0 if on_links or timeout <= 0 else max(0.0, deadline - time.monotonic())
            first = False
            try:
                msg = self._bus.recv(timeout=wait)
            except can.CanOperationError:
                # An undecodable udp_multicast datagram, or a bus error: count it and return
                # what we have; the next poll tries again (never spin on a failing bus).
                self._corrupted += 1
                return out
            if msg is None:
                return out
            if not msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
                continue  # not dh2rt traffic
            if msg.arbitration_id == MANAGEMENT_ID:
                out.append(Inbound(FrameFamily.MANAGEMENT, OFF_LINK, bytes(msg.data), self._arrived(msg.timestamp)))
                continue
            connector = self._listen.get(msg.arbitration_id & LINK_END_MASK)
            if connector is None:
                continue  # another module's link, or our own frame echoed back
            payload = self._reassembler.feed(msg.arbitration_id, bytes(msg.data), msg.timestamp)
            if payload is not None:
                on_links = True
                self._took((msg.arbitration_id >> 1) & MAX_LINK_ID, 1 - (msg.arbitration_id & 1))
                # arrived as its first frame did (a COMMIT's time left counts from then)
                out.append(Inbound.on_link(connector, payload, self._arrived(self._reassembler.started)))

    def _took(self, link_id: int, side: int) -> None:
        """A frame for my end ``(link_id, side)`` was taken: if it was sent before I attached
        the end (it waited in the bus's queue meanwhile), the end was mine from its stamp on:
        every later frame to the end comes after it in the queue, and is read too."""
        spans = self._held.get((link_id, side))
        stamp = self._reassembler.started
        if spans and stamp and stamp < spans[-1].since:
            spans[-1].since = stamp

    def held_ends(self) -> list[HeldEnd]:
        """The link ends this transport held, each span apart (see :class:`HeldEnd`)."""
        return [HeldEnd(link, side, s.since, s.until) for (link, side), spans in self._held.items() for s in spans]

    def _arrived(self, stamp: float) -> float:
        """python-can's receive timestamp (wall-clock seconds: the kernel's on SocketCAN and
        udp_multicast, the sender's on ``virtual``) on this transport's clock; now if none."""
        now = self.clock()
        if not stamp:
            return now
        return now - min(1.0, max(0.0, time.time() - stamp))

    def _medium_counts(self) -> tuple[int, int]:
        return self._reassembler.dropped, self._reassembler.corrupted

    def _close(self) -> None:
        self._bus.shutdown()


class VirtualCanTransport(CanTransport):
    """python-can's in-process ``virtual`` bus: modules in one process, no kernel support."""

    name = "virtual"
    interface = "virtual"
    default_channel = "dh2rt"


class UdpCanTransport(CanTransport):
    """python-can's ``udp_multicast``: crosses processes and hosts (IPv4 group by default).

    It follows the route table and cannot pick an interface: outside a private network
    namespace it sends on the default route.
    """

    name = "udp"
    interface = "udp_multicast"
    default_channel = "239.74.163.2"

    def __init__(self, codec: FrameCodec, **options: Any) -> None:
        options.setdefault("fd", False)
        super().__init__(codec, **options)


class SocketCanTransport(CanTransport):
    """A kernel SocketCAN interface (``vcan0``, ``can0``, ...); probes AF_CAN before opening."""

    name = "socketcan"
    interface = "socketcan"
    kernel_filters = True
    read_between_cycles = True
    default_channel = "vcan0"

    def _open_bus(self, options: dict[str, Any]) -> Any:
        problem = socketcan_problem(self.channel)
        if problem is not None:
            raise TransportUnavailable(
                f"SocketCAN interface {self.channel!r} is unavailable: {problem}. "
                f"On a Linux host with CAN support, create a virtual interface with: {VCAN_SETUP}. "
                f"Transports that work without SocketCAN: {FALLBACKS}."
            )
        return super()._open_bus(options)
