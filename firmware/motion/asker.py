"""The asking module's side of a docking motion (sans-IO): it learns its chain and talks to it
over the links, in motion frames (:mod:`dh2rt.wire.motion`); :class:`firmware.motion.member.Member`
is the other side.

The program's ``reach_dock(path, mine, theirs)`` gives the route as the connector to leave
through at each hop; a motion frame's route also names where each hop arrives. The asker
knows its own links (the peer's connector at each of its connectors, from its neighbours'
frames), so it knows the first hop; each member's ANGLES carries that member's links, so
the chain is learnt a hop a round trip (:attr:`Asker.known` once every member answered).

Each cycle (:meth:`Asker.frames`) it asks every member it knows for its angles and sends the
members it moves their targets; a member's latest ANGLES is its reading (:attr:`Known.angles`,
with the cycle it came in). An ASK that is not answered within :data:`ANSWER_CYCLES` is
counted lost (``unanswered``) and forgotten: the member's previous reading stands until the
next answer, and the next cycle's ASK asks again. An ANGLES for an ASK forgotten, or of
another motion, is dropped (``stale``). A member that answers nothing for
:data:`SILENT_CYCLES` no longer runs as far as the motion is concerned (:meth:`Asker.running`):
the sequence abandons the motion, as it does for a module that died.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from dh2rt.wire import motion as mw
from dh2rt.wire.fields import Path
from firmware.motion.member import IDLE_CYCLES
from firmware.outbound import Out

#: Cycles an ASK waits for its answer before it is counted lost: a frame crosses a hop a
#: cycle at worst (a module reads its links once a cycle), so a member k hops out answers
#: within 2k cycles; 2 * 8 covers the longest chain CONRO's docking asks for, with a margin.
ANSWER_CYCLES = 16
#: Cycles without an answer after which a member counts as stopped: the member itself gives
#: its joints back after IDLE_CYCLES without a frame, so the asker must not steer it longer.
SILENT_CYCLES = IDLE_CYCLES + ANSWER_CYCLES


@dataclass
class Known:
    """A member of the chain as the asker knows it."""

    route: Path
    #: its index, the angles it measured, its links, and the cycle its last answer came in
    #: (None: none yet)
    module: int | None = None
    angles: tuple[float, ...] = ()
    links: tuple[int, ...] = ()
    answered: int | None = None

    @property
    def attitude(self) -> tuple[float, float] | None:
        """Its IMU's roll and pitch (degrees), which an ANGLES carries after the joints' two
        angles when the member has one; None if it did not."""
        return (self.angles[2], self.angles[3]) if len(self.angles) >= 4 else None


@dataclass
class Asker:
    """One motion's frames, from the asking module's side (module docs)."""

    motion: int
    #: the asking module's index and links (the peer's connector at each of its connectors)
    me: int
    my_links: tuple[int, ...]
    #: the connector to leave through at each hop, the program's ``reach_dock`` path
    route: tuple[int, ...]
    started: int
    log: Callable[[str], None] = lambda line: None
    members: list[Known] = field(default_factory=list)
    counts: Counter[str] = field(default_factory=Counter)
    seq: int = 0
    #: seq of each ASK in flight -> (the member's place in :attr:`members`, the cycle it went)
    asked: dict[int, tuple[int, int]] = field(default_factory=dict)
    #: what went out in each cycle, for the link load: cycle -> [frames, bytes]
    sent: dict[int, list[int]] = field(default_factory=dict)
    #: the route ended before its last hop: a member's link for the next hop is down (a
    #: route as far as it goes, such as the body up a robot: :attr:`learnt`)
    short: bool = False

    def __post_init__(self) -> None:
        if not self.route:
            raise ValueError("a motion's route has at least one hop")
        first = self.route[0]
        received = self.my_links[first - 1] if first <= len(self.my_links) else 0
        if not received:
            raise ValueError(f"the route leaves through connector {first}, which has no link")
        self.members.append(Known(((first, received),)))

    @property
    def known(self) -> bool:
        """Every member of the chain answered at least once."""
        return len(self.members) == len(self.route) and all(m.answered is not None for m in self.members)

    @property
    def learnt(self) -> bool:
        """Every member there is answered: :attr:`known`, or the route ended :attr:`short`."""
        return self.known or (self.short and all(m.answered is not None for m in self.members))

    def member(self, module: int) -> Known | None:
        return next((m for m in self.members if m.module == module), None)

    def running(self, module: int, cycle: int) -> bool:
        """Whether ``module`` (the asker, or a member that answered) still answers."""
        if module == self.me:
            return True
        m = self.member(module)
        last = None if m is None else m.answered
        return last is not None and cycle - last <= SILENT_CYCLES

    def peer_of(self, module: int, connector: int) -> tuple[int, int] | None:
        """The chain's links as the asker knows them: the peer (module, connector) at
        ``module``'s ``connector``; a module outside the chain is -1 (linked, not named)."""
        if module == self.me:
            links, hop = self.my_links, 0
        else:
            place = next((i for i, m in enumerate(self.members) if m.module == module), None)
            if place is None:
                return None
            links, hop = self.members[place].links, place + 1
        remote = links[connector - 1] if connector <= len(links) else 0
        if not remote:
            return None
        if hop < len(self.route) and connector == self.route[hop] and hop < len(self.members):
            onward = self.members[hop].module
            return (-1 if onward is None else onward), remote
        return -1, remote

    def frames(self, cycle: int, targets: Mapping[int, Mapping[int, float]] = {}, *, ask: bool = True) -> list[Out]:
        """This cycle's frames: an ASK to every member known (none unless ``ask``), TARGETS to
        each member ``targets`` names (by module index; the asker's own are not sent)."""
        for seq, (_, at) in list(self.asked.items()):
            if cycle - at > ANSWER_CYCLES:
                del self.asked[seq]
                self.counts["unanswered"] += 1
        out = []
        for place, m in enumerate(self.members if ask else ()):
            seq = self._next()
            self.asked[seq] = (place, cycle)
            out.append(self._out(mw.Ask(self.motion, seq, m.route)))
        for module, dofs in sorted(targets.items()):
            moved = self.member(module)
            if moved is None or not dofs:
                continue
            held = tuple(sorted((dof, round(v, 2)) for dof, v in dofs.items()))
            out.append(self._out(mw.Targets(self.motion, self._next(), moved.route, held)))
        self._count(cycle, out)
        return out

    def set_off(self, cycle: int, target: int, connector: int, body: Sequence[int], others: Sequence[int]) -> Out:
        """The SET_OFF to the route's last member (a foot about to let go:
        :class:`firmware.motion.foot.Foot`): come to ``connector`` of module ``target``."""
        last = self.members[-1]
        out = self._out(mw.SetOff(self.motion, self._next(), last.route, target, connector, tuple(body), tuple(others)))
        self._count(cycle, [out])
        return out

    def end(self, cycle: int) -> list[Out]:
        """END to every member: their joints are their programs' again."""
        out = [self._out(mw.End(self.motion, self._next(), m.route)) for m in self.members]
        self._count(cycle, out)
        return out

    def received(self, report: mw.Angles, cycle: int) -> None:
        """An ANGLES that came back to the asker."""
        entry = self.asked.pop(report.seq, None) if report.motion == self.motion else None
        if entry is None or self.members[entry[0]].route != report.route:
            self.counts["stale"] += 1
            return
        place = entry[0]
        m = self.members[place]
        m.module, m.angles, m.links, m.answered = report.module, report.angles, report.links, cycle
        self.counts["answered"] += 1
        hop = place + 1
        if hop == len(self.members) and hop < len(self.route):  # learn the next hop
            c = self.route[hop]
            remote = report.links[c - 1] if c <= len(report.links) else 0
            if remote:
                self.members.append(Known((*m.route, (c, remote))))
            elif not self.short:
                self.short = True
                self.log(f"motion {self.motion}: the route leaves module {report.module} through {c}, not linked")

    def _next(self) -> int:
        seq, self.seq = self.seq, mw.next_seq(self.seq)
        return seq

    def _out(self, message: mw.Outward) -> Out:
        through = message.route[0][0]
        return Out(through, mw.encode(through, mw.onward(message)))

    def _count(self, cycle: int, out: Sequence[Out]) -> None:
        load = self.sent.setdefault(cycle, [0, 0])
        load[0] += len(out)
        load[1] += sum(len(o.frame) for o in out)
