"""``dh2rt run PROGRAM --sim pybullet [--record run.gif] [--plot run.png] [--trace t.jsonl]``:
the command body of a physics run (registered as the ``pybullet`` simulator in the
``dh2rt.simulators`` entry-point group)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from dh2rt.cmdline import EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, STDOUT, err, print_summary, timed_run
from dh2rt.errors import DH2Error
from dh2rt.events import Event
from dh2rt.robot import Robot
from dh2rt.trace import TraceWriter
from sim.record import Recorder, plot_run
from sim.runner import STEPS_PER_CYCLE, PhysicsRun


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

    try:
        elapsed, interrupted = timed_run(lambda: run.run(ns.cycles, events, on_cycle, sample=bool(ns.plot)), trace)
    except DH2Error as exc:  # an event that the robot's own docking made impossible
        run.close()
        err(str(exc))
        return EXIT_USAGE
    # standard output holds only the trace (--trace -) or the JSON summary (--json)
    to_stdout = ns.trace != STDOUT
    print_summary(robot, elapsed, as_json=ns.json, out=sys.stdout if to_stdout else sys.stderr)
    out = sys.stdout if to_stdout and not ns.json else sys.stderr
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
