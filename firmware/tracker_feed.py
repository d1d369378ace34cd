"""What a module hears from the overhead tracker: each marker's latest pose on the floor, and
how old it is.

``dh2rt tracker`` (tools/tracker/) broadcasts one datagram per camera frame
(:mod:`dh2rt.wire.tracker`). A module binds a UDP socket, non-blocking, and :meth:`TrackerFeed.poll`
drains it once a cycle from the main loop: no thread, no wait. Markers are named by the
mapping marker id -> module name the module is given (its config's, later). A pose that never
came, or came longer ago than the bound, is :class:`~dh2rt.errors.NoTrackerReading` naming the
marker and its age: a module never steers by a pose it does not have.

Datagrams that do not decode are counted and the last reason kept (a stray sender must not
stop a module); a datagram captured before the newest one already taken (UDP may reorder) is
dropped, so a marker's pose never goes back in time. Ages are on the module's own clock, from
when a datagram arrived: the tracker's clock is not the module's.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from dh2rt.closing import Closing
from dh2rt.errors import NoTrackerReading, TrackerDatagramError
from dh2rt.wire.tracker import DEFAULT_PORT, MAX_DATAGRAM, MarkerPose, decode

#: How old a pose may be before it is no reading (seconds): a few frames of a 30 fps camera.
DEFAULT_MAX_AGE_S = 0.25
#: Datagrams one poll takes at most, so a flood cannot stall a cycle.
MAX_PER_POLL = 64


@dataclass(frozen=True, slots=True)
class TrackedPose:
    """A module's pose as the tracker last reported it, and its age when asked."""

    module: str
    pose: MarkerPose
    sequence: int
    captured_us: int
    received_s: float  # the module's clock
    age_s: float

    @property
    def x_mm(self) -> float:
        return self.pose.x_mm

    @property
    def y_mm(self) -> float:
        return self.pose.y_mm

    @property
    def heading_deg(self) -> float:
        return self.pose.heading_deg


@dataclass(frozen=True, slots=True)
class _Latest:
    pose: MarkerPose
    sequence: int
    captured_us: int
    received_s: float


class TrackerFeed(Closing):
    """The tracker's poses, as a module polls them. ``modules`` maps marker id -> module name;
    ``own`` is this module's name (one of them). ``bind`` is the address to listen on
    (loopback by default; ``("", port)`` for every interface on a robot's network)."""

    def __init__(
        self,
        modules: Mapping[int, str],
        own: str,
        *,
        bind: tuple[str, int] = ("127.0.0.1", DEFAULT_PORT),
        max_age_s: float = DEFAULT_MAX_AGE_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if own not in modules.values():
            raise ValueError(f"TrackerFeed: own module {own!r} has no marker in {dict(modules)}")
        if len(set(modules.values())) != len(modules):
            raise ValueError(f"TrackerFeed: two markers name one module in {dict(modules)}")
        if not max_age_s > 0:
            raise ValueError(f"TrackerFeed: max_age_s must be more than 0, got {max_age_s!r}")
        self.modules = dict(modules)
        self.markers = {name: marker for marker, name in self.modules.items()}
        self.own = own
        self.max_age_s = max_age_s
        self.clock = clock
        self.datagrams = 0  # taken
        self.rejected = 0  # did not decode
        self.stale = 0  # captured before one already taken
        self.last_error: TrackerDatagramError | None = None
        self._latest: dict[int, _Latest] = {}
        self._newest_capture = -1
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:  # no SO_REUSEADDR: two modules on one port would split the datagrams between them
            self._sock.bind(bind)
            self._sock.setblocking(False)
        except OSError:
            self._sock.close()
            raise

    @property
    def address(self) -> tuple[str, int]:
        """Where the feed listens (the port the OS chose, when bound to port 0)."""
        host, port = self._sock.getsockname()[:2]
        return str(host), int(port)

    def poll(self) -> int:
        """Take the datagrams that have arrived (at most MAX_PER_POLL); how many were taken."""
        taken = 0
        for _ in range(MAX_PER_POLL):
            try:
                data = self._sock.recv(MAX_DATAGRAM + 1)
            except (BlockingIOError, InterruptedError):
                break
            taken += self.take(data, self.clock())
        return taken

    def take(self, data: bytes, received_s: float) -> int:
        """One datagram's bytes, received at ``received_s`` on the module's clock (sans-IO:
        :meth:`poll` feeds it from the socket); 1 if taken, 0 if rejected or stale."""
        try:
            frame = decode(data)
        except TrackerDatagramError as exc:
            self.rejected += 1
            self.last_error = exc
            return 0
        if frame.captured_us < self._newest_capture:
            self.stale += 1
            return 0
        self._newest_capture = frame.captured_us
        self.datagrams += 1
        for pose in frame.markers:
            if pose.marker in self.modules:
                self._latest[pose.marker] = _Latest(pose, frame.sequence, frame.captured_us, received_s)
        return 1

    def pose(self, module: str, max_age_s: float | None = None) -> TrackedPose:
        """``module``'s latest pose; NoTrackerReading if none came, or none within ``max_age_s``
        (default: the feed's bound)."""
        bound = self.max_age_s if max_age_s is None else max_age_s
        if module not in self.markers:
            raise KeyError(f"no marker is given for module {module!r} (markers: {self.modules})")
        marker = self.markers[module]
        latest = self._latest.get(marker)
        if latest is None:
            raise NoTrackerReading(marker, module, None, bound)
        age = self.clock() - latest.received_s
        if age > bound:
            raise NoTrackerReading(marker, module, age, bound)
        return TrackedPose(module, latest.pose, latest.sequence, latest.captured_us, latest.received_s, age)

    def own_pose(self, max_age_s: float | None = None) -> TrackedPose:
        """This module's own pose (see :meth:`pose`)."""
        return self.pose(self.own, max_age_s)

    def fresh(self, max_age_s: float | None = None) -> dict[str, TrackedPose]:
        """Every module whose pose is within the bound, by name."""
        found: dict[str, TrackedPose] = {}
        for module in self.markers:
            try:
                found[module] = self.pose(module, max_age_s)
            except NoTrackerReading:
                continue
        return found

    def close(self) -> None:
        self._sock.close()
