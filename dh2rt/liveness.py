"""Who is on the other side of each connector, and whether it is still there: a sans-IO
state machine (frames and cycle ticks in; verdicts, silent connectors and beacons out).

It does no I/O and knows no engine: :class:`~dh2rt.runtime.ModuleRuntime` feeds it every
frame it receives and ticks it once per cycle, then carries out what it says (sets
ConnectorStatus, sends the beacons). Tested on its own in ``tests/dh2rt/test_liveness.py``.

Per attached connector::

    unverified --Hello(same digest)--> verified --silent for `silence_cycles` cycles--> unverified
        |  ^                              |
        |  +------Hello(same digest)------+ (answered with our Hello once per silence_cycles
        |                                    cycles, or at once when the peer said Hello twice
        |                                    since ours: it has not heard us; two peers never
        |                                    ping-pong)
        +--Hello(other digest)--> refused (frames ignored; status 0) --Hello(same)--> verified
        +--Hello(NO_PROGRAM)--> a tool (a programming cable: frames ignored, status 0, not
                                counted as refused; settled like a verified peer)

- Hello: carries the sender's program digest. A peer running another program is refused
  rather than fed hormones whose indices it would misread.
- Any frame through a verified connector counts as heard (and sets ConnectorStatus).
  Frames through an unverified connector are ignored and counted.
- KeepAlives are numbered per connector: a gap in the numbers is a beacon the link lost.
- Liveness bound: a connector heard nothing from for ``silence_cycles`` consecutive cycles
  falls to 0 (if it was up) and must be verified again by a Hello.
- Beacons: each cycle every attached connector that carried no hormone sends a KeepAlive,
  or a Hello while its peer is unverified or a Hello answer is due.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import NamedTuple

from dh2rt.wire.frame import NO_PROGRAM, Frame, Hello, KeepAlive

#: Consecutive silent cycles after which a linked connector falls to 0.
SILENCE_CYCLES = 3
#: The peer's Hellos since our last one that show it has not heard ours: answered at once.
#: Two, not one: a peer answering our Hello says it once, and is not answered back (no
#: ping-pong). Found in the loop (snake to quadruped with the latch emulator): a module's
#: first Hello on a new link was lost (the peer's end was not attached yet); the peer said
#: Hello for 7 cycles, unanswered within ``silence_cycles``, and dropped the hormone (LEG)
#: sent meanwhile; the program waited for it for ever.
REPEATED_HELLOS = 2


class Verdict(enum.Enum):
    """What a received frame means for its connector."""

    HEARD = "heard"  # from a verified peer: the connector is linked, reset its silence
    IGNORED = "ignored"  # through an unverified connector (counted)
    REFUSED = "refused"  # a Hello from a peer running another program: status must fall to 0
    TOOL = "tool"  # a Hello from a peer that runs no program (a programming cable): status 0
    UNATTACHED = "unattached"  # through a connector that is not attached (not counted)


class Beacon(NamedTuple):
    """A frame to send through a connector this cycle."""

    connector: int
    frame: Hello | KeepAlive


@dataclass(slots=True)
class _Link:
    """What is known of one attached connector."""

    verified: bool = False
    refused: bool = False
    tool: bool = False  # the peer said it runs no program (a programming cable)
    silent: int = 0
    last_hello: int = -(10**9)  # cycle a counted Hello last went out
    hello_due: bool = True
    hellos_in: int = 0  # the peer's Hellos since our last one
    digest: bytes | None = None  # the program digest of the peer's last accepted Hello
    seq_out: int = 0
    seq_in: int | None = None  # last KeepAlive sequence number heard


@dataclass(slots=True)
class LivenessCounters:
    refused: int = 0
    ignored: int = 0
    links_lost: int = 0
    beacons_missed: int = 0


class Liveness:
    """The liveness of one module's connectors (see the module docs)."""

    def __init__(self, digest: bytes, silence_cycles: int = SILENCE_CYCLES) -> None:
        if silence_cycles < 1:
            raise ValueError(f"silence_cycles {silence_cycles!r} must be at least 1")
        self.digest = digest
        #: the program version this module's Hellos state (None: 7-byte Hellos without one)
        self.version: int | None = None
        #: other program digests accepted from a neighbour for now (a rollout's switch window,
        #: ``dh2rt.flash.rollout.Rollout.tolerated``); its frames are heard but not its hormones
        self.tolerated: frozenset[bytes] = frozenset()
        self.silence_cycles = silence_cycles
        self.counters = LivenessCounters()
        self._links: dict[int, _Link] = {}

    # ------------------------------------------------------------ connectors

    def attach(self, connector: int) -> None:
        """A connector was attached: its next beacon is a Hello announcing this module's
        program. Not one at once: the peer may not listen yet, and a frame sent to nobody is
        a frame nobody can account for."""
        self._links[connector] = _Link()

    def detach(self, connector: int) -> None:
        self._links.pop(connector, None)

    @property
    def connectors(self) -> list[int]:
        return list(self._links)

    def verified(self, connector: int) -> bool:
        link = self._links.get(connector)
        return link is not None and link.verified

    def foreign(self, connector: int) -> bool:
        """The peer on ``connector`` was verified on a tolerated program, not this one: its
        hormones may mean other hormones here (drop them; its frames still count as heard)."""
        link = self._links.get(connector)
        return link is not None and link.digest is not None and link.digest != self.digest

    def announce(self, digest: bytes, version: int | None) -> None:
        """This module now runs another program: every peer is told by a Hello at the next
        beacon (the host may also send one at once), and peers whose last Hello named another
        program count as foreign until they say Hello on this one."""
        self.digest, self.version = digest, version
        for link in self._links.values():
            link.hello_due = True

    def refused(self, connector: int) -> bool:
        link = self._links.get(connector)
        return link is not None and link.refused

    @property
    def settled(self) -> bool:
        """Every attached connector's peer was verified or refused, or is a tool."""
        return all(link.verified or link.refused or link.tool for link in self._links.values())

    # ------------------------------------------------------------ frames in

    def receive(self, connector: int, frame: Frame, cycle: int) -> Verdict:
        """Account for one frame received through ``connector`` during ``cycle``."""
        link = self._links.get(connector)
        if link is None:
            return Verdict.UNATTACHED
        if isinstance(frame, Hello) and frame.digest == NO_PROGRAM:
            link.tool, link.verified, link.refused = True, False, False
            return Verdict.TOOL
        if isinstance(frame, Hello):
            link.tool = False
            foreign = frame.digest != self.digest
            if foreign and frame.digest not in self.tolerated:
                link.refused = True
                link.verified = False
                self.counters.refused += 1
                return Verdict.REFUSED
            link.digest = frame.digest
            link.refused = False
            link.seq_in = None  # a (re)started peer numbers its beacons afresh
            link.hellos_in += 1
            if cycle - link.last_hello >= self.silence_cycles or link.hellos_in >= REPEATED_HELLOS:
                # the peer may not have heard us (it (re)started, or our Hello was lost: a
                # peer that says Hello again since ours has not heard it, and drops every
                # hormone we send until it does)
                link.hello_due = True
            link.verified = True
            return Verdict.HEARD
        if not link.verified:
            self.counters.ignored += 1
            return Verdict.IGNORED
        if isinstance(frame, KeepAlive):
            if link.seq_in is not None:
                self.counters.beacons_missed += (frame.seq - link.seq_in - 1) & 0xFF
            link.seq_in = frame.seq
        return Verdict.HEARD

    # ------------------------------------------------------------ once per cycle

    def tick(self, heard: set[int], linked: set[int]) -> list[tuple[int, int]]:
        """The liveness step of a cycle. ``heard``: connectors that had a HEARD frame since
        the last tick; ``linked``: connectors whose ConnectorStatus is not 0 now.

        Returns ``(connector, silent cycles)`` for each linked connector that has now been
        silent for ``silence_cycles`` cycles: its status must fall to 0, and its peer must
        announce itself again before it is heard."""
        lost: list[tuple[int, int]] = []
        for c, link in self._links.items():
            if c in heard:
                link.silent = 0
                continue
            link.silent += 1
            if link.silent >= self.silence_cycles and c in linked:
                self.counters.links_lost += 1
                link.verified = False
                link.seq_in = None
                link.hello_due = True
                lost.append((c, link.silent))
        return lost

    def beacons(self, carried: set[int], cycle: int) -> list[Beacon]:
        """What to send this cycle through every attached connector that carried no hormone:
        a Hello while the peer is unverified or an answer is due, else a KeepAlive."""
        out: list[Beacon] = []
        for c, link in self._links.items():
            if c in carried:
                continue
            if not link.verified or link.hello_due:
                link.last_hello = cycle
                link.hello_due = False
                link.hellos_in = 0
                out.append(Beacon(c, Hello(self.digest, self.version)))
            else:
                link.seq_out = (link.seq_out + 1) & 0xFF
                out.append(Beacon(c, KeepAlive(link.seq_out)))
        return out
