"""Legs to snake in physics, run whole from Python: the dragon, LTS, until it is one snake.

What tests/sim/test_legs_to_snake_physics.py and ``python -m benchmarks.bench_legs_to_snake``
share: :func:`reconfigure` runs examples/legs_to_snake.dh2 (or another program) on the dragon
in a :class:`sim.runner.PhysicsRun`, injects LTS at spine0 on cycle 50 and steps the world
until the live modules form one snake (:func:`snake_of`) with every docking motion over, or
the budget runs out; :class:`KillWinner` kills the first winning foot on its trip or as its
dock begins (the issue's interruption). docs/physics.md, *Legs to snake in physics*.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

from dh2rt.events import parse_event
from dh2rt.profile import CONRO
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from firmware.motion.assimilating import SelfAssimilate
from sim.runner import PhysicsRun

DRAGON = parse_spec("dragon")
FRONT, BACK = CONRO.connector_index("front"), CONRO.connector_index("back")
#: Cycles a whole reconfiguration may take (measured 4,161 to 9,236 over the 72 runs of
#: benchmarks.bench_legs_to_snake at seeds 0 to 11, every one of which formed; docs/physics.md).
BUDGET = 11_000
#: When LTS is injected (at spine0).
LTS_CYCLE = 50
#: How far into its trip :class:`KillWinner` kills a foot on its way (cycles).
TRIP_KILL_CYCLES = 400
#: The interruptions :class:`KillWinner` knows: none, on the trip, as the dock begins.
KILLS = ("none", "trip", "dock")


def snake_of(robot: Robot) -> list[int] | None:
    """The live modules as one snake from head to tail (front/back links only), or None."""
    live = [m for m, e in enumerate(robot.engines) if e is not None]
    types = Counter(robot.engines[m].topo_type.name for m in live)  # type: ignore[union-attr]
    if types != Counter({"head": 1, "tail": 1, "body": len(live) - 2}):
        return None
    head = next(m for m in live if robot.engines[m].topo_type.name == "head")  # type: ignore[union-attr]
    chain = [head]
    while (peer := robot.peer_of((chain[-1], BACK))) is not None:
        if peer[1] != FRONT or peer[0] in chain:
            return None
        chain.append(peer[0])
    linked = {m for m, _c in robot.peer}
    return chain if len(chain) == len(live) and linked <= set(chain) else None


def reconfigure(
    program: CompiledProgram,
    seed: int,
    on_cycle: Callable[[PhysicsRun], None] | None = None,
    *,
    budget: int = BUDGET,
    setup: Callable[[PhysicsRun], None] | None = None,
    modules_move: bool = False,
) -> tuple[PhysicsRun, int | None]:
    """Run LTS on the dragon until it is one snake (or ``budget`` cycles pass); the run (the
    caller closes it) and the cycle the snake formed. ``setup`` adjusts the run before the
    first cycle; ``on_cycle`` is called after every cycle from LTS on. ``modules_move``: the
    modules carry out the docking themselves (sim.module_motions), not the run's sequence."""
    robot = Robot(program, DRAGON, seed=seed)
    run = PhysicsRun(robot, modules_move=modules_move)
    if setup is not None:
        setup(run)
    run.run(LTS_CYCLE)
    run.apply(parse_event(f"{LTS_CYCLE}:inject:spine0:LTS", DRAGON, program.vocabulary))
    while robot.cycle < budget:
        run.cycle()
        if on_cycle is not None:
            on_cycle(run)
        if not run.moving and snake_of(robot) is not None and len(run.contacts) >= 3:
            return run, robot.cycle
    return run, None


class KillWinner:
    """An ``on_cycle`` hook for :func:`reconfigure` that kills the first winning foot: on its
    trip (``"trip"``, :data:`TRIP_KILL_CYCLES` into it) or as the tail and it begin to close
    the dock (``"dock"``); ``"none"`` kills nothing. :attr:`killed` holds the foot killed."""

    def __init__(self, when: str) -> None:
        if when not in KILLS:
            raise ValueError(f"unknown kill {when!r}: one of {', '.join(KILLS)}")
        self.when = when
        self.killed: list[int] = []

    def __call__(self, run: PhysicsRun) -> None:
        if self.killed or self.when == "none":
            return
        foot = self._due(run)
        if foot is None:
            return
        self.killed.append(foot)
        run.robot.kill(foot)

    def _due(self, run: PhysicsRun) -> int | None:
        """The foot to kill now, if any: on its trip's cycle, or as the dock begins (the
        run's sequence, or the modules' own: a foot running its trip, an asker squaring)."""
        trips = [(b.trip.module, b.trip.cycles) for b in run.docking.trips]
        creeps = [m.creep.module for m in run.docking.motions if m.creep is not None]
        if run.module_motions is not None:
            for host in run.module_motions.hosts:
                foot = host.foot
                if foot is not None and not foot.done and foot.trip is not None:
                    trips.append((foot.module, foot.trip.cycles))
                reach = host.reach
                if isinstance(reach, SelfAssimilate) and reach.docking is not None and reach.foot is not None:
                    creeps.append(reach.foot)
        if self.when == "trip":
            return next((m for m, cycles in trips if cycles == TRIP_KILL_CYCLES), None)
        if self.when == "dock" and creeps:
            return creeps[0]
        return None
