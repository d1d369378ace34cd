"""A chain of modules bends one free connector onto another: the docking motion, sans-IO.

:class:`Reach` is the motion, stepped once a control cycle with that cycle's
:class:`firmware.motion.readings.Readings` (the chain's joint angles, the asking connector's
infrared pair, the overhead tracker's poses); it returns the joint targets the chain's modules
hold, in three phases:

``bend``
    joint targets move, at most :data:`BEND_STEP_DEG` a cycle, towards the configuration that
    puts the asking face :data:`STANDOFF_M` in front of the target, square to it (for a
    target that creeps towards the face itself, on the face's axis and square at whatever
    distance: :attr:`firmware.motion.kinematics.Chain.free_distance`);
``approach``
    the standoff shrinks to zero (and a little past it, :data:`PRESS_M`) while the chain
    keeps the faces square (a ``settle`` and a ``close`` phase between: :meth:`Reach.step`);
``latch``
    the asking connector's infrared pair sees the face within the tolerance: the motion asks
    for the latch (the infrared reading does not steer the chain: the single pair gives no
    bearing).

Where the target face is relative to the asking face (:meth:`Reach.relative`) comes from the
asking module's own joint to its own centre, and from there the overhead tracker's poses of
that centre and of the target's part: the docks along a bent chain give under its load (up to
9 degrees a dock), so the chain's forward kinematics from its far end put the asking face
centimetres from where it is. Without the tracker's report (``tracked=False``, or no report
yet) it is the chain's forward kinematics of the *measured* joint angles (proprioception),
and for a target on another body (:meth:`firmware.motion.kinematics.Chain.to_other`, a foot
lying apart) the tracker's pose of the target's part from the chain's end. The planner and the
least-squares steps use the chain's kinematics either way. Nothing here reads a simulator.

A chain that closes a loop on its own robot runs a pitch wave in every phase
(:data:`WIGGLE_DEG`): its modules are pressed and unloaded in turn, so that its yaws are not
stalled by the floor's friction on the modules they drag.

The latch is not the motion's to close: the motion *asks* for it (:meth:`Reach.asks_latch`)
when the asking connector's infrared pair sees a face within the tolerance; whether the latch
closes is physics, and the owner answers (:meth:`Reach.latch` when it did). A reach that does
not latch within ``timeout`` cycles gives up.
"""

from __future__ import annotations

import math

import numpy as np

from firmware.motion.body import CENTRE
from firmware.motion.kinematics import ROT_WEIGHT_M, Chain, dls_step, plan
from firmware.motion.readings import Readings

#: How far in front of the target face the asking face stops before the approach (metres).
STANDOFF_M = 0.03
#: How far past contact the approach aims (metres): the faces press lightly.
PRESS_M = 0.004
#: Largest joint target change per control cycle while closing in (degrees): 40 deg/s.
MAX_STEP_DEG = 2.0
#: Largest joint target change per cycle while bending to the planned configuration (degrees).
BEND_STEP_DEG = 2.0
#: The bend is done when every joint is within this of its target (degrees) ...
SETTLED_DEG = 6.0
#: ... or after this many cycles of waiting.
SETTLE_CYCLES = 60
#: How fast the standoff closes during the approach (metres per control cycle).
APPROACH_M_PER_CYCLE = 0.0015
#: Cycles the close phase may take before the approach starts anyway (two yaws cannot always
#: square the faces and place them at once: the approach then closes what is left).
CLOSE_CYCLES = 40
#: The pitch wave the chain runs while it moves (degrees, amplitude): a yaw that has to drag
#: three or four modules over the floor (friction 0.9, about 0.5 N m) stalls the 0.3 N m
#: servos; with the chain's pitch joints swinging, adjacent modules in antiphase, each
#: module is pressed and unloaded in turn and the yaws advance while the friction drops.
WIGGLE_DEG = 20.0
#: ... and its period (control cycles).
WIGGLE_PERIOD = 6
#: Fraction of the least-squares correction applied each cycle.
GAIN = 0.3
#: Cycles a reach may take before it gives up.
DEFAULT_TIMEOUT = 400


class Reach:
    """One docking motion, stepped once per control cycle by its owner.

    ``readings`` is the first cycle's (the plan starts from the measured angles, and a
    target on another body from the tracker's poses). Each cycle the owner asks
    :meth:`asks_latch`; if it does and the latch closed, :meth:`latch`; else :meth:`step`,
    whose joint targets (degrees) the chain's modules hold. :attr:`done` ends it;
    :attr:`latched` says how.
    """

    def __init__(
        self,
        chain: Chain,
        readings: Readings,
        tolerance_m: float,
        tolerance_deg: float,
        *,
        timeout: int = DEFAULT_TIMEOUT,
        start_cycle: int = 0,
        wiggle_deg: float | None = None,
        tracked: bool = True,
    ) -> None:
        self.chain = chain
        #: Whether a chain along the robot closes its loop on the overhead tracker's view of
        #: both faces' modules when the readings carry it (:meth:`relative`); False: on its
        #: kinematics alone.
        self.tracked = tracked
        self._own_centre = Chain.to_own_centre(chain.model, chain.asking)
        self.tolerance_m = tolerance_m
        self.tolerance_deg = tolerance_deg
        self.timeout = timeout
        self.start_cycle = start_cycle
        #: The pitch wave's amplitude: :data:`WIGGLE_DEG` for a loop that closes on the robot
        #: itself, none towards a body lying apart (a pitch wave makes the chain crawl, the
        #: caterpillar's gait, and that would carry the asking face away from it).
        self.wiggle_deg = wiggle_deg if wiggle_deg is not None else (0.0 if chain.anchor is not None else WIGGLE_DEG)
        self.limits = chain.limits_rad()
        name = chain.model.connector(chain.asking[1]).name
        self._ir = (f"ir_{name}", f"ir_{name}_align")
        self.phase = "bend"
        self._settling = 0  # cycles spent in the settle phase
        self._closing = 0  # cycles spent in the close phase
        self.cycles = 0
        self.done = False
        self.latched = False
        self.standoff = STANDOFF_M
        self.command = self.measured(readings)
        self.relative(readings)  # measures chain.beyond for a target on another body
        #: The configuration the bend heads for: the chain's kinematics solved from a few
        #: starting curls (the loop may close either way round), the best kept.
        self.plan = plan(chain, self.command, self.limits, STANDOFF_M)

    @property
    def modules(self) -> set[int]:
        """The modules whose joints the motion moves."""
        return {m for m, _ in self.chain.joints}

    def measured(self, readings: Readings) -> np.ndarray:
        """The chain's joint angles (radians) as the modules measure them (``pos1``, ``pos2``)."""
        return np.array([math.radians(readings.joint(m, dof)) for m, dof in self.chain.joints])

    def infrared(self, readings: Readings) -> tuple[float, float]:
        """The asking connector's reading: distance (mm, 0 = nothing) and angle off square."""
        m = self.chain.asking[0]
        return readings.ir(m, self._ir[0]), readings.ir(m, self._ir[1])

    def relative(self, readings: Readings) -> np.ndarray:
        """The target connector's part in the asking connector's part frame, as it is now
        (module docs): the asking module's own joint and the tracker's poses of its centre and
        of the target's part; without the tracker (``tracked`` False), the chain's forward
        kinematics of the measured joint angles, and for a target on another body the tracker's
        pose of the target's part seen from the chain's end
        (:attr:`firmware.motion.kinematics.Chain.beyond`, both on the floor plane), which is
        measured either way: the least-squares steps differentiate the chain with it."""
        chain = self.chain
        if chain.anchor is not None:
            anchor = readings.floor.part(*chain.anchor).transform()
            target_link = chain.model.connector(chain.target[1]).link
            target = readings.floor.part(chain.target[0], target_link).transform()
            chain.beyond = np.linalg.solve(anchor, target)
        oracle = readings.oracle.get((chain.asking, chain.target))
        if oracle is not None:  # measuring only (Readings.oracle)
            return oracle
        if self.tracked and readings.floor.modules:
            # the chain bends through docks that give (a docked pair twists by up to 9 degrees
            # under a bent chain's load): the asking module's own centre by its own joint, and
            # from there the target's part as the tracker sees both on the floor
            q = {j: math.radians(readings.joint(*j)) for j in self._own_centre.joints}
            centre = self._own_centre.target_part(np.array([q[j] for j in self._own_centre.joints]))
            # tilted as the asking module's IMU reads it (the pitch wave rocks it)
            asking_tilt = readings.attitude.get(chain.asking[0], (0.0, 0.0))
            a = readings.floor.part(chain.asking[0], CENTRE).transform(*asking_tilt)
            target_link = chain.model.connector(chain.target[1]).link
            # on the robot, the target's part tilted as its module's IMU reads it (an
            # approximation for a part on a pitch joint; the targets along the robot lie on the
            # yaw joint's back part); a foot lying apart is flat: its IMU, at its centre, rocks
            # with the creep's pitch, which its front part does not share that way
            tilt = readings.attitude.get(chain.target[0], (0, 0)) if chain.anchor is None else (0, 0)
            b = readings.floor.part(chain.target[0], target_link).transform(*tilt)
            out: np.ndarray = centre @ np.linalg.solve(a, b)
            return out
        return chain.target_part(self.measured(readings))

    def targets(self) -> dict[int, dict[int, float]]:
        """module -> {dof: degrees} of the current command."""
        out: dict[int, dict[int, float]] = {}
        for (m, dof), v in zip(self.chain.joints, self.command, strict=True):
            out.setdefault(m, {})[dof] = math.degrees(float(v))
        if self.wiggle_deg and not self.done:
            # the pitch wave: adjacent modules in antiphase, so each is unloaded in turn
            swing = self.wiggle_deg * math.sin(2 * math.pi * self.cycles / WIGGLE_PERIOD)
            pitches = [m for m, dof in self.chain.joints if dof == 0]
            for k, m in enumerate(pitches):
                out[m][0] += swing if k % 2 == 0 else -swing
        return out

    def asks_latch(self, readings: Readings) -> bool:
        """Whether the asking connector's infrared pair sees a face within the tolerance: the
        motion asks its owner to close the latch."""
        ir, ir_align = self.infrared(readings)
        return 0 < ir <= self.tolerance_m * 1000 and ir_align <= self.tolerance_deg

    def latch(self) -> dict[int, dict[int, float]]:
        """The owner closed the latch this cycle: the motion is done; the joint targets held."""
        self.cycles += 1
        self.done = self.latched = True
        return self.targets()

    def step(self, readings: Readings) -> dict[int, dict[int, float]]:
        """Advance the motion by one control cycle (no latch this cycle); the joint targets to
        hold. Past ``timeout`` cycles the motion gives up (:attr:`done`, not :attr:`latched`)."""
        self.cycles += 1
        if self.cycles > self.timeout:
            self.done = True
            return self.targets()
        q_now = self.measured(readings)
        e = self.chain.error_of(self.relative(readings), self.standoff)
        if self.phase == "bend":
            gap = self.plan - self.command
            step = np.clip(gap, -math.radians(BEND_STEP_DEG), math.radians(BEND_STEP_DEG))
            self.command = self.command + step
            if float(np.max(np.abs(gap))) > math.radians(BEND_STEP_DEG):
                return self.targets()
            self.phase, self._settling = "settle", 0
        if self.phase == "settle":
            # the servos drag the chain over the floor: wait until they are where they were sent
            self._settling += 1
            lag = float(np.max(np.abs(q_now - self.command)))
            if lag > math.radians(SETTLED_DEG) and self._settling < SETTLE_CYCLES:
                return self.targets()
            self.phase, self._closing = "close", 0
        if self.phase == "close":
            self._closing += 1
            square = float(np.linalg.norm(e[:3])) < 0.008 and float(np.linalg.norm(e[3:])) < 0.3 * ROT_WEIGHT_M
            if square or self._closing >= CLOSE_CYCLES:
                self.phase = "approach"
        if self.phase == "approach":
            self.standoff = max(-PRESS_M, self.standoff - APPROACH_M_PER_CYCLE)
        dq = dls_step(self.chain, q_now, e, self.standoff, damping=0.05, pitch_weight=0.02)
        step = np.clip(GAIN * dq, -math.radians(MAX_STEP_DEG), math.radians(MAX_STEP_DEG))
        self.command = np.clip(self.command + step, -self.limits, self.limits)
        return self.targets()
