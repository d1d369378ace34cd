"""A ``reach_and_dock`` carried out by the module that asked for it (sans-IO): the asking side
of legs to snake's ``dock_tail_to_foot`` (docs/hil.md, *`reach_and_dock` in the modules*).

The foot at the end of the program's route lets go of the body and comes to the asking face
by its own trip and creep (:class:`firmware.motion.foot.Foot`, told by a SET_OFF); this is
everything else, run in the asking module from what it has on a robot: its own joints and
infrared pairs, the overhead tracker's report, and what its neighbours answer over the links.

Phases (:attr:`SelfAssimilate.phase`):

1. ``learn``: two chains are learnt a hop a round trip (:class:`firmware.motion.asker.Asker`):
   the route to the foot (its module index, and the connector it hangs by, which must be its
   front) and the body up the asking robot by front links (:func:`dh2rt.docking.body_up`, as
   far as it goes): the markers the foot's trip follows.
2. ``clearing`` (only if the tracker shows a module lying on the spot behind the face,
   :func:`firmware.motion.clearing.spot_taken`): the body crawls forward
   (:class:`firmware.motion.clearing.Clearing`, its DOF1 targets sent as TARGETS), then gives
   the members their joints back (END).
3. ``hand over``: SET_OFF to the foot each cycle until its link goes (the foot lets go: the
   member before it, or this module, reports that connector unlinked), at most
   :data:`LET_GO_CYCLES`.
4. ``waiting``: nothing is sent; each cycle the tracker's report (or the face's own infrared
   pair) says whether the foot has parked where its trip ends (:func:`firmware.motion.crawl.parked`).
5. ``squaring``: the last modules up the robot (:func:`dh2rt.docking.squaring_route`) are
   learnt again, and :meth:`firmware.motion.docking.Docking.reach_other` squares the face to
   the foot's front while the foot creeps on its own (``creeps_itself``); the latch is asked
   as for a ``reach_dock`` (:class:`firmware.motion.asking.LatchAsk`). Linked: done. Not
   linked: the foot goes round again by itself (its creep runs out), so this waits again,
   for the foot to leave the spot and come back, up to :data:`firmware.motion.foot.ATTEMPTS`
   squarings in all; it never sends the foot round itself (it has no link to it).

The whole wait is bounded (:data:`WAIT_CYCLES`: every trip the foot may make, each with its
creep); past it, when the foot's trips are spent, or when the tracker shows the foot hardly
moving for :data:`STILL_CYCLES` (it died or is stuck), or when the foot lies where the face's
infrared pair must see it, lying still, and the pair sees nothing (its emitter is dark: it
has no power, :data:`DARK_CYCLES`), the verdict is ``not linked``, and the program may ask for the next foot.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from dh2rt import docking as rules
from dh2rt.docking import End
from dh2rt.profile import Profile
from dh2rt.wire import motion as mw
from firmware.motion.asker import Asker
from firmware.motion.asking import LEARN_CYCLES, LatchAsk, ModuleWorld, OwnSenses, learn_cycles
from firmware.motion.body import ConroModel
from firmware.motion.clearing import Clearing, spot_taken
from firmware.motion.crawl import parked
from firmware.motion.docking import Docking, Options
from firmware.motion.foot import ATTEMPTS, CREEP_BUDGET
from firmware.motion.readings import FloorPoses, TrackerMissing
from firmware.outbound import Out

#: Cycles the SET_OFF is sent before the foot's letting go is given up on: the foot takes it
#: a hop a cycle down the route and lets go at once; a link seen down takes the neighbour's
#: silence to show (the launcher's ``--silence-cycles``, a few cycles).
LET_GO_CYCLES = 60
#: Hops up the robot by front links learnt at most (a snake of 17 modules).
MAX_BODY = 16
#: A trip's budget (firmware.motion.crawl.Trip's ``budget``), for the whole wait's bound.
TRIP_BUDGET = 2500
#: Cycles this waits for the foot in all: each of its trips with its creep.
WAIT_CYCLES = ATTEMPTS * (TRIP_BUDGET + CREEP_BUDGET)
#: The face's own infrared pair sees the foot parked: nearer than this (mm) and square.
SEES_MM = 85.0
SEES_DEG = 20.0
#: Cycles in a row the foot must be seen parked before the square-up begins: a foot passing
#: through the parking window on its way (turning, or moving across) is not there yet, and a
#: square-up begun then moves the face the foot's trip steers to (seen in physics, seed 0: the
#: trip gave up, and the squarings with it).
PARKED_CYCLES = 10
#: How square (degrees, in the face's frame) the foot must lie to count as parked: wider than
#: the trip's own 6, since the foot creeps on from its arrival and turns as it does (seed 0,
#: second round: 8.5 to 11 degrees off in the 60 cycles after it arrived, so a 6-degree window
#: never saw it, and its creep ran out unsquared); 25 rather than 15 since the heading must
#: also hold steady (below): seed 0, the winner killed as it docked, the last foot crept 15 to
#: 20 degrees off the face's axis, steady, and a 15-degree window never saw it parked for 10
#: cycles in a row (its creep ran out unsquared, and the snake did not form).
PARKED_HEADING_DEG = 25.0
#: How steady the foot's heading must be over those :data:`PARKED_CYCLES` (the span of its
#: readings, degrees): a foot that has arrived stands square and creeps straight (seed 3,
#: first round: its heading moved 0.7 degrees in the 10 cycles after it arrived), while a foot
#: still turning in place in the parking window, not yet square to its own 6 degrees, rocks
#: 6 to 20 degrees in 10 cycles (seeds 3 and 9, the third round: the face squared at such a
#: foot, moved the spot the foot steered for, and the foot turned on until its trip gave up).
PARKED_STEADY_DEG = 5.0
#: After a squaring that did not latch, the foot has gone round again once the tracker shows
#: its front this far from where it lay then (its trip backs it off 8 cm), or it has been off
#: the parking window :data:`PARKED_CYCLES` in a row.
BACKED_OFF_M = 0.07
#: A foot on its trip crawls 8 to 10 cm a 100 cycles or turns in place; one that in
#: :data:`STILL_CYCLES` has moved less than :data:`STILL_M` and turned less than
#: :data:`STILL_DEG` has died or is stuck, and the dock is given up: nothing else tells the
#: asker (the world's sequence learns it from the link map; a module cannot). A foot killed on
#: its trip in physics (seed 0) slid 0.5 to 1 cm and turned 5 to 20 degrees a 100 cycles as it
#: settled: hence a window, not a stillness.
STILL_CYCLES = 400
STILL_M = 0.06
STILL_DEG = 60.0
#: The foot lies where the face's infrared pair must see it (the tracker shows its front
#: within :data:`SIGHT_M` of the face, each face within :data:`SIGHT_DEG` of the other's
#: normal: inside a CONRO pair's 10 cm and 30 degrees, docs/physics.md *Sensors*), the pair
#: sees nothing, and the foot's front face moves less than :data:`DARK_PATH_M` (its path on
#: the tracker, summed cycle to cycle) for :data:`DARK_CYCLES` in a row: its emitter is dark,
#: it has no power, and the dock is given up. The infrared pairs are active (an emitter on
#: each face): what a real robot has to tell a dead module from a live one without a link. The
#: stillness is part of the rule because a live foot creeping at the face lifts its front 30
#: degrees with each step, out of the pair's cone for tens of cycles (legs to snake, seed 0,
#: in physics: the tracker's floor plan cannot show a tilt), and never lies still. A foot
#: killed as its square-up began (seed 1) was otherwise known dead only by
#: :data:`STILL_CYCLES` after that square-up's 400 cycles ran out.
SIGHT_M = 0.08
SIGHT_DEG = 20.0
DARK_CYCLES = 40
DARK_PATH_M = 0.015


@dataclass
class SelfAssimilate(ModuleWorld):
    """One ``reach_and_dock`` of the asking module (module docs)."""

    to_foot: Asker
    #: up the robot by front links; None when the asking module's front is free (it is the head)
    up_body: Asker | None
    connector: int
    senses: OwnSenses
    latch_world: LatchAsk
    model: ConroModel
    profile: Profile
    log: Callable[[str], None]
    #: the asking module's links now (its ConnectorStatus)
    own_links: Callable[[], Sequence[int]]
    #: a fresh motion id for each chain learnt later (the squaring's)
    next_motion: Callable[[], int]
    options: Options = field(default_factory=Options)
    cycle: int = 0
    phase: str = "learn"
    foot: int | None = None
    body: list[int] = field(default_factory=list)
    clearing: Clearing | None = None
    squaring: Asker | None = None
    docking: Docking | None = None
    #: the cycle the current phase began
    since: int = 0
    waited: int = 0
    squarings: int = 0
    #: the foot was seen off the spot since the last squaring (it went round again)
    away: bool = True
    #: the foot's heading (degrees) each cycle in a row it was seen parked, steady (the
    #: tracker's, else the face's pair's): :attr:`parked_for` is how many
    parked_headings: list[float] = field(default_factory=list)
    #: cycles in a row the foot was seen off the parking window (after a squaring that did not
    #: latch)
    off_for: int = 0
    #: where the foot was (x, y, heading) when the current window began, and that cycle
    moved: tuple[float, float, float, int] | None = None
    #: how far (m) and how much (degrees) the foot has been from there in this window, at most
    strayed: tuple[float, float] = (0.0, 0.0)
    #: where the foot's front lay when the last squaring gave up (the tracker's)
    left_at: tuple[float, float] | None = None
    #: cycles in a row the foot lay in the face's sight and its pair saw nothing, and the
    #: path its front face went meanwhile (m), and where it was last
    dark_for: int = 0
    dark_path: float = 0.0
    dark_at: tuple[float, float] | None = None
    own_targets: dict[int, float] = field(default_factory=dict)
    verdict: str | None = None
    #: what this asks of its own module besides frames and joints (the host reports them):
    #: ``("release", [connector])``, its own face let go of before the robot crawls clear
    effects: list[tuple[str, list[int]]] = field(default_factory=list)

    @property
    def me(self) -> int:
        return self.to_foot.me

    @property
    def done(self) -> bool:
        return self.verdict is not None

    @property
    def askers(self) -> list[Asker]:
        return [a for a in (self.to_foot, self.up_body, self.squaring) if a is not None]

    def received(self, report: mw.Angles, cycle: int) -> None:
        """An ANGLES that came back: to the chain whose motion it answers."""
        for asker in self.askers:
            if asker.motion == report.motion:
                asker.received(report, cycle)
                return

    # ------------------------------------------------------------ each cycle

    def step(self, cycle: int) -> list[Out]:
        """One control cycle: the frames to send."""
        self.cycle = cycle
        if self.done:
            return []
        self.own_targets = {}
        phase = getattr(self, "_" + self.phase.replace(" ", "_"))
        out: list[Out] = phase()
        return out

    def _learn(self) -> list[Out]:
        body = self.up_body
        if not (self.to_foot.known and (body is None or body.learnt)):
            # the longer of the two chains, as far as the body is known yet
            limit = learn_cycles(max(len(self.to_foot.route), 0 if body is None else len(body.members) + 1))
            if self.cycle - self.to_foot.started > limit:
                return self._finish(f"the route or the body did not answer in {limit} cycles")
            return self.to_foot.frames(self.cycle) + ([] if body is None else body.frames(self.cycle))
        refused = self._rules()
        if refused:
            return self._finish(refused)
        floor = self.senses.floor()
        if not floor.modules:
            if self.cycle - self.to_foot.started > LEARN_CYCLES:
                return self._finish("no report of the overhead tracker (the foot's trip needs one)")
            return self.to_foot.frames(self.cycle)  # the tracker's latency: keep the route answering
        lying = self._spot_taken(floor)
        if lying is not None and body is not None:
            self.clearing = Clearing(self.body[::-1], lambda: self._spot_taken(self.senses.floor()) is not None)
            self.log(f"reach_and_dock: module {lying} lies behind the face; the robot crawls clear first")
            # the face has no link (the rules above), yet its latch may still hold a foot that
            # died docked to it: let go first, or the crawl drags the body along (physics, seed
            # 7, the winner killed as it docked: 8 gait cycles, the spot still taken, 3 times)
            self.effects.append(("release", [self.connector]))
            return self._enter("clearing")
        return self._enter("hand over")

    def _rules(self) -> str | None:
        """The foot and the body as learnt; why the rules refuse the dock, or None."""
        front = self.profile.connector_index("front")
        foot = self.to_foot.members[-1]
        if foot.module is None or foot.module == self.me:
            return "the route leads back"
        if foot.route[-1][1] != front:
            return "the foot does not hang by its front"
        if self.own_links()[self.connector - 1]:
            return f"{self.where(self.me, self.connector)} is not free"
        if not self.profile.can_link(self.connector, front):
            return "both connectors are of one gender"
        self.foot = foot.module
        up = [] if self.up_body is None else [m.module for m in self.up_body.members if m.module is not None]
        self.body = [self.me, *up]
        self.log(f"reach_and_dock: the foot is module {self.foot}; the body up is {self.body}")
        return None

    def _spot_taken(self, floor: FloorPoses) -> int | None:
        assert self.foot is not None
        if not floor.modules:  # no fresh report (a module hearing the tracker itself): nothing known
            return None
        try:
            size = 1 + max(floor.modules)
            return spot_taken(floor, self.model, self.peer_of, self.profile, size, self._face, self.foot)
        except TrackerMissing:
            return None

    @property
    def _face(self) -> End:
        return self.me, self.connector

    def _clearing(self) -> list[Out]:
        assert self.clearing is not None and self.up_body is not None
        dof1 = self.clearing.step()
        if not self.clearing.done:
            if self.me in dof1:
                self.own_targets = {0: dof1.pop(self.me)}
            return self.up_body.frames(self.cycle, {m: {0: v} for m, v in dof1.items()})
        c = self.clearing
        self.log(
            f"reach_and_dock: crawled {c.gait_cycles} gait cycles, the spot "
            + ("clear" if c.cleared else "still taken; the foot sets off anyway")
        )
        return self.up_body.end(self.cycle) + self._enter("hand over")

    def _hand_over(self) -> list[Out]:
        assert self.foot is not None
        if self._let_go():
            self.log(f"reach_and_dock: module {self.foot} let go after {self.cycle - self.since} cycles")
            return self.to_foot.end(self.cycle) + self._enter("waiting")
        if self.cycle - self.since > LET_GO_CYCLES:
            return self._finish(f"the foot did not let go in {LET_GO_CYCLES} cycles")
        floor = self.senses.floor()
        others = sorted(set(floor.modules) - set(self.body) - {self.foot})
        asks = self.to_foot.frames(self.cycle)  # first: a member takes only frames newer than the last
        return [*asks, self.to_foot.set_off(self.cycle, self.me, self.connector, self.body, others)]

    def _let_go(self) -> bool:
        """The foot's link is down: seen by the member before it, or by this module."""
        route = self.to_foot.route
        if len(route) == 1:
            links: Sequence[int] = self.own_links()
        else:
            before = self.to_foot.members[-2]
            if before.answered is None or before.answered <= self.since:
                return False
            links = before.links
        return route[-1] > len(links) or not links[route[-1] - 1]

    def _waiting(self) -> list[Out]:
        assert self.foot is not None
        self.waited += 1
        if self.waited > WAIT_CYCLES:
            return self._finish(f"not linked: no foot parked at the face in {WAIT_CYCLES} cycles")
        if self._still():
            return self._finish(f"not linked: module {self.foot} hardly moved in {STILL_CYCLES} cycles (dead or stuck)")
        if self._dark():
            return self._finish(self._dark_verdict())
        if not self.away:  # where the last squaring left it, until it has gone round again
            self.off_for = 0 if self._foot_there(heading_deg=180.0) else self.off_for + 1
            self.away = self.off_for >= PARKED_CYCLES or self._backed_off()
            return []
        self._note_parked()
        if self.parked_for < PARKED_CYCLES:
            return []
        route = rules.squaring_route(self.peer_of, self.profile, self.me)
        if not route:
            return self._finish("the asking module has no body up its front to square its face with")
        self.squaring = Asker(self.next_motion(), self.me, tuple(self.own_links()), route, self.cycle, log=self.log)
        self.log(f"reach_and_dock: module {self.foot} is at the face; squaring along {list(route)}")
        return self._enter("squaring")

    @property
    def parked_for(self) -> int:
        """Cycles in a row (up to :data:`PARKED_CYCLES`) the foot has been seen parked with its
        heading steady (:data:`PARKED_STEADY_DEG`) over them."""
        return len(self.parked_headings)

    def _note_parked(self) -> None:
        """This cycle's reading of the foot into :attr:`parked_headings`: none when it is not
        parked now."""
        if not self._foot_there():
            self.parked_headings = []
            return
        heading = self._foot_heading()
        kept = self.parked_headings[-(PARKED_CYCLES - 1) :]
        # the oldest readings go until the rest and this one lie within PARKED_STEADY_DEG
        while kept and _span([*kept, heading]) > PARKED_STEADY_DEG:
            kept.pop(0)
        self.parked_headings = [*kept, heading]

    def _backed_off(self) -> bool:
        """The tracker shows the foot's front :data:`BACKED_OFF_M` or more from where it lay
        when the last squaring gave up: it has set off round again, even if it never left the
        parking window (seed 2: it backed off 8 cm inside it and was back in 79 cycles)."""
        front = self._front()
        if front is None or self.left_at is None:
            return False
        return math.dist(front, self.left_at) >= BACKED_OFF_M

    def _front(self) -> tuple[float, float] | None:
        """Where the tracker shows the foot's front face, if it shows the foot."""
        face = self._foot_front()
        return None if face is None else face[:2]

    def _foot_front(self) -> tuple[float, float, float, float] | None:
        """The foot's front face as the tracker shows it (centre and outward normal), if it
        shows the foot."""
        assert self.foot is not None
        floor = self.senses.floor()
        if self.foot not in floor.modules:
            return None
        try:
            return floor.face(self.model, self.foot, "front")
        except TrackerMissing:
            return None

    def _foot_heading(self) -> float:
        """The foot's heading as the tracker shows it (degrees), else the face's pair's
        alignment reading."""
        assert self.foot is not None
        try:
            floor = self.senses.floor()
            if self.foot in floor.modules:
                return math.degrees(floor.heading(self.foot))
        except TrackerMissing:
            pass
        return self._face_pair()[1]

    def _foot_there(self, heading_deg: float = PARKED_HEADING_DEG) -> bool:
        """The tracker shows the foot parked behind the face (squared within ``heading_deg``),
        or the face's pair sees it."""
        assert self.foot is not None
        floor = self.senses.floor()
        try:
            if self.foot in floor.modules and parked(floor, self.model, self.foot, self._face, heading_deg=heading_deg):
                return True
        except TrackerMissing:
            pass
        mm, deg = self._face_pair()
        return 0.0 < mm <= SEES_MM and deg <= SEES_DEG

    def _face_pair(self) -> tuple[float, float]:
        """The asking face's infrared pair: distance (mm, 0 seeing nothing) and alignment (degrees)."""
        name = self.profile.connector_name(self.connector)
        ir = self.senses.infrared()
        return ir.get(f"ir_{name}", 0.0), ir.get(f"ir_{name}_align", 180.0)

    def _still(self) -> bool:
        """The tracker shows the foot hardly moved over the last :data:`STILL_CYCLES`."""
        assert self.foot is not None
        floor = self.senses.floor()
        if self.foot not in floor.modules:
            return False
        x, y = floor.centre(self.foot)
        heading = math.degrees(floor.heading(self.foot))
        start = self.moved
        if start is None:
            self.moved, self.strayed = (x, y, heading, self.cycle), (0.0, 0.0)
            return False
        # the farthest from the window's start, not where it ends: a foot that backed off
        # and came back to the face in the window has moved (seed 2, its second round)
        self.strayed = (
            max(self.strayed[0], math.hypot(x - start[0], y - start[1])),
            max(self.strayed[1], abs(_turned(start[2], heading))),
        )
        if self.cycle - start[3] < STILL_CYCLES:
            return False
        far, turned = self.strayed
        self.moved, self.strayed = (x, y, heading, self.cycle), (0.0, 0.0)  # the next window starts here
        return far < STILL_M and turned < STILL_DEG

    def _dark(self) -> bool:
        """The tracker shows the foot in the face's sight and lying still, and the face's pair
        sees nothing, :data:`DARK_CYCLES` cycles in a row (module docs, :data:`SIGHT_M`)."""
        front = None if self._face_pair()[0] > 0.0 else self._in_sight()
        if front is None:
            self.dark_for, self.dark_path, self.dark_at = 0, 0.0, None
            return False
        if self.dark_at is not None:
            self.dark_path += math.dist(front, self.dark_at)
        self.dark_for, self.dark_at = self.dark_for + 1, front
        if self.dark_path >= DARK_PATH_M:  # it moves: alive, out of the pair's cone for now
            self.dark_for, self.dark_path = 0, 0.0
        return self.dark_for >= DARK_CYCLES

    def _dark_verdict(self) -> str:
        return f"not linked: module {self.foot} lies in the face's sight and its infrared is dark (no power)"

    def _in_sight(self) -> tuple[float, float] | None:
        """Where the tracker shows the foot's front face, if it shows it where the face's
        infrared pair must see it; else None."""
        front = self._foot_front()
        if front is None:
            return None
        fx, fy, fnx, fny = front
        try:
            px, py, nx, ny = self.senses.floor().face(self.model, *self._face)
        except TrackerMissing:
            return None
        dx, dy = fx - px, fy - py
        d = math.hypot(dx, dy)
        cone = math.cos(math.radians(SIGHT_DEG))
        opposed = -(nx * fnx + ny * fny) / ((math.hypot(nx, ny) * math.hypot(fnx, fny)) or 1.0)
        if d < 0.015:  # face to face: no direction between the centres to speak of
            sees = opposed >= cone
        else:
            mine = (dx * nx + dy * ny) / (d * (math.hypot(nx, ny) or 1.0))
            theirs = -(dx * fnx + dy * fny) / (d * (math.hypot(fnx, fny) or 1.0))
            sees = d <= SIGHT_M and mine >= cone and theirs >= cone
        return (fx, fy) if sees else None

    def _squaring(self) -> list[Out]:
        chain = self.squaring
        assert chain is not None and self.foot is not None
        if self._dark():  # _finish ends the squaring chain with the others
            return self._finish(self._dark_verdict())
        if self.docking is None:
            if not chain.known:
                if self.cycle - chain.started > LEARN_CYCLES:
                    return self._finish(f"the squaring chain did not answer in {LEARN_CYCLES} cycles")
                return chain.frames(self.cycle)
            size = 1 + max([self.me, self.foot, *self.body])
            names = [f"m{i}" for i in range(size)]
            self.docking = Docking(self, self, self.model, self.profile, names, self.options)
            front = self.profile.connector_index("front")
            if not self.docking.reach_other(
                self.me, self.connector, chain.route, (self.foot, front), creeps_itself=True
            ):
                return self._finish("refused")
        docking = self.docking
        targets = docking.step(self.cycle)
        if docking.busy:
            self.own_targets = dict(targets.pop(self.me, {}))
            return chain.frames(self.cycle, targets)
        ended = chain.end(self.cycle)
        self.squarings += 1
        if docking.outcomes and docking.outcomes[-1].latched:
            return ended + self._finish("linked")
        why = "the chain went silent" if not docking.outcomes else "not latched"
        self.docking, self.squaring = None, None
        if self.squarings >= ATTEMPTS:
            return ended + self._finish(f"not linked: {self.squarings} squarings ({why})")
        self.log(f"reach_and_dock: squaring {self.squarings} {why}; waiting for the foot to come round again")
        self.away, self.off_for, self.moved = False, 0, None
        self.parked_headings, self.left_at = [], self._front()
        return ended + self._enter("waiting")

    def _enter(self, phase: str) -> list[Out]:
        self.phase, self.since = phase, self.cycle
        return []

    def _finish(self, verdict: str) -> list[Out]:
        self.verdict, self.own_targets = verdict, {}
        self.log(f"reach_and_dock from m{self.me}: {verdict}")
        out: list[Out] = []
        for asker in self.askers:
            if asker.members and any(m.answered is not None for m in asker.members):
                out += asker.end(self.cycle)
        return out

    # ------------------------------------------------------------ the world, as the module knows it

    def peer_of(self, end: End) -> End | None:
        module, connector = end
        if module == self.foot:
            return None  # the foot is lone once it let go; nothing docks it but the latch
        for asker in (self.squaring, self.up_body, self.to_foot):
            if asker is not None and (module == self.me or asker.member(module) is not None):
                peer = asker.peer_of(module, connector)
                if peer is not None and peer[0] != -1:
                    return peer
        if module == self.me:
            remote = self.own_links()[connector - 1] if connector <= len(self.own_links()) else 0
            return (-1, remote) if remote else None
        return None

    def running(self, module: int) -> bool:
        if module == self.foot:
            return True  # lone: nothing tells; its own trip gives up if it must
        chain = self.squaring if self.squaring is not None else self.up_body
        return chain is not None and chain.running(module, self.cycle)

    def _askers(self) -> list[Asker]:
        return self.askers

    def _member_angles(self, module: int) -> Sequence[float]:
        known = None if self.squaring is None else self.squaring.member(module)
        if known is None or len(known.angles) < 2:
            raise KeyError(f"no joint reading of module {module}")
        return known.angles


def _span(headings: Sequence[float]) -> float:
    """How far apart (degrees) the headings lie, measured from the first across the wrap."""
    offsets = [_turned(headings[0], h) for h in headings]
    return max(offsets) - min(offsets)


def _turned(start: float, heading: float) -> float:
    """From ``start`` to ``heading`` (degrees) the short way round: in [-180, 180)."""
    return (heading - start + 180.0) % 360.0 - 180.0
