"""DH2 robots in physics: the in-process engines drive the PyBullet world's joints.

Each control cycle: the robot takes one lockstep cycle (hormones cross one link), every
module whose DOF1/DOF2 changed commands its driver, and the world advances
``steps_per_cycle`` physics steps. The drivers are the PyBullet stand-ins by default; any
:class:`drivers.base.ModuleDriver` can take their place (the Dynamixel driver talking to a
servo emulator whose joints are these same PyBullet joints runs the full firmware path).

Docking follows the world: a ``cut`` undocks both the logical link and the physical latch;
a ``dock`` (an event or a native action's ``reach_and_dock``) stays logical only if the two
connectors are physically aligned within tolerance, and is undone otherwise.

``dh2rt run PROGRAM --sim pybullet [--record run.gif] [--plot run.png] [--trace t.jsonl]``
ends here (see :func:`run_physics`).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

from dh2rt.cli import EXIT_INTERRUPTED, EXIT_OK, print_summary, timed_run
from dh2rt.events import Event
from dh2rt.robot import DOCK_DELAY, Robot, reach_target
from dh2rt.trace import TraceWriter
from drivers.base import ModuleDriver
from sim.record import Recorder, Sample, plot_run
from sim.world import World

#: Physics steps per DH2 control cycle: 12 steps at 240 Hz = 50 ms per cycle.
STEPS_PER_CYCLE = 12
#: How far apart two connectors may be for a logical dock to hold physically.
DOCK_TOLERANCE_M = 0.02
DOCK_TOLERANCE_DEG = 20.0


class PhysicsRun:
    """A robot whose modules' joints live in a PyBullet world."""

    def __init__(
        self,
        robot: Robot,
        *,
        world: World | None = None,
        drivers: Sequence[ModuleDriver] | None = None,
        steps_per_cycle: int = STEPS_PER_CYCLE,
        gui: bool = False,
        settle: Callable[[], None] | None = None,
    ) -> None:
        self.robot = robot
        self.world = world or World(robot.topology, gui=gui, seed=robot.seed)
        self.drivers: list[ModuleDriver] = (
            list(drivers) if drivers else [self.world.driver(m) for m in range(robot.size)]
        )
        self.steps_per_cycle = steps_per_cycle
        #: Called after the joints are commanded and before physics steps: a driver whose
        #: writes are not acknowledged (Dynamixel SYNC_WRITE) can make sure they landed.
        self.settle = settle
        self._sent: list[tuple[float, float] | None] = [None] * robot.size
        self.start = self.world.centroid()
        self.samples: list[Sample] = []
        self.log = robot.log
        robot.effect_handlers["reach_and_dock"] = self._reach_and_dock

    # ------------------------------------------------------------ events and docking

    def apply(self, event: Event) -> None:
        if event.kind == "cut":
            other = self.robot.peer.get((event.module, event.connector))
            self.robot.apply(event)
            if other is not None:
                self.world.undock(event.module, event.connector)
        elif event.kind == "dock":
            self.robot.apply(event)
            self._physical_dock(event.module, event.connector, event.other, event.other_connector)
        else:
            self.robot.apply(event)

    def _physical_dock(self, a: int, ac: int, b: int, bc: int) -> None:
        if self.world.dock(a, ac, b, bc, tolerance_m=DOCK_TOLERANCE_M, tolerance_deg=DOCK_TOLERANCE_DEG):
            return
        self.robot.cut(a, ac)
        self.log.append(f"cycle {self.robot.cycle}: dock refused by physics: connectors not aligned")

    def _reach_and_dock(self, robot: Robot, module: int, args: tuple[object, ...]) -> None:
        # As the in-process world does, DOCK_DELAY cycles later; but the link changes only if
        # the two connectors are physically aligned by then. The bending and aligning motions
        # of the paper's [17] are not modelled, so far-apart connectors are refused (logged)
        # and nothing is released.
        connector, route = args
        assert isinstance(connector, int) and isinstance(route, tuple)

        def carry_out() -> None:
            target = reach_target(robot, module, connector, route)
            if target is None:
                return
            here, at = target
            if not self.world.aligned(module, connector, here, at, DOCK_TOLERANCE_M, DOCK_TOLERANCE_DEG):
                robot.log.append(
                    f"cycle {robot.cycle}: {robot.where(module, connector)} cannot reach {robot.where(here, at)}: "
                    "not aligned in the world"
                )
                return
            self.world.undock(here, at)
            robot.cut(here, at)
            robot.dock(module, connector, here, at)
            self.world.dock(module, connector, here, at, tolerance_m=DOCK_TOLERANCE_M, tolerance_deg=DOCK_TOLERANCE_DEG)
            robot.log.append(f"cycle {robot.cycle}: {robot.where(module, connector)} docked to {robot.where(here, at)}")

        robot.schedule(DOCK_DELAY, carry_out)

    # ------------------------------------------------------------ running

    def cycle(self) -> None:
        """One control cycle: engines, then joints, then physics."""
        self.robot.step()
        for m, e in enumerate(self.robot.engines):
            if e is None:
                continue
            target = (e.dof[0], e.dof[1])
            if target != self._sent[m]:
                self.drivers[m].set_targets(*target)
                self._sent[m] = target
        if self.settle is not None:
            self.settle()
        self.world.step(self.steps_per_cycle)

    def run(
        self,
        cycles: int,
        events: Iterable[Event] = (),
        on_cycle: Callable[[int], None] | None = None,
        sample: bool = False,
    ) -> None:
        by_cycle: dict[int, list[Event]] = {}
        for ev in events:
            by_cycle.setdefault(ev.cycle, []).append(ev)
        end = self.robot.cycle + cycles
        while self.robot.cycle < end:
            for ev in by_cycle.pop(self.robot.cycle, []):
                self.apply(ev)
            self.cycle()
            if sample:
                n = self.robot.size
                self.samples.append(
                    (self.world.time, [self.world.joint_angles(m) for m in range(n)], self.world.centroid())
                )
            if on_cycle is not None:
                on_cycle(self.robot.cycle - 1)

    def displacement(self) -> float:
        """Metres the robot's centroid moved along the direction its head faced at the start."""
        return self.world.travel(self.start)

    def close(self) -> None:
        self.world.close()


def run_physics(robot: Robot, ns: argparse.Namespace, events: list[Event]) -> int:
    """``dh2rt run ... --sim pybullet``: run, record, plot, trace, summarise."""
    steps = STEPS_PER_CYCLE
    run = PhysicsRun(robot, gui=bool(getattr(ns, "gui", False)), steps_per_cycle=steps)
    trace = None
    if ns.trace:
        world = run.world
        trace = TraceWriter.open(ns.trace, robot, extra=lambda m: {"pos": list(world.module_position(m))})
    recorder = Recorder(run.world, Path(ns.record)) if ns.record else None
    frame_every = max(1, round(run.world.physics_hz / (recorder.fps if recorder else 10) / steps))

    def on_cycle(c: int) -> None:
        if trace is not None:
            trace.write_cycle()
        if recorder is not None and c % frame_every == 0:
            recorder.capture()

    elapsed, interrupted = timed_run(lambda: run.run(ns.cycles, events, on_cycle, sample=bool(ns.plot)), trace)
    print_summary(robot, elapsed, as_json=ns.json)
    out = sys.stdout
    gait = robot.program.clock_cycle
    periods = robot.cycle / gait
    d = run.displacement()
    simulated = run.world.time
    print(
        f"physics: {simulated:.1f} s simulated in {elapsed:.1f} s ({simulated / elapsed:.1f}x real time); "
        f"moved {d * 100:+.1f} cm forward, {d * 100 / periods if periods else 0.0:+.2f} cm per gait cycle "
        f"({gait} cycles of {steps / run.world.physics_hz * 1000:.0f} ms)",
        file=out,
    )
    if recorder is not None and recorder.frame_count:
        print(f"animation: {recorder.save()} ({recorder.frame_count} frames)", file=out)
    if ns.plot:
        title = f"{robot.program.name} on {robot.topology.spec}"
        print(f"plot: {plot_run(run.samples, Path(ns.plot), title=title)}", file=out)
    run.close()
    return EXIT_INTERRUPTED if interrupted else EXIT_OK
