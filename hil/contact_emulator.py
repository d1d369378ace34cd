"""The contact emulator: the connectors' local signals (CONRO's infrared pairs), as ptys.

The world side of :class:`drivers.connector_channel.PtyConnectorChannel`, as the link emulator
is the world side of the serial links. Each connector of each module gets a pty pair
(:meth:`ContactEmulator.add_connector` returns the path its module opens); the world's physics
says which connectors touch (:meth:`~ContactEmulator.make_contact`,
:meth:`~ContactEmulator.break_contact`, with whether they line up), and the emulator

* tells both modules in CONTACT frames, and answers a module's QUERY frame (sent when it opens
  its port) with its connector's contact, so a restarted module learns it at once;
* relays DATA frames between two connectors only while they touch *and* line up; a DATA frame
  from a connector in no such contact goes nowhere (counted ``discarded``);
* may lose whole DATA frames (``frame_loss``) and flip bits of the relayed ones (``bit_error``,
  a probability per bit), from one ``random.Random(seed)``. CONTACT frames are the physics'
  word and are never impaired.

The frames are those of :mod:`drivers.connector_channel` (dh2rt's serial framing around a kind
byte). One relay thread reads every master through a selector; CONTACT frames are written by
the caller's thread under the same lock, so after :meth:`~ContactEmulator.break_contact`
returns, no DATA frame of the old contact reaches either module after their CONTACT frame.
``close()`` stops the thread and closes every fd; close the modules' ports first (a slave whose
master is gone reads EIO).
"""

from __future__ import annotations

import os
import random
import threading
from dataclasses import dataclass, field, replace

from dh2rt.closing import Closing
from dh2rt.errors import ContactEmulatorError, FrameCorrupted
from dh2rt.wire.serial_framing import SerialDecoder
from drivers.connector_channel import (
    ContactFrame,
    DataFrame,
    LocalFrame,
    QueryFrame,
    decode_local,
    encode_local,
    local_decoder,
)
from hil.ptys import PtyRelay, close_fd, open_raw_pty

#: A connector of a module: ``(module, connector)``.
End = tuple[int, int]


@dataclass(slots=True)
class ContactStats:
    """Counts for one connector (frames from its module, and what became of them)."""

    data_frames: int = 0  # DATA frames its module sent
    relayed: int = 0  # of them, delivered to the connector it touches
    lost: int = 0  # dropped by frame_loss
    discarded: int = 0  # sent out of contact (or out of line), or refused by a full pty
    bits_flipped: int = 0  # bits flipped in its relayed frames
    malformed: int = 0  # frames from its module that do not decode, or are not DATA or QUERY
    contact_frames: int = 0  # CONTACT frames sent to its module


@dataclass(slots=True)
class _Connector:
    end: End
    master: int
    slave: int
    path: str
    decoder: SerialDecoder = field(default_factory=local_decoder)
    stats: ContactStats = field(default_factory=ContactStats)
    partner: End | None = None
    aligned: bool = False
    bad_kinds: int = 0
    resync: bool = True  # a delimiter before the next frame (the first one, or after a cut one)

    @property
    def contact(self) -> ContactFrame:
        return ContactFrame(self.partner is not None, self.partner is not None and self.aligned)


class ContactEmulator(Closing):
    """Plays every connector's local signal from what the physics says touches what."""

    def __init__(self, *, frame_loss: float = 0.0, bit_error: float = 0.0, seed: int | None = None) -> None:
        for name, value in (("frame_loss", frame_loss), ("bit_error", bit_error)):
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"contact emulator: {name}={value} is not a probability in [0, 1]")
        self.frame_loss = frame_loss
        self.bit_error = bit_error
        self._rng = random.Random(seed)
        self._lock = threading.Lock()
        self._connectors: dict[End, _Connector] = {}
        self._by_master: dict[int, _Connector] = {}
        self._ptys = PtyRelay("dh2rt-contact-emulator", self._lock, self._from_master)

    # -- connectors and contacts ----------------------------------------------------------------

    def add_connector(self, module: int, connector: int) -> str:
        """A pty pair for ``connector`` of ``module``; the path its module opens."""
        end = (module, connector)
        with self._lock:
            if self._ptys.closed:
                raise ContactEmulatorError("contact emulator is closed")
            if end in self._connectors:
                raise ContactEmulatorError(f"contact emulator: connector {end} already exists")
            master, slave, path = open_raw_pty()
            conn = _Connector(end, master, slave, path)
            self._connectors[end] = conn
            self._by_master[master] = conn
            self._ptys.watch(master)
        return conn.path

    def path(self, end: End) -> str:
        return self._connector(end).path

    def partner(self, end: End) -> End | None:
        """The connector ``end`` touches, if any."""
        with self._lock:
            return self._connector(end).partner

    def make_contact(self, a: End, b: End, *, aligned: bool = True) -> None:
        """``a`` and ``b`` touch (and line up, with ``aligned``): both modules are told. For two
        connectors already touching, a new alignment (told only if it changed)."""
        with self._lock:
            ca, cb = self._connector(a), self._connector(b)
            if a == b:
                raise ContactEmulatorError(f"contact emulator: connector {a} cannot touch itself")
            for conn, other in ((ca, b), (cb, a)):
                if conn.partner not in (None, other):
                    raise ContactEmulatorError(
                        f"contact emulator: {conn.end} touches {conn.partner}; "
                        f"break that contact before touching {other}"
                    )
            if ca.partner == b and ca.aligned == aligned:
                return
            for conn, other in ((ca, b), (cb, a)):
                conn.partner, conn.aligned = other, aligned
                self._tell_contact(conn)

    def break_contact(self, a: End, b: End) -> None:
        """``a`` and ``b`` no longer touch: both modules are told, and DATA stops flowing."""
        with self._lock:
            ca, cb = self._connector(a), self._connector(b)
            if ca.partner != b:
                raise ContactEmulatorError(f"contact emulator: {a} and {b} are not in contact")
            for conn in (ca, cb):
                conn.partner, conn.aligned = None, False
                self._tell_contact(conn)

    def stats(self, end: End) -> ContactStats:
        with self._lock:
            return replace(self._connector(end).stats)

    def inject(self, end: End, data: bytes) -> None:
        """Write raw bytes towards the module at ``end`` (tests: noise, foreign frames)."""
        with self._lock:
            os.write(self._connector(end).master, bytes(data))

    def _connector(self, end: End) -> _Connector:
        try:
            return self._connectors[end]
        except KeyError:
            raise ContactEmulatorError(f"contact emulator: no connector {end}") from None

    # -- lifecycle ------------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the relay thread and close every pty; idempotent."""
        if not self._ptys.stop():
            return
        for conn in self._connectors.values():
            close_fd(conn.master)
            close_fd(conn.slave)
        self._connectors.clear()
        self._by_master.clear()

    # -- the relay thread (and what it shares with the callers, under the lock) ---------------

    def _from_master(self, fd: int, data: bytes) -> None:
        with self._lock:
            conn = self._by_master.get(fd)
            if conn is not None and not self._ptys.closed:
                self._from_module(conn, data)

    def _from_module(self, conn: _Connector, data: bytes) -> None:
        for payload in conn.decoder.feed(data):
            try:
                frame: LocalFrame | None = decode_local(payload)
            except FrameCorrupted:
                frame = None
            if isinstance(frame, DataFrame):
                self._relay(conn, frame)
            elif isinstance(frame, QueryFrame):
                self._tell_contact(conn)
            else:  # undecodable, or a CONTACT frame (only the world sends those)
                conn.bad_kinds += 1
        conn.stats.malformed = conn.decoder.corrupted + conn.decoder.dropped + conn.bad_kinds

    def _relay(self, conn: _Connector, frame: DataFrame) -> None:
        conn.stats.data_frames += 1
        peer = self._connectors.get(conn.partner) if conn.partner is not None and conn.aligned else None
        if peer is None:
            conn.stats.discarded += 1
        elif self.frame_loss and self._rng.random() < self.frame_loss:
            conn.stats.lost += 1
        elif self._write(peer, self._garble(conn, encode_local(frame))):
            conn.stats.relayed += 1
        else:
            conn.stats.discarded += 1

    def _garble(self, conn: _Connector, wire: bytes) -> bytes:
        if not self.bit_error:
            return wire
        out = bytearray(wire)
        for i in range(len(out) * 8):
            if self._rng.random() < self.bit_error:
                out[i // 8] ^= 1 << (i % 8)
                conn.stats.bits_flipped += 1
        return bytes(out)

    def _tell_contact(self, conn: _Connector) -> None:
        self._write(conn, encode_local(conn.contact))
        conn.stats.contact_frames += 1

    @staticmethod
    def _write(conn: _Connector, frame: bytes) -> bool:
        """Write one frame to ``conn``'s module whole, without blocking (see _SerialChannel._write)."""
        wire = b"\x00" + frame if conn.resync else frame
        try:
            written = os.write(conn.master, wire)
        except OSError:  # full (EAGAIN), or the pty is gone
            written = 0
        conn.resync = written != len(wire)
        return not conn.resync
