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
delimiter as the relay cuts them, once its fate is known: ``tap(time, link_id, side, wire,
lost)`` with the wall-clock time the frame reached its receiver (a lost one's: when it left
its sender), the side that sent it, and the
bytes as delivered (after bit errors and byte loss) or, for a frame that never reached a
reader (see below), the bytes as sent with ``lost=True``. It runs on the relay thread (or on
the caller's, for what a cut or ``close()`` loses): keep it short.

Counting frames (:class:`LinkStats`): every frame sent into a link is counted once in
``frames`` and ends in exactly one of these, each counted where it happens:

* ``frames_lost``: it never reached a reader: lost by ``frame_loss``, sent into an undocked
  link, on the line when the link was undocked or the emulator closed, due for a side whose
  reader is gone (:meth:`LinkEmulator.reader_gone`: a killed module) or, with ``await_open``,
  that no module has opened yet (opening a port flushes it), or refused by a full pty;
* written into the other side's pty, where the receiver's decoder sees the chunks its
  delimiters end (``frames_delivered``): a bit error or a lost byte that destroys the
  frame's delimiter joins it to the next chunk (``frames_merged``), one that makes a 0x00
  inside it cuts it in two (``frames_split``, also for a lone delimiter that ends a chunk);
* of what was written, ``frames_unread`` chunks were still in the pty when its reader died
  or at ``close()`` (the emulator reads them out then).

So, exactly: ``frames + frames_split = frames_delivered + frames_lost + frames_merged``, and
the chunks the receivers counted (received, corrupted, dropped) are ``frames_delivered -
frames_unread``.
"""

from __future__ import annotations

import heapq
import itertools
import os
import random
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, fields, replace

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
    """Per-link counts, both directions together (see "Counting frames" in the module docs)."""

    frames: int = 0
    frames_lost: int = 0
    frames_delivered: int = 0
    frames_merged: int = 0
    frames_split: int = 0
    frames_unread: int = 0
    bytes_lost: int = 0
    bits_flipped: int = 0
    bytes_discarded: int = 0  # read while undocked, or refused by a full pty
    bytes_relayed: int = 0


@dataclass(slots=True)
class SideCounts:
    """One side's part of the counts: what the module there sent (``sent``), the chunk ends
    written into its pty for it to read (``written``) and those read out of it unread
    (``unread``): the module read ``written - unread`` of them."""

    sent: int = 0
    written: int = 0
    unread: int = 0


@dataclass(slots=True)
class _Side:
    master: int
    slave: int
    path: str
    pending: bytearray = field(default_factory=bytearray)
    #: the stream written into this side's pty is at a chunk's start (nothing yet, or a 0x00 last)
    fresh: bool = True
    #: its reader is gone (a killed module): what is due for it is lost, not written
    reader_gone: bool = False
    #: frames sent from this side, chunk ends written into its pty, and chunks read out of it unread
    counts: SideCounts = field(default_factory=SideCounts)


@dataclass(frozen=True, slots=True)
class _Piece:
    """What the relay cut from one side and will write into the other: a frame (``base`` 1)
    or a lone delimiter or an undelimited chunk (``base`` 0), after impairments."""

    link_id: int
    side: int  # the side that sent it
    data: bytes
    base: int
    sent_at: float  # wall-clock time it left its sender (the tap's stamp if it is lost)


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
        await_open: bool = False,
    ) -> None:
        self.default = Impairments(frame_loss, byte_loss, bit_error, latency, jitter, baudrate)
        self.tap = tap
        #: a side has no reader until its module opened it (see _opened)
        self.await_open = await_open
        self._rng = random.Random(seed)
        self._lock = threading.Lock()
        self._links: dict[int, EmulatedLink] = {}
        self._by_fd: dict[int, tuple[EmulatedLink, int]] = {}
        self._queue: list[tuple[float, int, int, _Piece]] = []  # (due, order, master fd, piece)
        self._order = itertools.count()
        #: per target master fd: when the line into it is free again (paced links)
        self._line_free: dict[int, float] = {}
        #: every link's counts, kept after close() (cut links' and cables' too)
        self._final: dict[int, LinkStats] = {}
        self._final_sides: dict[str, SideCounts] = {}
        self._ptys = PtyRelay(
            "dh2rt-link-emulator",
            self._lock,
            self._from_master,
            wait=self._next_due,
            after_reads=self._deliver_due,
            watch_held=True,
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
            sides = (_open_side(self.await_open), _open_side(self.await_open))
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
        """Stop relaying on ``link_id``: bytes sent either way are discarded, and the frames on
        the line when it parts are lost (counted, so that frames add up)."""
        link = self.link(link_id)
        with self._lock:
            link.docked = False
            link.sides[0].pending.clear()
            link.sides[1].pending.clear()
            self._lose_queued(lambda piece: piece.link_id == link_id)

    def side_counts(self, path: str) -> SideCounts:
        """The counts of the side a module opens at ``path`` (kept after close())."""
        with self._lock:
            found = self._side(path)
            if found is not None:
                return replace(found[1].counts)
            return replace(self._final_sides.get(path, SideCounts()))

    def reader_gone(self, path: str) -> None:
        """The module that opens ``path`` is dead (killed): the chunks left unread in its pty are
        read out and counted (``frames_unread``), and frames due for it from now on are lost
        (``frames_lost``) until :meth:`reader_back` (with ``await_open``: until a module opens
        it again). A path of no link is ignored."""
        with self._lock:
            found = self._side(path)
            if found is not None:
                link, side = found
                side.reader_gone = True
                self._read_out(link, side)
                # what it wrote before it died goes on; a frame it did not finish is no frame
                self._relay(link, link.sides.index(side), _read_all(side.master))
                link.stats.bytes_discarded += len(side.pending)
                side.pending.clear()

    def reader_back(self, path: str) -> None:
        """A module reads ``path`` again (a restart): frames are written to it again."""
        with self._lock:
            found = self._side(path)
            if found is not None:
                found[1].reader_gone = False

    def new_sender(self, path: str) -> None:
        """A new module is about to open ``path`` (a restart): bytes of a frame the dead one
        did not finish writing are no frame, and must not join the new one's first."""
        with self._lock:
            found = self._side(path)
            if found is not None:
                link, side = found
                link.stats.bytes_discarded += len(side.pending)
                side.pending.clear()

    def _side(self, path: str) -> tuple[EmulatedLink, _Side] | None:
        for link in self._links.values():
            for side in link.sides:
                if side.path == path:
                    return link, side
        return None

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
            if link_id in self._final:
                return replace(self._final[link_id])
            return replace(self.link(link_id).stats)

    @property
    def held_s(self) -> float:
        """The most the machine held the relay thread so far (s): every byte on every link
        waited that long on top of its line time (see :class:`~hil.ptys.PtyRelay`)."""
        return self._ptys.held_s

    def holds(self) -> list[tuple[float, float]]:
        """The latest times the machine held the relay: ``(ended, seconds)`` on
        CLOCK_MONOTONIC (:func:`held_within` adds them up over a span)."""
        return list(self._ptys.holds)

    def totals(self) -> LinkStats:
        """Every link's counts added up (cut links and cables too; still there after close())."""
        with self._lock:
            every = [*self._final.values(), *(lk.stats for lk in self._links.values())]
        out = LinkStats()
        for stats in every:
            for f in fields(LinkStats):
                setattr(out, f.name, getattr(out, f.name) + getattr(stats, f.name))
        return out

    # -- lifecycle ----------------------------------------------------------------------------

    def close(self) -> None:
        """Stop relaying, count what is left (frames still on their way are lost, chunks still
        in a pty unread), and close every pty; idempotent. Close the modules' ports first."""
        if not self._ptys.stop():
            return
        with self._lock:
            for link in self._links.values():
                for i, side in enumerate(link.sides):  # sent, but not yet read by the relay
                    self._lost_unrelayed(link, i, _read_all(side.master))
            self._lose_queued(lambda piece: True)
            for link in self._links.values():
                for side in link.sides:
                    self._read_out(link, side)
                    self._final_sides[side.path] = side.counts
                self._final[link.link_id] = link.stats
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
            if entry is not None:
                self._relay(*entry, data)

    def _relay(self, link: EmulatedLink, side_index: int, data: bytes) -> None:
        """What a module at ``side_index`` wrote, cut into frames and sent on (under the lock)."""
        if not link.docked:
            link.stats.bytes_discarded += len(data)
            self._lost_unrelayed(link, side_index, data)  # the capture shows them lost
            return
        side = link.sides[side_index]
        target = link.sides[1 - side_index].master
        side.pending += data
        imp = link.impairments
        now = time.monotonic()
        for frame in self._frames(side.pending):
            base = _base(frame)
            self._opened(side, frame)
            link.stats.frames += base
            side.counts.sent += base
            if base and imp.frame_loss and self._rng.random() < imp.frame_loss:
                link.stats.frames_lost += 1
                self._tapped(link, side_index, frame, time.time(), lost=True)
                self._on_line(target, len(frame), now, imp)  # it took the line all the same
                continue
            piece = _Piece(link.link_id, side_index, self._impair(link, frame, imp), base, time.time())
            self._schedule(link, target, piece, now, imp)

    def _lost_unrelayed(self, link: EmulatedLink, side_index: int, data: bytes) -> None:
        """Frames sent that never go on the line (an undocked link, the emulator closing)."""
        side = link.sides[side_index]
        side.pending += data
        for frame in self._frames(side.pending):
            base = _base(frame)
            self._opened(side, frame)
            link.stats.frames += base
            side.counts.sent += base
            link.stats.frames_lost += base
            self._tapped(link, side_index, frame, time.time(), lost=True)

    def _opened(self, side: _Side, frame: bytes) -> None:
        """With ``await_open``: a lone delimiter from a side is its module's first write after
        opening its port (dh2rt's serial transport sends one on attach; the open flushed what
        was in the pty before): from now on it reads. Frames due for it before were lost."""
        if self.await_open and side.reader_gone and frame == b"\x00":
            side.reader_gone = False

    def _lose_queued(self, which: Callable[[_Piece], bool]) -> None:
        """Take the pieces ``which`` picks off the line: their frames are lost (under the lock)."""
        kept = []
        for item in self._queue:
            piece = item[3]
            if not which(piece):
                kept.append(item)
                continue
            link = self._links[piece.link_id]
            link.stats.frames_lost += piece.base
            link.stats.bytes_discarded += len(piece.data)
            self._tapped(link, piece.side, piece.data, piece.sent_at, lost=True)
        self._queue[:] = kept
        heapq.heapify(self._queue)

    def _read_out(self, link: EmulatedLink, side: _Side) -> None:
        """Read what is left in ``side``'s pty (its reader is gone): unread chunks (under the lock)."""
        left = _chunk_ends(_read_all(side.slave, nonblocking=True), True)[0]
        link.stats.frames_unread += left
        side.counts.unread += left
        side.fresh = True  # a next reader starts at a chunk's start

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

    def _tapped(self, link: EmulatedLink, side: int, wire: bytes, sent_at: float, *, lost: bool) -> None:
        if self.tap is not None and wire and wire != b"\x00":
            self.tap(sent_at, link.link_id, side, wire, lost)

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

    def _schedule(self, link: EmulatedLink, target: int, piece: _Piece, now: float, imp: Impairments) -> None:
        if not piece.data:  # every byte of it lost: nothing reaches the receiver
            self._written(link, link.sides[1 - piece.side], piece, b"", b"")
            return
        delay = imp.latency + (self._rng.uniform(0.0, imp.jitter) if imp.jitter else 0.0)
        now = self._on_line(target, len(piece.data), now, imp)
        # Keep order per direction: never schedule before what is already queued for target.
        due = now + delay
        for item in self._queue:
            if item[2] == target and item[0] > due:
                due = item[0]
        heapq.heappush(self._queue, (due, next(self._order), target, piece))

    def _deliver_due(self) -> None:
        now = time.monotonic()
        while True:
            with self._lock:
                if not self._queue or self._queue[0][0] > now:
                    return
                _, _, target, piece = heapq.heappop(self._queue)
                link = self._links.get(piece.link_id)
                if link is None:
                    return
                receiver = link.sides[1 - piece.side]
                if not link.docked or receiver.reader_gone:  # nobody there to read it: lost
                    link.stats.bytes_discarded += len(piece.data)
                    link.stats.frames_lost += piece.base
                    self._tapped(link, piece.side, piece.data, piece.sent_at, lost=True)
                    continue
                # written under the lock, so that reader_gone() reads out all that was written
                try:
                    n = os.write(target, piece.data)
                except (BlockingIOError, OSError):
                    n = 0
                link.stats.bytes_relayed += n
                link.stats.bytes_discarded += len(piece.data) - n
                self._written(link, receiver, piece, piece.data[:n], piece.data[n:])

    def _written(self, link: EmulatedLink, receiver: _Side, piece: _Piece, written: bytes, refused: bytes) -> None:
        """Count what ``piece`` became in the receiver's stream (under the lock): the chunks its
        delimiters end there, against the one frame it was (see the module docs)."""
        ends, receiver.fresh = _chunk_ends(written, receiver.fresh)
        stats = link.stats
        stats.frames_delivered += ends
        receiver.counts.written += ends
        if ends > piece.base:
            stats.frames_split += ends - piece.base
        elif ends < piece.base and (refused or not piece.data):  # never whole in the pty (full), or no byte left
            stats.frames_lost += piece.base - ends
        elif ends < piece.base:  # its delimiter destroyed: it joins the next chunk
            stats.frames_merged += piece.base - ends
        lost = bool(piece.base) and not ends and bool(refused or not piece.data)
        # a delivered frame is stamped as it reaches the receiver (a tap at the receiving
        # end, as a CAN capture's bus stamps it): one read from its sender and held up here
        # before it was written (this process descheduled) is stamped late, not early, and a
        # receiver never reads a frame stamped after it read it; a lost one when it was sent
        self._tapped(link, piece.side, piece.data, piece.sent_at if lost else time.time(), lost=lost)


def _base(frame: bytes) -> int:
    """1 for a frame (bytes ended by a delimiter), 0 for a lone delimiter or undelimited bytes."""
    return 1 if len(frame) > 1 and frame[-1] == 0 else 0


def _chunk_ends(data: bytes, fresh: bool) -> tuple[int, bool]:
    """How many chunks the delimiters in ``data`` end for a decoder (an empty chunk, two
    delimiters in a row, is none), given whether the stream before was at a chunk's start;
    and whether it is after ``data``."""
    parts = data.split(b"\x00")
    ends = sum(1 for i, part in enumerate(parts[:-1]) if part or (i == 0 and not fresh))
    return ends, (data[-1] == 0) if data else fresh


def _read_all(fd: int, *, nonblocking: bool = False) -> bytes:
    """Everything ``fd`` holds now (a pty end nobody else reads any more)."""
    if nonblocking:
        os.set_blocking(fd, False)
    out = bytearray()
    while True:
        try:
            data = os.read(fd, 4096)
        except OSError:  # nothing more now (EAGAIN), or nobody at the other end (EIO)
            break
        if not data:
            break
        out += data
    return bytes(out)


def _open_side(unopened: bool) -> _Side:
    return _Side(*open_raw_pty(), reader_gone=unopened)


def held_within(holds: Iterable[tuple[float, float]], start: float, end: float) -> float:
    """How long, between ``start`` and ``end`` (CLOCK_MONOTONIC), the relay was held: what a
    frame crossing then waited on top of its line time (``holds`` from :meth:`LinkEmulator.holds`)."""
    return sum(max(0.0, min(ended, end) - max(ended - seconds, start)) for ended, seconds in holds)
