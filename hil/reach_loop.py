"""Docking by motion in the loop: a ``reach_dock`` carried out by the modules' own motion.

With the PyBullet stand-in, the hardware-in-the-loop world carries a native's ``reach_dock``
(dock my connector to a connector of the module a route leads to) out as the physics runner
does (``sim.runner.PhysicsRun.start_reach``): the chain of modules along the route bends,
aligns and approaches by :class:`sim.reach.Reach` on the stand-in's PyBullet world, one
step per world cycle, and the latch closes only when the world says the faces are aligned
within ``DOCK_TOLERANCE_M`` / ``DOCK_TOLERANCE_DEG`` *and* the asking connector's infrared
pair sees the target within them. Then the world docks the link as for a ``dock`` event (the
emulated serial link or the link map, the contact emulator on a bus), after the latch in
physics; a motion that gives up (``sim.reach.DEFAULT_TIMEOUT`` steps) links nothing.

The modules move themselves: each world cycle the world sends every module of the chain a
:class:`hil.control.Hold` with the joint targets the motion wants of it; the module writes
them to its own servos through its own driver (dynamixel-sdk over its pty) in place of its
program's DOF1/DOF2 from its next cycle on, and an empty ``Hold`` gives the joints back to
its program when the motion ends. The world never writes a joint itself. docs/hil.md
("Docking by motion in the loop") says why and what it costs.

Every latch is recorded in :attr:`LoopReaches.contacts` (a :class:`sim.reach.Contact`: both
faces' world poses, distance, attitude error and the infrared reading at that moment) and
logged with the cycles it took; every motion that gave up, in :attr:`LoopReaches.failed`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from dh2rt import docking
from hil.physics_stand_in import PhysicsStandIn
from sim.reach import Chain, Contact, Reach
from sim.runner import DOCK_TOLERANCE_DEG, DOCK_TOLERANCE_M
from sim.sensors import PhysicsSensors

if TYPE_CHECKING:
    from hil.world import World


@dataclass
class Motion:
    """One docking motion under way in the loop."""

    reach: Reach
    #: ``asking -> target`` in words
    where: str
    #: the world cycle it was asked at, and the one its plan was ready at
    asked: int
    planned: int
    #: seconds the plan took (sim.reach.plan, in the world's thread)
    plan_s: float
    #: the world cycle it was last stepped at, and the world cycles since its plan was ready
    #: that went by without a step (the world's thread came too late for them)
    last: int = -1
    missed: int = 0

    @property
    def modules(self) -> set[int]:
        return {m for m, _ in self.reach.chain.joints}


@dataclass(frozen=True)
class Outcome:
    """How a motion ended: world cycles (asked, plan ready, latched or given up), its steps,
    the world cycles it missed, the plan's seconds."""

    asked: int
    planned: int
    ended: int
    steps: int
    missed: int
    plan_s: float
    latched: bool


class LoopReaches:
    """The docking motions of a loop world whose body is the PyBullet stand-in."""

    def __init__(self, world: World, physics: PhysicsStandIn) -> None:
        self.world = world
        self.physics = physics
        model = physics.world.model
        with physics.lock:
            #: The infrared pairs the motions read (every connector's), as PhysicsRun's.
            self.ir = PhysicsSensors(
                physics.world, [f"ir_{c.name}{s}" for c in model.connectors for s in ("", "_align")]
            )
        self.motions: list[Motion] = []
        #: Every link formed by a motion, and every motion that gave up.
        self.contacts: list[Contact] = []
        self.failed: list[Contact] = []
        #: How each motion ended (those abandoned because a module stopped are only logged).
        self.outcomes: list[Outcome] = []
        #: What each module was last told to hold (absent: its joints are its program's).
        self.holding: dict[int, dict[int, float]] = {}

    def start(self, module: int, connector: int, route: Sequence[int], target_conn: int) -> bool:
        """Begin bending ``module``'s ``connector`` to ``target_conn`` of the module at the end
        of ``route``; False (logged) if the rules say no or a motion already holds one of the
        chain's joints."""
        w = self.world
        target = docking.reach_dock_target(w, module, connector, route, target_conn)
        if target is None:
            return False
        here, where = target
        if not w.profile.can_link(connector, target_conn):
            w.note(f"reach_dock {where}: both connectors are {w.profile.gender(connector)}")
            return False
        chain = Chain.along(self.physics.world.model, (module, connector), tuple(route), w.peer_of, target_conn)
        if any(m in motion.modules for motion in self.motions for m, _ in chain.joints):
            w.note(f"reach_dock {where}: another docking motion owns part of the chain")
            return False
        world = self.physics.world

        def aligned() -> bool:  # called inside Reach.step, which the caller runs under the lock
            return world.aligned(module, connector, here, target_conn, DOCK_TOLERANCE_M, DOCK_TOLERANCE_DEG)

        cycle, started = w.cycle, time.perf_counter()
        reach = Reach(
            world,
            self.ir,
            chain,
            aligned,
            DOCK_TOLERANCE_M,
            DOCK_TOLERANCE_DEG,
            start_cycle=cycle,
            lock=self.physics.lock,
        )
        plan_s, planned = time.perf_counter() - started, w.cycle
        self.motions.append(Motion(reach, where, cycle, planned, plan_s, last=planned - 1))
        modules = sorted({m for m, _ in chain.joints})
        w.note(
            f"reach_dock {where}: bending ({len(chain.joints)} joints of modules {modules}; asked at world cycle "
            f"{cycle}, planned in {plan_s:.2f} s)"
        )
        return True

    def step(self, cycle: int) -> None:
        """Once per world cycle: advance every motion by one step, send the chain's modules
        the targets to hold, and latch (or give up) those that are done."""
        due = [motion for motion in self.motions if cycle > motion.last]
        if not due:
            return
        w = self.world
        holds: dict[int, dict[int, float]] = {}
        done: list[Motion] = []
        with self.physics.lock:
            for motion in due:
                motion.missed += cycle - motion.last - 1
                motion.last = cycle
                reach = motion.reach
                (a, _), (b, _) = reach.chain.asking, reach.chain.target
                if not all(w.running(m) for m in {a, b} | motion.modules):
                    self.motions.remove(motion)
                    w.note(f"reach_dock {motion.where}: a module of the chain stopped; motion abandoned")
                    continue
                targets = reach.step(cycle)
                if reach.done:
                    self.motions.remove(motion)
                    done.append(motion)
                    continue
                for m, dofs in targets.items():
                    holds.setdefault(m, {}).update(dofs)
        for motion in done:  # outside the lock: the latch takes it
            self._finish(motion, cycle)
        self._send_holds(holds)

    def _finish(self, motion: Motion, cycle: int) -> None:
        w, reach = self.world, motion.reach
        (a, ac), (b, bc) = reach.chain.asking, reach.chain.target
        contact = reach.contact
        assert contact is not None
        how = (
            f"{contact.distance_m * 1000:.1f} mm, {contact.attitude_deg:.1f} deg apart; infrared "
            f"{contact.ir_mm:.1f} mm, {contact.ir_align_deg:.1f} deg"
        )
        took = f"{reach.cycles} steps, world cycles {motion.asked}-{cycle}, {motion.missed} missed"
        latched = reach.latched and w.latch(a, ac, b, bc)
        outcome = Outcome(motion.asked, motion.planned, cycle, reach.cycles, motion.missed, motion.plan_s, latched)
        self.outcomes.append(outcome)
        if latched:
            self.contacts.append(contact)
            w.note(f"{w.where(a, ac)} docked to {w.where(b, bc)} by motion after {took} ({how})")
            return
        self.failed.append(contact)
        w.note(f"reach_dock {motion.where} gave up after {took} ({how})")

    def _send_holds(self, holds: dict[int, dict[int, float]]) -> None:
        """Tell the chains' modules what to hold; modules no motion holds any more get their
        joints back (an empty hold)."""
        for m in [m for m in self.holding if m not in holds]:
            del self.holding[m]
            self.world.hold(m, {})
        for m, dofs in holds.items():
            rounded = {dof: round(v, 2) for dof, v in dofs.items()}
            if self.holding.get(m) != rounded:
                self.holding[m] = rounded
                self.world.hold(m, rounded)

    def release_all(self) -> None:
        """Give every held joint back (the world stops)."""
        self._send_holds({})
