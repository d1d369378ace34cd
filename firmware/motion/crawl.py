"""A lone module's own motion: how a released foot comes to a face and closes a dock itself.

The foot moves by the gaits of :mod:`firmware.motion.gaits` (:func:`back_off`, :func:`creep`,
:func:`turn`). :class:`Trip` takes a released foot to just behind a free face; :class:`Creep` is the
foot's half of the dock that follows, whose target lies beyond a straight chain's reach (a
chain lying straight cannot lengthen by bending): while the other side's docking motion
(:class:`firmware.motion.reach.Reach`) squares its face to the foot, the foot creeps front first; it
holds still, its front square, once its front's infrared pair reads the face within
:data:`HOLD_MM`, and creeps again if the reading grows past :data:`RESUME_MM` or the face
drops out of view for :data:`LOST_CYCLES` cycles.

Both are sans-IO: :class:`Creep` reads the foot's front infrared pair, :class:`Trip` the
overhead tracker's poses (:class:`firmware.motion.readings.FloorPoses`: the foot's, the
target module's, and those of the robot's modules it passes); each returns the foot's joint
targets a cycle.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from dh2rt.docking import End
from firmware.motion.body import DEFAULT_MODEL, ConroModel
from firmware.motion.gaits import back_off, creep, turn
from firmware.motion.readings import FloorPoses, Readings

#: The foot holds still (front square) once its front infrared reads the target this close (mm).
HOLD_MM = 12.0
#: ... and creeps again once the reading is beyond this (mm).
RESUME_MM = 22.0
#: Cycles with nothing in view before a holding foot creeps again.
LOST_CYCLES = 16


class Creep:
    """A lone module creeping front first towards what its front infrared sees.

    Stepped once a control cycle by its owner with that cycle's readings (the module's
    front infrared pair); :meth:`step` returns the joint targets (degrees) the module holds
    this cycle.
    """

    def __init__(self, module: int, connector_name: str = "front") -> None:
        self.module = module
        self._ir = f"ir_{connector_name}"
        self.cycles = 0
        self.holding = False
        self._lost = 0
        #: Cycles spent creeping (not holding).
        self.crept = 0

    def reading_mm(self, readings: Readings) -> float:
        return readings.ir(self.module, self._ir)

    def step(self, readings: Readings) -> tuple[float, float]:
        self.cycles += 1
        mm = self.reading_mm(readings)
        if self.holding:
            self._lost = self._lost + 1 if mm == 0 else 0
            if mm > RESUME_MM or self._lost >= LOST_CYCLES:
                self.holding = False
        elif 0 < mm <= HOLD_MM:
            self.holding, self._lost = True, 0
        if self.holding:
            return 0.0, 0.0
        self.crept += 1
        return creep(self.crept)


#: How far beyond a leg's centre (or a module's lying beside the robot; m) a foot passing it
#: keeps its front, and from how far ahead (m, along the path) it does so.
OBSTACLE_CLEAR_M = 0.10
OBSTACLE_AHEAD_M = 0.30

#: How far before the end of the line along (m, in ``s``) the foot starts across towards its
#: spot: it then backs diagonally past the face instead of going past it and then across
#: (two turns of about 90 degrees in place, each drifting the foot; docs/physics.md).
DIAGONAL_M = 0.22
#: ... and at most this steeply (degrees off the line): a foot that came along closer to the
#: robot than its line starts across later (one that started 16 cm before the face at 5 cm
#: beside the axis caught its back on the tail's end and stayed there).
DIAGONAL_LEAN_DEG = 25.0
#: While its front is still beside the target module, a foot this close to the axis (m) backs
#: straight along rather than in towards the spot.
ALONGSIDE_M = 0.05
#: A foot at most this far too far back (m) moves across to its spot instead of turning about.
ACROSS_BEHIND_M = 0.05


#: Where a trip parks the foot's front in the target face's frame (along, aside; m), and how
#: much further back than that it moves across (:class:`Trip`'s ``park`` and ``margin_m``).
PARK = (-0.03, 0.005)
MARGIN_M = 0.03


def parked(
    floor: FloorPoses,
    model: ConroModel,
    foot: int,
    target: End,
    *,
    park: tuple[float, float] = PARK,
    margin_m: float = MARGIN_M,
    heading_deg: float = 6.0,
) -> bool:
    """Whether the tracker's ``floor`` shows ``foot`` where a :class:`Trip` to ``target``
    arrives: its front squared (within ``heading_deg``) within 3 cm of the spot aside and
    between ``margin_m`` + 2.5 cm further back and 2 cm nearer than it. What the asking
    module, which cannot see the foot's trip, reads as "the foot is there"
    (firmware.motion.assimilating)."""
    fx, fy, _, _ = floor.face(model, foot, "front")
    px, py, nx, ny = floor.face(model, *target)
    norm = math.hypot(nx, ny) or 1.0
    ux, uy = -nx / norm, -ny / norm
    rx, ry = fx - px, fy - py
    s, lat = rx * ux + ry * uy, -rx * uy + ry * ux
    heading = (floor.heading(foot) - math.atan2(uy, ux) + math.pi) % (2 * math.pi) - math.pi
    aim = park[0] - margin_m
    return (
        abs(abs(lat) - park[1]) <= 0.03
        and aim - 0.025 <= s <= park[0] + 0.02
        and abs(math.degrees(heading)) <= heading_deg
    )


class Trip:
    """A released foot's trip to a spot just behind a free face (the tail's back), facing it.

    The foot's front is the face that will dock, so the foot ends facing along the target's
    module (its heading that module's, reversed from the face's normal). In the target
    face's frame (``s`` along the module's heading from the face, ``lat`` across it, positive
    on the foot's side) the trip is: :func:`back_off` :attr:`backoff_m` away from where it
    hung (its side of the target module is the one it is on then), and on out to the line
    below while beside the robot (further while a module off the path is in the way
    along, see ``others``); then, turning in place
    (:func:`turn`) whenever its heading is more than 8 degrees off the one it wants, else
    backing off: along a line :attr:`clear_m` beside the robot's axis (the heading it wants
    leans into the line by 5 degrees per cm off it, at most 29; out by up to 70 to pass a
    leg) until its front is :attr:`diagonal_m` short of :attr:`margin_m` further back than
    :attr:`park` [0] (or that far back itself while a leg on the body is near); then, back
    first, towards the spot :attr:`park` [1] aside on that line (re-aimed from where the
    foot is each cycle: the gaits drift differently with the floor's friction at each
    heading): from up to :attr:`diagonal_m` before it, the foot backs diagonally past the
    face, leaning :data:`DIAGONAL_LEAN_DEG` at most (so a foot that came along closer to the
    robot starts later), rather than going past it and then across (two turns of about 90
    degrees in place, each drifting it, where most trips that gave up had spent their
    budget); while its front is still beside the target module within :data:`ALONGSIDE_M`
    of the axis it backs straight instead; once within 2 cm of the axis and between 2 and
    8 cm behind the face,
    square (within 6 degrees) and still. Squared within 3 cm of the axis and between 1
    and 8.5 cm behind the face it has arrived (the dock's creep closes the rest);
    otherwise it moves across again, or back along if it was pushed alongside the target
    module. A turn keeps its direction while the foot faces about the other way (the
    error's sign flips there from cycle to cycle). Up to :data:`ACROSS_BEHIND_M` too far
    back, it moves straight across; further, it turns about to back towards the spot: its
    front, read as where it is, is then a module's length further from the face than its
    back, and a foot can press its back on the tail while it still reads itself too far
    back (a rear foot going first at seed 0 did, before the diagonal, until its budget ran
    out).

    ``others`` (the modules off the path) are the legs still on the body, and any module
    lying apart beside the robot: a foot passing one on its side keeps its front
    :data:`OBSTACLE_CLEAR_M` beyond the module's centre (a front foot going first ran into
    the rear leg and stayed there; a rear foot hanging beside the front foot that died on its
    way turned in place against it, between it and the body, for 2,000 cycles).

    The line follows the target's robot as it lies: ``body`` (the modules from the target
    module up its robot, each the one the last is docked to by its front) makes a polyline
    from the face through each module's centre, and while backing along, ``s`` is the arc
    length from the face along it (negative beyond the face) and ``lat`` and the heading are
    taken against the nearest segment. Without ``body`` the line is straight along the
    target module: it followed a tail only while the tail lay straight (a second round, with
    the first foot docked a little askew, drifted out and ran the foot into the tail's side).

    Where the face and the foot are is the overhead tracker's (``floor``: the first
    reading, then each :meth:`step`'s; :class:`firmware.motion.readings.FloorPoses`); the
    last centimetres are the dock's (:class:`Creep`, the foot's infrared).
    """

    def __init__(
        self,
        floor: FloorPoses,
        module: int,
        target: End,
        *,
        model: ConroModel = DEFAULT_MODEL,
        backoff_m: float = 0.08,
        clear_m: float = 0.10,
        park: tuple[float, float] = PARK,
        budget: int = 2500,
        body: Callable[[], list[int]] | None = None,
        others: Callable[[], list[int]] | None = None,
        margin_m: float = MARGIN_M,
        diagonal_m: float = DIAGONAL_M,
    ) -> None:
        self.floor = floor
        self.model = model
        self.module = module
        self.target = target
        self.body = body
        #: The modules off the path (the legs still on the body, a module lying beside it).
        self.others = others
        #: How much further back than the spot the foot goes before it moves sideways, so
        #: that it clears the target module's corner.
        self.margin_m = margin_m
        #: How far before the line's end the foot starts across (:data:`DIAGONAL_M`).
        self.diagonal_m = diagonal_m
        self.backoff_m = backoff_m
        self.clear_m = clear_m
        self.park = park
        self.budget = budget
        #: +1 if the foot travels on the target module's left, -1 on its right (decided when
        #: it has backed off).
        self.side = 1
        self._start = self._front()
        self.phase = "back off"
        self.cycles = 0
        self._turning = 0
        #: Cycles spent in each phase, and turning in each phase (:meth:`account`).
        self.spent: dict[str, int] = {}
        self.turning: dict[str, int] = {}
        self.done = False
        #: Whether the foot got to the spot (False: the budget ran out).
        self.arrived = False

    def _front(self) -> tuple[float, float]:
        """The foot's front face on the floor."""
        fx, fy, _, _ = self.floor.face(self.model, self.module, "front")
        return fx, fy

    def _frame(self) -> tuple[float, float, float]:
        """The foot's front in the target face's frame (s, lat unmirrored) and its heading off
        the target module's (radians, unmirrored)."""
        fx, fy = self._front()
        px, py, nx, ny = self.floor.face(self.model, *self.target)
        norm = math.hypot(nx, ny) or 1.0
        ux, uy = -nx / norm, -ny / norm
        rx, ry = fx - px, fy - py
        heading = self.floor.heading(self.module) - math.atan2(uy, ux)
        return rx * ux + ry * uy, -rx * uy + ry * ux, (heading + math.pi) % (2 * math.pi) - math.pi

    def _path_frame(self) -> tuple[float, float, float]:
        """As :meth:`_frame`, against the polyline from the face through :attr:`body`'s
        centres (the nearest segment; the first one extends beyond the face)."""
        if self.body is None:
            return self._frame()
        fx, fy = self._front()
        psi = self.floor.heading(self.module)
        s, lat, direction = self._on_path(self._polyline(), fx, fy)
        return s, lat, (psi - direction + math.pi) % (2 * math.pi) - math.pi

    def _polyline(self) -> list[tuple[float, float]]:
        px, py, _, _ = self.floor.face(self.model, *self.target)
        body = self.body() if self.body is not None else []
        return [(px, py)] + [self.floor.centre(m) for m in body]

    @staticmethod
    def _on_path(points: list[tuple[float, float]], fx: float, fy: float) -> tuple[float, float, float]:
        """(s, lat, the segment's direction) of the point (fx, fy) against the polyline."""
        best: tuple[float, float, float, float] | None = None  # distance, s, lat, direction
        along = 0.0
        for i in range(len(points) - 1):
            (ax, ay), (bx, by) = points[i], points[i + 1]
            length = math.hypot(bx - ax, by - ay) or 1e-9
            ux, uy = (bx - ax) / length, (by - ay) / length
            rx, ry = fx - ax, fy - ay
            proj = rx * ux + ry * uy
            clamped = proj if i == 0 else max(0.0, proj)
            if i < len(points) - 2:
                clamped = min(clamped, length)
            dist = math.hypot(rx - clamped * ux, ry - clamped * uy)
            if best is None or dist < best[0]:
                best = (dist, along + clamped, -rx * uy + ry * ux, math.atan2(uy, ux))
            along += length
        assert best is not None, "a polyline has at least two points"
        return best[1], best[2], best[3]

    def _clearance(self, s: float) -> float:
        """How far beside the path (m, the foot's side) the foot's front keeps at ``s``: at
        least :attr:`clear_m`, and :data:`OBSTACLE_CLEAR_M` beyond the centre of any module
        off the path (:attr:`others`) on the foot's side, from :data:`OBSTACLE_AHEAD_M`
        ahead of the foot to a little behind it. A module whose centre lies further out
        than that from the line :attr:`clear_m` beside the path is not in the way; nor is
        one beyond the face (a foot killed as it docked: the robot crawls clear of it first,
        :mod:`firmware.motion.clearing`, and the foot's way to its spot is the diagonal's)."""
        if self.others is None or self.body is None:
            return self.clear_m
        points = self._polyline()
        clear = self.clear_m
        for m in self.others():
            ox, oy = self.floor.centre(m)
            so, lo, _ = self._on_path(points, ox, oy)
            lo *= self.side
            if 0 < lo < self.clear_m + OBSTACLE_CLEAR_M and max(0.0, s - OBSTACLE_AHEAD_M) < so <= s + 0.08:
                clear = max(clear, lo + OBSTACLE_CLEAR_M)
        return clear

    def state(self, *, path: bool = False) -> tuple[float, float, float]:
        """(s, lat, heading) with lat and heading mirrored to the foot's side; with ``path``
        against the target's robot as it lies (:meth:`_path_frame`), else the face's frame; from
        the last reading."""
        s, lat, heading = self._path_frame() if path else self._frame()
        return s, lat * self.side, heading * self.side

    def step(self, floor: FloorPoses) -> tuple[float, float]:
        """Advance by one control cycle with the tracker's ``floor``; the foot's joint targets
        (DOF1, DOF2 degrees)."""
        self.floor = floor
        targets = self._step()
        if not self.done or self.arrived:
            self.spent[self.phase] = self.spent.get(self.phase, 0) + 1
            if self._turning:
                self.turning[self.phase] = self.turning.get(self.phase, 0) + 1
        return targets

    def account(self) -> str:
        """Where the cycles went, phase by phase, and how many of them the foot turned: the
        first thing to read when a trip takes long or gives up."""
        parts = []
        for phase, cycles in self.spent.items():
            turned = self.turning.get(phase, 0)
            parts.append(f"{phase} {cycles}" + (f" ({turned} turning)" if turned else ""))
        return ", ".join(parts)

    def _step(self) -> tuple[float, float]:
        self.cycles += 1
        c = self.cycles
        if self.cycles > self.budget:
            self.done = True
            return 0.0, 0.0
        if self.phase == "back off":
            if math.dist(self._front(), self._start) <= self.backoff_m:
                return back_off(c)
            s, lat, _heading = self._path_frame()
            self.side = 1 if lat >= 0 else -1
            # beside the robot, out to the line first (further if a module off the path is
            # in the way along); behind the face (a foot going round again) it is there
            if s > 0 and abs(lat) < self._clearance(s) - 0.01 and self.cycles < self.budget // 4:
                return back_off(c)
            self.phase = "along"
        aim = self.park[0] - self.margin_m  # where the sideways leg runs
        clear = self.clear_m
        if self.phase == "along":
            s, lat, heading = self.state(path=True)
            clear = self._clearance(s)
            # across from up to DIAGONAL_M before the line's end, leaning DIAGONAL_LEAN_DEG at
            # most, unless a module off the path is near
            early = min(self.diagonal_m, max(0.0, lat - self.park[1]) / math.tan(math.radians(DIAGONAL_LEAN_DEG)))
            if s <= aim + early * (clear <= self.clear_m):
                self.phase = "aside"
        if self.phase != "along":
            s, lat, heading = self.state()
        crawl: Callable[[int], tuple[float, float]] | None = back_off
        if self.phase == "along":  # still along: ``clear`` is this cycle's, at this ``s``
            # leaning in by up to 29 degrees; out by up to 70 past a module off the path
            want = max(-1.2 if clear > self.clear_m else -0.5, min(0.5, 5.0 * (lat - clear)))
        elif self.phase == "aside":
            off, ahead = lat - self.park[1], s - aim
            if abs(off) <= 0.02 and aim - 0.02 <= s <= self.park[0] + 0.01:
                self.phase, want, crawl = "square", 0.0, None
            elif s > 0 and lat < ALONGSIDE_M:  # beside the target module: not into it
                want = 0.0
            elif -ACROSS_BEHIND_M < ahead < 0:  # a little too far back: across, not about
                want = math.copysign(math.pi / 2, off)
            else:
                # back first towards the spot (the foot moves away from where its front
                # points; too far back, it turns about and backs towards the face); the
                # gait's drift is corrected as the foot's place is read again
                want = math.atan2(off, ahead)
        else:
            want, crawl = 0.0, None
        err = (want - heading + math.pi) % (2 * math.pi) - math.pi
        # a turn ends on target or just past it; facing about the other way, the error's sign
        # flips from cycle to cycle, and the turn keeps its direction
        if self._turning and (abs(err) < math.radians(4) or (self._turning * err < 0 and abs(err) < math.pi / 2)):
            self._turning = 0
        if not self._turning and abs(err) > math.radians(6 if crawl is None else 8):
            self._turning = 1 if err > 0 else -1
        if self._turning:
            return turn(c, self._turning * self.side)
        if self.phase == "square":
            if s > self.park[0] + 0.02:  # pushed alongside the target module: back along again
                self.phase = "along"
            elif abs(lat - self.park[1]) > 0.03 or s < aim - 0.025:
                self.phase = "aside"
            else:  # the last centimetres are the dock's (Creep)
                self.done = self.arrived = True
            return 0.0, 0.0
        return crawl(c) if crawl is not None else (0.0, 0.0)
