"""A ``reach_dock`` carried out by the module that asked for it (sans-IO): the docking sequence
(:class:`firmware.motion.docking.Docking`, the same the physics runner drives) run in the
asking module, its chain reached over the links (:class:`firmware.motion.asker.Asker`).

What it reads is what the asking module has: its own joints (its servos), its own
connectors' infrared pairs and IMU, the overhead tracker if it hears one
(:class:`OwnSenses`, filled by the module's host), and the chain's joint angles and links
from the members' ANGLES. What it writes: its own joints (:attr:`SelfReach.own_targets`,
the host holds them on its servos) and every other member's, as TARGETS.

The latch is not the module's yet (the latch driver is a later step of issue 28): the
module asks its world whether the latch closes now and to close it (:class:`LatchAsk`; in the
loop, over the control channel: ``hil.world.World``), as the physics runner's world answers
``Docking``. Everything else the world did for a ``reach_dock`` is the module's now.

Steps: the chain is learnt (a hop a round trip: :attr:`Asker.known`), at most
:data:`LEARN_CYCLES` cycles, then :meth:`Docking.start_reach` plans and each cycle
:meth:`Docking.step` moves; when the motion ends (latched, given up, or abandoned because a
member went silent) every member is sent END.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from dh2rt.docking import End
from dh2rt.profile import Profile
from dh2rt.wire import motion as mw
from firmware.motion.asker import Asker
from firmware.motion.body import ConroModel
from firmware.motion.docking import Docking, Options
from firmware.motion.readings import FloorPoses, Readings
from firmware.motion.underway import Motion, Needs
from firmware.outbound import Out

#: Cycles the chain may take to answer before the reach is given up: a hop a round trip, each
#: round trip up to two cycles a hop when a module reads its links once a cycle; a chain of 6
#: takes 2 * (1 + 2 + ... + 6) = 42 cycles at worst.
LEARN_CYCLES = 80


def learn_cycles(hops: int) -> int:
    """Cycles a chain of ``hops`` may take to answer: :data:`LEARN_CYCLES`, or for a longer
    chain its round trips at two cycles a hop each way (2 * (1 + ... + hops)) and 20 more."""
    return max(LEARN_CYCLES, hops * (hops + 1) + 20)


class OwnSenses(Protocol):
    """What the asking module senses of itself."""

    def angles(self) -> tuple[float, ...]:
        """Its joints (degrees, DOF1 first)."""
        ...

    def infrared(self) -> Mapping[str, float]:
        """Its infrared pairs: ``ir_<c>`` (mm) and ``ir_<c>_align`` (degrees), by name."""
        ...

    def floor(self) -> FloorPoses:
        """The overhead tracker's last report (empty: no tracker)."""
        ...

    def attitude(self) -> Mapping[int, tuple[float, float]]:
        """Its own IMU reading (roll, pitch, degrees), by its module index (empty: none).
        Another module's tilt comes from that module, in its ANGLES."""
        ...


class LatchAsk(Protocol):
    """The latch, asked of the world for now (module docs)."""

    def aligned(self, a: int, a_conn: int, b: int, b_conn: int) -> bool: ...

    def latch(self, a: int, a_conn: int, b: int, b_conn: int) -> bool: ...


class ModuleWorld:
    """The world and the owner a docking sequence (:class:`Docking`) sees when a module runs it:
    what the module has of the world (its chains' links and answers, its own senses) and its
    latch. Shared by :class:`SelfReach` and :class:`firmware.motion.assimilating.SelfAssimilate`,
    which say where the chain's links and angles come from (``peer_of``, ``running``,
    ``_member_angles``)."""

    cycle: int
    senses: OwnSenses
    latch_world: LatchAsk
    profile: Profile
    log: Callable[[str], None]

    @property
    def me(self) -> int:
        raise NotImplementedError

    def peer_of(self, end: End) -> End | None:
        raise NotImplementedError

    def running(self, module: int) -> bool:
        raise NotImplementedError

    def _member_angles(self, module: int) -> Sequence[float]:
        raise NotImplementedError

    def aligned(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        return self.latch_world.aligned(a, a_conn, b, b_conn)

    def latch(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        return self.latch_world.latch(a, a_conn, b, b_conn)

    def cut(self, module: int, connector: int) -> None:
        raise NotImplementedError("a module's reach cuts no link")

    def dock(self, a: int, a_conn: int, b: int, b_conn: int) -> None:
        raise NotImplementedError("a module's reach links only through the latch")

    def schedule(self, cycles_from_now: int, action: Callable[[], None]) -> None:
        raise NotImplementedError("the sequence schedules nothing")

    def where(self, module: int, connector: int) -> str:
        return f"m{module}.{self.profile.connector_name(connector)}"

    def note(self, message: str) -> None:
        self.log(message)

    # ------------------------------------------------------------ the owner: what it reads

    @property
    def now(self) -> int:
        return self.cycle

    def sense(self, cycle: int, needs: Needs) -> Readings:
        joints: dict[int, tuple[float, float]] = {}
        for m in needs.joints:
            angles = self.senses.angles() if m == self.me else self._member_angles(m)
            joints[m] = (angles[0], angles[1])
        infrared = {self.me: dict(self.senses.infrared())} if self.me in needs.infrared else {}
        floor = self.senses.floor() if needs.floor else FloorPoses()
        attitude = {}
        own = self.senses.attitude().get(self.me)
        for m in needs.attitude:
            tilt = own if m == self.me else self._member_attitude(m)
            if tilt is not None:
                attitude[m] = tilt
        return Readings(joints, infrared, floor, attitude)

    def _member_attitude(self, module: int) -> tuple[float, float] | None:
        """A member's IMU as its last ANGLES carried it (None: it carried none)."""
        for asker in self._askers():
            known = asker.member(module)
            if known is not None and known.attitude is not None:
                return known.attitude
        return None

    def ended(self, motion: Motion, linked: bool, readings: Readings) -> None:
        (a, ac), (b, bc) = motion.reach.chain.asking, motion.reach.chain.target
        counts = Counter[str]()
        for asker in self._askers():
            counts.update(asker.counts)
        self.log(
            f"reach_dock {self.where(a, ac)} -> {self.where(b, bc)}: {'latched' if linked else 'gave up'} after "
            f"{motion.reach.cycles} steps (cycles {motion.asked}-{motion.last}); chain frames {dict(counts)}"
        )

    def _askers(self) -> list[Asker]:
        raise NotImplementedError


@dataclass
class SelfReach(ModuleWorld):
    """One ``reach_dock`` of the asking module ``me`` (module docs)."""

    asker: Asker
    connector: int
    target_conn: int
    senses: OwnSenses
    latch_world: LatchAsk
    model: ConroModel
    profile: Profile
    log: Callable[[str], None]
    options: Options = field(default_factory=Options)
    cycle: int = 0
    docking: Docking | None = None
    #: the asking module's own joint targets this cycle (empty: its program's)
    own_targets: dict[int, float] = field(default_factory=dict)
    #: how it ended: None while under way, else "linked", "not linked", or why not
    verdict: str | None = None
    #: what this asks of its own module besides frames and joints (none for a reach_dock)
    effects: list[tuple[str, list[int]]] = field(default_factory=list)

    @property
    def me(self) -> int:
        return self.asker.me

    @property
    def done(self) -> bool:
        return self.verdict is not None

    def received(self, report: mw.Angles, cycle: int) -> None:
        """An ANGLES that came back to the asker."""
        self.asker.received(report, cycle)

    def step(self, cycle: int) -> list[Out]:
        """One control cycle: the frames to send (ASKs, TARGETS; END at the end)."""
        self.cycle = cycle
        if self.done:
            return []
        if self.docking is None:
            if not self.asker.known:
                if cycle - self.asker.started > LEARN_CYCLES:
                    return self._finish(f"the chain did not answer in {LEARN_CYCLES} cycles")
                return self.asker.frames(cycle)
            if not self._start():
                return self._finish("refused")
        docking = self.docking
        assert docking is not None
        targets = docking.step(cycle)
        if not docking.busy:
            if not docking.outcomes:
                return self._finish("abandoned: a member of the chain went silent")
            return self._finish("linked" if docking.outcomes[-1].latched else "not linked")
        self.own_targets = dict(targets.pop(self.me, {}))
        return self.asker.frames(cycle, targets)

    def _start(self) -> bool:
        """The chain is known: plan the reach (False: the rules refuse it, logged)."""
        size = 1 + max([self.me, *(m.module for m in self.asker.members if m.module is not None)])
        names = [f"m{i}" for i in range(size)]
        self.docking = Docking(self, self, self.model, self.profile, names, self.options)
        return self.docking.start_reach(self.me, self.connector, self.asker.route, self.target_conn)

    def _finish(self, verdict: str) -> list[Out]:
        self.verdict = verdict
        self.own_targets = {}
        self.log(f"reach_dock from m{self.me}: {verdict}")
        return self.asker.end(self.cycle)

    # ------------------------------------------------------------ the world, as the module knows it

    def peer_of(self, end: End) -> End | None:
        return self.asker.peer_of(*end)

    def running(self, module: int) -> bool:
        return self.asker.running(module, self.cycle)

    def _member_angles(self, module: int) -> Sequence[float]:
        known = self.asker.member(module)
        if known is None or len(known.angles) < 2:
            raise KeyError(f"no joint reading of module {module}")
        return known.angles

    def _askers(self) -> list[Asker]:
        return [self.asker]
