"""A chain member's side of a docking motion (sans-IO): what a module does with the motion
frames (:mod:`dh2rt.wire.motion`) that reach it, whoever asks.

* An outward frame (ASK, TARGETS, END) must come in where its route says, or it is dropped
  (counted ``off_route``). One whose route goes further is passed on through the route's
  next connector, one hop further (``relayed``); the module at the route's end takes it.
* Taken frames of a motion must be newer than the newest taken of that motion (its ``seq``,
  compared as 16-bit serial numbers); others are dropped (``stale``): a late TARGETS never
  undoes a later one, and a late one of a motion that ended never takes the joints again.
* ASK: the module answers with ANGLES, back along the route: its index, the angles it
  measures of its own joints (its :class:`Body`: the servos' present positions) and its
  links (for each connector, the peer's connector linked there), so that the asker can
  route on to the next module.
* TARGETS: the module holds them on its servos from its next cycle, in place of its
  program's DOF1/DOF2 (as the loop's ``Hold`` did: :attr:`held`).
* END, or no frame of the motion it holds for :data:`IDLE_CYCLES` of its own cycles: the
  joints are its program's again. The asker sends each member a frame every cycle a motion
  lasts; a member that hears nothing for that long has lost its asker (it died, or a link of
  the route went), and a module must not stay bent in a pose nobody steers.
* ANGLES going back are passed on one hop nearer the asker; one with no hop left is the
  asker's own (:attr:`reports`, for :class:`firmware.motion.asker.Asker`).

Frames out are :class:`Out` (the caller sends each through its connector); the module's own
cycle is passed in, never read from a clock.
"""

from __future__ import annotations

from collections import Counter, OrderedDict
from collections.abc import Callable
from typing import Protocol

from dh2rt.errors import DecodeError, EncodeError
from dh2rt.wire import motion as mw
from firmware.outbound import Out

#: Cycles a member holds targets with no frame of their motion before it gives its joints
#: back. The asker writes to every member each cycle; liveness declares a silent link dead
#: after 3 (``dh2rt.liveness.SILENCE_CYCLES``), and a frame of a long route crosses a hop a
#: cycle: 10 is past both for a 4-hop chain, and short enough (a second at CONRO's 100 ms
#: cycle) that a member of a dead asker does not stand bent for long.
IDLE_CYCLES = 10
#: Motions whose newest seq a member remembers (so that late frames of an ended one stay
#: ignored); the oldest is forgotten first.
REMEMBERED = 16


class Body(Protocol):
    """What a member reports of itself when asked."""

    def angles(self) -> tuple[float, ...]:
        """Its joints' angles as it measures them (degrees, DOF1 first)."""
        ...

    def links(self) -> tuple[int, ...]:
        """For each of its connectors, the peer's connector linked there (0: none)."""
        ...


class Member:
    """One module's side of the motions of the chains it is part of."""

    def __init__(
        self,
        module: int,
        body: Body,
        log: Callable[[str], None] = lambda line: None,
        idle_cycles: int = IDLE_CYCLES,
        attitude: Callable[[], tuple[float, float] | None] = lambda: None,
    ) -> None:
        self.module = module
        self.body = body
        #: its own IMU (roll, pitch, degrees), None without one: an ANGLES carries it after
        #: the joints' angles (the asker plans with a target's tilt: firmware.motion.reach)
        self.attitude = attitude
        self.log = log
        self.idle_cycles = idle_cycles
        #: Joint targets (degrees by DOF index) its servos hold in place of the program's;
        #: empty: the joints are the program's.
        self.held: dict[int, float] = {}
        #: The motion whose targets it holds, and the cycle its last frame came.
        self.holding: int | None = None
        self.heard = 0
        #: Reports for this module as the asker (ANGLES with no hop left), oldest first.
        self.reports: list[mw.Angles] = []
        self._seen: OrderedDict[int, int] = OrderedDict()
        self.counts: Counter[str] = Counter()
        #: the last SET_OFF this module took (it is the foot of a ``reach_and_dock``), until
        #: its owner takes it (:mod:`firmware.motion.foot`)
        self.set_off: mw.SetOff | None = None

    def received(self, connector: int, payload: bytes, cycle: int) -> list[Out]:
        """A motion frame came in at ``connector`` in this module's cycle ``cycle``: what to
        send on or in answer."""
        try:
            sender, message = mw.decode(payload)
        except DecodeError as exc:
            self.counts["malformed"] += 1
            self.log(f"motion: a frame at connector {connector} does not decode: {exc}")
            return []
        if isinstance(message, mw.Angles):
            return self._report(connector, sender, message)
        hops, route = message.hops, message.route
        if hops == 0 or route[hops - 1] != (sender, connector):
            self.counts["off_route"] += 1
            return []
        if hops < len(route):
            self.counts["relayed"] += 1
            through = route[hops][0]
            return [Out(through, mw.encode(through, mw.onward(message)))]
        if not mw.newer(message.seq, self._seen.get(message.motion)):
            self.counts["stale"] += 1
            return []
        self._remember(message.motion, message.seq)
        self.counts[type(message).__name__.lower()] += 1
        if isinstance(message, mw.End):
            if self.holding == message.motion:
                self._give_back(f"motion {message.motion} ended")
            return []
        if isinstance(message, mw.SetOff):
            self.set_off = message  # the foot's hand-over: firmware.motion.foot runs it
            return []
        if isinstance(message, mw.Targets):
            if self.holding != message.motion:
                self.log(f"motion: holding targets of motion {message.motion}")
            self.holding, self.heard = message.motion, cycle
            self.held = dict(message.targets)
            return []
        if self.holding == message.motion:
            self.heard = cycle
        try:
            body = self.body
            tilt = self.attitude()
            angles = body.angles() + (() if tilt is None else tuple(tilt))
            answer = mw.Angles(message.motion, message.seq, route, self.module, angles, body.links(), len(route) - 1)
            return [Out(connector, mw.encode(connector, answer))]
        except EncodeError as exc:
            self.log(f"motion: cannot answer motion {message.motion}: {exc}")
            return []

    def cycle(self, cycle: int) -> None:
        """Once per cycle, before the joints are written: give the joints back if the motion
        holding them went silent."""
        if self.holding is not None and cycle - self.heard > self.idle_cycles:
            self.counts["timed_out"] += 1
            self._give_back(f"no frame of motion {self.holding} for {cycle - self.heard} cycles")

    def _report(self, connector: int, sender: int, message: mw.Angles) -> list[Out]:
        left, route = message.left, message.route
        if left >= len(route) or route[left] != (connector, sender):
            self.counts["off_route"] += 1
            return []
        if left == 0:
            self.reports.append(message)
            return []
        self.counts["relayed"] += 1
        through = route[left - 1][1]
        return [Out(through, mw.encode(through, mw.back(message)))]

    def _give_back(self, why: str) -> None:
        self.log(f"motion: joints back to the program ({why})")
        self.held, self.holding = {}, None

    def _remember(self, motion: int, seq: int) -> None:
        self._seen[motion] = seq
        self._seen.move_to_end(motion)
        while len(self._seen) > REMEMBERED:
            self._seen.popitem(last=False)
