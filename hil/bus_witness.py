"""The witness of a shared CAN bus: every dh2rt frame on it, by the link end that sent it.

On serial links the link emulator carries every frame and so can count the ones no module
can: sent into an undocked link, due for a killed module. A bus carries every frame to every
node and each node keeps the ones for the link ends it holds, so a frame for a link end
nobody holds (a cut, a killed or stopped module, an end not yet negotiated) is dropped by
every filter and counted nowhere. The :class:`BusWitness` is one more node on the robot's
bus, in the world's process, that keeps every frame: the number each link end sent, and
when (the stamp python-can gives the frame, the clock the modules' transports note the
spans they held their ends on, :class:`~dh2rt.transport.base.HeldEnd`).

A dh2rt frame is one CAN frame, or a train of segments: the witness counts a single frame
and the first segment of a train (:mod:`dh2rt.wire.can_frames`), one per frame the sender
counted sent, stamped as a receiver's reassembler stamps it (its first segment's time).
Management frames (link negotiation's) are no link's and are not counted, as the modules
count them nowhere.

It can watch only a bus every node shares (python-can ``virtual``, ``udp_multicast``,
SocketCAN): an adapter of one module's (``slcan`` on a port) is no bus the world can join.
"""

from __future__ import annotations

import re
import threading
from bisect import bisect_left
from collections.abc import Iterable, Mapping
from typing import Any

from dh2rt.closing import Closing
from dh2rt.errors import TransportUnavailable
from dh2rt.wire.can_frames import FIRST, MANAGEMENT_ID, MAX_LINK_ID, SINGLE

#: python-can interfaces on which every node sees every frame, as the witness must.
SHARED_INTERFACES = frozenset({"virtual", "udp_multicast", "socketcan"})
#: A link end on the bus: (link id, side).
EndId = tuple[int, int]
#: How long the witness reads on after it is told to stop, until the bus is quiet (s).
QUIET_S = 0.1


class BusWitness(Closing):
    """Every dh2rt frame on one python-can bus, by sending link end (see the module docs)."""

    def __init__(self, interface: str, channel: str, **options: Any) -> None:
        import can

        try:
            self._bus: Any = can.Bus(interface=interface, channel=channel, **options)
        except (can.CanError, OSError, ImportError, ValueError) as exc:
            raise TransportUnavailable(f"the witness cannot open python-can {interface} on {channel!r}: {exc}") from exc
        self._can: Any = can
        #: CAN frames that could not be read (an undecodable datagram)
        self.errors = 0
        self._sent: dict[EndId, list[float]] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="dh2rt-bus-witness", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            try:
                msg = self._bus.recv(timeout=QUIET_S)
            except self._can.CanOperationError:
                self.errors += 1
                continue
            if msg is None:
                if self._stop.is_set():
                    return
                continue
            self._saw(msg)

    def _saw(self, msg: Any) -> None:
        can_id = msg.arbitration_id
        if not msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame or can_id == MANAGEMENT_ID:
            return
        if (can_id >> 25) & 3 not in (SINGLE, FIRST):
            return  # a train's later segments: its first one counted the frame
        end = ((can_id >> 1) & MAX_LINK_ID, can_id & 1)
        with self._lock:
            self._sent.setdefault(end, []).append(float(msg.timestamp))

    def ends(self) -> list[EndId]:
        """Every link end a frame was sent from."""
        with self._lock:
            return list(self._sent)

    def sent_from(self, end: EndId, since: float = float("-inf"), until: float = float("inf")) -> int:
        """Frames ``end`` sent, stamped within [since, until)."""
        with self._lock:
            stamps = sorted(self._sent.get(end, ()))
        return bisect_left(stamps, until) - bisect_left(stamps, since)

    def sent_to(self, end: EndId, spans: Iterable[tuple[float, float]]) -> int:
        """Frames sent to ``end`` (by the link's other side) stamped within one of ``spans``."""
        link, side = end
        return sum(self.sent_from((link, 1 - side), since, until) for since, until in spans)

    def total(self) -> int:
        """Every frame the witness saw."""
        with self._lock:
            return sum(len(s) for s in self._sent.values())

    def close(self) -> None:
        """Read on until the bus is quiet (the frames the last senders sent are counted), then
        close the bus."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(5.0)
        self._bus.shutdown()


#: A span a module (or a cable) held a link end: (end, since, until), wall-clock seconds.
Span = tuple[EndId, float, float]

_NEGOTIATED = re.compile(r"link negotiated: connector \d+ is link (\d+) side ([01])")


def spans_of(status: Mapping[str, Any], until: float | None = None) -> list[Span]:
    """The spans a module's status says its transport held its link ends: an end held still
    is held until ``until`` (a killed module's death), or else until the status was taken
    (after a final status the module reads nothing more)."""
    at = float(status.get("link_ends_at", 0.0))
    end_of = at if until is None else until
    return [
        ((int(link), int(side)), float(since), end_of if last is None else min(float(last), end_of))
        for link, side, since, last in status.get("link_ends", ())
    ]


def negotiated_end(line: str) -> EndId | None:
    """The link end a module's log line says it negotiated (firmware.negotiated_links), or None."""
    found = _NEGOTIATED.search(line)
    return None if found is None else (int(found.group(1)), int(found.group(2)))
