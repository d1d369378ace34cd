"""The link emulator: the physical world's infrared pairs, as pty pairs with a relay.

Each docked connector pair (a *link*) gets two pty pairs. The module at side 0 opens the
slave path ``link.paths[0]`` as its connector's serial port, the module at side 1 opens
``link.paths[1]``; one relay thread moves bytes between the two masters. On the way it can:

* drop whole frames (``frame_loss``; frames are cut at the 0x00 delimiter of the serial
  framing), drop single bytes (``byte_loss``), flip bits (``bit_error``: probability per bit);
* delay delivery (``latency`` seconds plus uniform ``jitter``), keeping order;
* pace the bytes at a line's rate (``baudrate``: 10 bits a byte, 8N1): each direction sends
  one byte after another, so a frame arrives ``len × 10 / baudrate`` s after the line is free,
  and a sender that writes faster than the line queues behind itself, as a UART would;
* stop relaying (``undock``): sends still succeed, bytes go nowhere, and the modules'
  liveness notices the silence; ``dock`` resumes.

Random choices come from one ``random.Random(seed)``. ``close()`` stops the thread and
closes every pty; close the modules' ports first (a slave whose master is gone reads EIO).

A ``tap`` (the launcher's ``--capture``) sees every frame on every link, cut at the
delimiter as the relay cuts them: ``tap(time, link_id, side, wire, lost)`` with the wall-clock
time the frame left its sender, the side that sent it, and the bytes as delivered (after bit
errors and byte loss) or, for a frame the link lost or that was sent into an undocked link,
the bytes as sent with ``lost=True``. It runs on the relay thread: keep it short.
"""

from __future__ import annotations

import heapq
import itertools
import os
import random
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

from dh2rt.closing import Closing
from dh2rt.errors import TransportError
from dh2rt.topology import Topology
from hil.ptys import IDLE_WAIT_S, PtyRelay, close_fd, open_raw_pty

#: Bytes held while waiting for a delimiter before they are relayed as they are.
_MAX_PENDING = 2048

#: What sees every frame: ``tap(time, link_id, side_that_sent, wire_bytes, lost)``.
Tap = Callable[[float, int, int, bytes, bool], None]


@dataclass(frozen=True, slots=True)
class Impairments:
    """What the emulated medium does to the bytes it carries."""

    frame_loss: float = 0.0
    byte_loss: float = 0.0
    bit_error: float = 0.0
    latency: float = 0.0
    jitter: float = 0.0
    baudrate: float = 0.0  # 0: bytes cross at once (no line rate)

    def __post_init__(self) -> None:
        for name in ("frame_loss", "byte_loss", "bit_error"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"link emulator: {name}={value} is not a probability in [0, 1]")
        for name in ("latency", "jitter", "baudrate"):
            if getattr(self, name) < 0:
                raise ValueError(f"link emulator: {name}={getattr(self, name)} must not be negative")


@dataclass(slots=True)
class LinkStats:
    """Per-link counts, both directions together."""

    frames: int = 0
    frames_lost: int = 0
    bytes_lost: int = 0
    bits_flipped: int = 0
    bytes_discarded: int = 0  # read while undocked, or refused by a full pty
    bytes_relayed: int = 0


@dataclass(slots=True)
class _Side:
    master: int
    slave: int
    path: str
    pending: bytearray = field(default_factory=bytearray)


@dataclass(slots=True)
class EmulatedLink:
    """One docked pair: ``paths[side]`` is the port a module opens at that end."""

    link_id: int
    sides: tuple[_Side, _Side]
    impairments: Impairments
    docked: bool = True
    stats: LinkStats = field(default_factory=LinkStats)

    @property
    def paths(self) -> tuple[str, str]:
        return self.sides[0].path, self.sides[1].path


class LinkEmulator(Closing):
    """Relays bytes between the two ends of each emulated link, with impairments."""

    def __init__(
        self,
        *,
        frame_loss: float = 0.0,
        byte_loss: float = 0.0,
        bit_error: float = 0.0,
        latency: float = 0.0,
        jitter: float = 0.0,
        baudrate: float = 0.0,
        seed: int | None = None,
        tap: Tap | None = None,
    ) -> None:
        self.default = Impairments(frame_loss, byte_loss, bit_error, latency, jitter, baudrate)
        self.tap = tap
        self._rng = random.Random(seed)
        self._lock = threading.Lock()
        self._links: dict[int, EmulatedLink] = {}
        self._by_fd: dict[int, tuple[EmulatedLink, int]] = {}
        self._queue: list[tuple[float, int, int, bytes, int]] = []  # (due, order, master fd, data, link)
        self._order = itertools.count()
        #: per target master fd: when the line into it is free again (paced links)
        self._line_free: dict[int, float] = {}
        self._ptys = PtyRelay(
            "dh2rt-link-emulator", self._lock, self._from_master, wait=self._next_due, after_reads=self._deliver_due
        )

    # -- links --------------------------------------------------------------------------------

    def add_link(self, link_id: int | None = None, *, docked: bool = True, **impairments: float) -> EmulatedLink:
        """Create a link (two pty pairs); ``impairments`` override the emulator's defaults."""
        with self._lock:
            if self._ptys.closed:
                raise TransportError("link emulator is closed")
            if link_id is None:
                link_id = max(self._links, default=-1) + 1
            if link_id in self._links:
                raise TransportError(f"link emulator: link {link_id} already exists")
            sides = (_open_side(), _open_side())
            link = EmulatedLink(link_id, sides, replace(self.default, **impairments), docked)
            self._links[link_id] = link
            for i, side in enumerate(sides):
                self._by_fd[side.master] = (link, i)
                self._ptys.watch(side.master)
        return link

    def link(self, link_id: int) -> EmulatedLink:
        try:
            return self._links[link_id]
        except KeyError:
            raise TransportError(f"link emulator: no link {link_id}") from None

    @property
    def links(self) -> Mapping[int, EmulatedLink]:
        return dict(self._links)

    def for_topology(self, topology: Topology) -> dict[tuple[int, int], str]:
        """One link per docked pair of ``topology``; returns ``(module, connector) -> port path``.

        Link ``i`` is ``topology.links[i]``; its ``a`` end is side 0.
        """
        ports: dict[tuple[int, int], str] = {}
        for i, lk in enumerate(topology.links):
            em = self.add_link(i)
            ports[(lk.a, lk.a_conn)] = em.paths[0]
            ports[(lk.b, lk.b_conn)] = em.paths[1]
        return ports

    def dock(self, link_id: int) -> None:
        """Relay bytes on ``link_id`` again."""
        self.link(link_id).docked = True

    def undock(self, link_id: int) -> None:
        """Stop relaying on ``link_id``: bytes sent either way are discarded."""
        link = self.link(link_id)
        with self._lock:
            link.docked = False
            link.sides[0].pending.clear()
            link.sides[1].pending.clear()
            # frames on the line when it parts are lost: counted, so that frames add up
            kept = [item for item in self._queue if item[4] != link_id]
            for item in self._queue:
                if item[4] == link_id:
                    link.stats.frames_lost += 1
                    link.stats.bytes_discarded += len(item[3])
            self._queue[:] = kept
            heapq.heapify(self._queue)

    def set_impairments(self, link_id: int, **impairments: float) -> None:
        """Change what ``link_id`` does to its bytes from now on."""
        link = self.link(link_id)
        link.impairments = replace(link.impairments, **impairments)

    def inject(self, link_id: int, to_side: int, data: bytes) -> None:
        """Write raw bytes towards the module at ``to_side`` (tests: line noise, garbage)."""
        link = self.link(link_id)
        try:
            os.write(link.sides[to_side].master, bytes(data))
        except OSError as exc:
            raise TransportError(f"link emulator: cannot inject on link {link_id}: {exc}") from exc

    def stats(self, link_id: int) -> LinkStats:
        with self._lock:
            return replace(self.link(link_id).stats)

    # -- lifecycle ----------------------------------------------------------------------------

    def close(self) -> None:
        """Stop relaying and close every pty; idempotent."""
        if not self._ptys.stop():
            return
        for link in self._links.values():
            for side in link.sides:
                for fd in (side.master, side.slave):
                    close_fd(fd)
        self._links.clear()
        self._by_fd.clear()

    # -- the relay thread ---------------------------------------------------------------------

    def _next_due(self) -> float:
        """How long the relay may wait for a byte: until the next delivery is due (under the lock)."""
        return IDLE_WAIT_S if not self._queue else max(0.0, self._queue[0][0] - time.monotonic())

    def _from_master(self, fd: int, data: bytes) -> None:
        with self._lock:
            entry = self._by_fd.get(fd)
            if entry is None:
                return
            link, side_index = entry
            side = link.sides[side_index]
            if not link.docked:
                link.stats.bytes_discarded += len(data)
                side.pending += data  # sent into an undocked link: lost (and the capture shows it so)
                for frame in self._frames(side.pending):
                    if frame[-1] == 0 and len(frame) > 1:
                        link.stats.frames += 1
                        link.stats.frames_lost += 1
                    self._tapped(link, side_index, frame, lost=True)
                return
            target = link.sides[1 - side_index].master
            side.pending += data
            imp = link.impairments
            now = time.monotonic()
            for frame in self._frames(side.pending):
                if frame[-1] == 0:
                    link.stats.frames += 1
                    if len(frame) > 1 and imp.frame_loss and self._rng.random() < imp.frame_loss:
                        link.stats.frames_lost += 1
                        self._tapped(link, side_index, frame, lost=True)
                        self._on_line(target, len(frame), now, imp)  # it took the line all the same
                        continue
                delivered = self._impair(link, frame, imp)
                self._tapped(link, side_index, delivered, lost=False)
                self._schedule(link, target, delivered, now, imp)

    @staticmethod
    def _frames(pending: bytearray) -> list[bytes]:
        """Cut ``pending`` at each delimiter (each frame keeps its 0x00); bytes with no
        delimiter stay pending, unless there are more than _MAX_PENDING of them (no framing:
        they pass through as one chunk)."""
        out: list[bytes] = []
        while True:
            idx = pending.find(0)
            if idx < 0:
                if len(pending) > _MAX_PENDING:
                    out.append(bytes(pending))
                    pending.clear()
                return out
            out.append(bytes(pending[: idx + 1]))
            del pending[: idx + 1]

    def _tapped(self, link: EmulatedLink, side: int, wire: bytes, *, lost: bool) -> None:
        if self.tap is not None and wire and wire != b"\x00":
            self.tap(time.time(), link.link_id, side, wire, lost)

    def _impair(self, link: EmulatedLink, data: bytes, imp: Impairments) -> bytes:
        if not imp.byte_loss and not imp.bit_error:
            return data
        out = bytearray()
        p_byte_hit = 1.0 - (1.0 - imp.bit_error) ** 8
        for b in data:
            if imp.byte_loss and self._rng.random() < imp.byte_loss:
                link.stats.bytes_lost += 1
                continue
            if p_byte_hit and self._rng.random() < p_byte_hit:
                b ^= 1 << self._rng.randrange(8)
                link.stats.bits_flipped += 1
            out.append(b)
        return bytes(out)

    def _on_line(self, target: int, size: int, now: float, imp: Impairments) -> float:
        """When ``size`` bytes sent at ``now`` towards ``target`` have crossed the line: at
        once, or on a paced link one byte after another once the line is free."""
        if not imp.baudrate:
            return now
        done = max(now, self._line_free.get(target, 0.0)) + size * 10.0 / imp.baudrate
        self._line_free[target] = done
        return done

    def _schedule(self, link: EmulatedLink, target: int, data: bytes, now: float, imp: Impairments) -> None:
        if not data:
            return
        delay = imp.latency + (self._rng.uniform(0.0, imp.jitter) if imp.jitter else 0.0)
        now = self._on_line(target, len(data), now, imp)
        # Keep order per direction: never schedule before what is already queued for target.
        due = now + delay
        for item in self._queue:
            if item[2] == target and item[0] > due:
                due = item[0]
        heapq.heappush(self._queue, (due, next(self._order), target, data, link.link_id))

    def _deliver_due(self) -> None:
        now = time.monotonic()
        while True:
            with self._lock:
                if not self._queue or self._queue[0][0] > now:
                    return
                _, _, target, data, link_id = heapq.heappop(self._queue)
                link = self._links.get(link_id)
                if link is None:
                    return
                if not link.docked:  # (undock() takes its frames off the queue; a race is lost all the same)
                    link.stats.bytes_discarded += len(data)
                    link.stats.frames_lost += 1
                    continue
            try:
                n = os.write(target, data)
            except (BlockingIOError, OSError):
                n = 0
            with self._lock:
                link.stats.bytes_relayed += n
                link.stats.bytes_discarded += len(data) - n


def _open_side() -> _Side:
    return _Side(*open_raw_pty())
