"""The loop's overhead tracker over UDP, as ``dh2rt tracker`` publishes a camera's (``--tracker-udp``).

With it, each module of the loop hears the tracker itself (module.toml ``[tracker]``,
firmware/tracker_floor.py) rather than being pushed its parts in a ``Floor`` command: the
world encodes the stand-in tracker's report (every module's three parts, markers ``3 m + k``)
as :mod:`dh2rt.wire.tracker` datagrams and sends one to every module's own port on
127.0.0.1 each world cycle that a module reads the floor. Loopback only: each module has a
port of its own (the feed binds without SO_REUSEADDR), chosen free when the world starts.
"""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Iterable

from dh2rt.closing import Closing
from dh2rt.wire.tracker import MarkerPose, TrackerDatagram, encode
from firmware.motion.readings import FloorPoses

LOOPBACK = "127.0.0.1"


def free_ports(count: int) -> list[int]:
    """``count`` distinct UDP ports free on 127.0.0.1 just now (each bound at once, then let go)."""
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(count)]
    try:
        for s in socks:
            s.bind((LOOPBACK, 0))
        return [int(s.getsockname()[1]) for s in socks]
    finally:
        for s in socks:
            s.close()


def markers(floor: FloorPoses) -> list[MarkerPose]:
    """The report's parts as markers: ``3 m``, ``3 m + 1``, ``3 m + 2`` for module ``m``'s
    centre, front and back (mm, degrees counter-clockwise in 0..360)."""
    out = []
    for m, pose in sorted(floor.modules.items()):
        for k, part in enumerate((pose.centre, pose.front, pose.back)):
            heading = math.degrees(part.heading) % 360.0
            out.append(MarkerPose(3 * m + k, part.x * 1000, part.y * 1000, heading, 0.0))
    return out


class TrackerPublisher(Closing):
    """Sends the tracker's datagrams to each of ``ports`` on 127.0.0.1."""

    def __init__(self, ports: Iterable[int]) -> None:
        self.ports = list(ports)
        self.sequence = 0
        #: datagrams sent (one a port each time), and sends the OS refused
        self.sent = 0
        self.failed = 0
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def publish(self, floor: FloorPoses, ports: Iterable[int] | None = None) -> None:
        """One frame: ``floor``'s parts to every port (or those of ``ports``)."""
        data = encode(TrackerDatagram(self.sequence, time.time_ns() // 1000, tuple(markers(floor))))
        self.sequence = (self.sequence + 1) % (1 << 32)
        for port in self.ports if ports is None else ports:
            try:
                self._sock.sendto(data, (LOOPBACK, port))
                self.sent += 1
            except OSError:  # a full buffer: the frame is lost, as a camera's can be
                self.failed += 1

    def close(self) -> None:
        self._sock.close()
