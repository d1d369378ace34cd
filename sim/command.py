"""``dh2rt run PROGRAM --sim pybullet [--record run.gif [--camera fixed|follow] [--record-speed X]]
[--plot run.png] [--gui] [--trace t.jsonl]``:
the options and the command body of a physics run (:data:`PYBULLET`, registered as the
``pybullet`` simulator in the ``dh2rt.simulators`` entry-point group).

``dh2rt run --help`` imports this module to list the options, so PyBullet, numpy and the
recorder are imported only when a physics run starts."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from dh2rt.cmdline import (
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    PLOT_SUFFIXES,
    STDOUT,
    err,
    output_path,
    print_summary,
    timed_run,
)
from dh2rt.errors import DH2Error, OptionError
from dh2rt.events import Event
from dh2rt.plugins import OptionAdder
from dh2rt.robot import Robot
from dh2rt.trace import TraceWriter

if TYPE_CHECKING:
    from sim.runner import PhysicsRun


class PybulletSimulator:
    """``--sim pybullet``: the modules' joints in PyBullet (a :class:`dh2rt.plugins.Simulator`)."""

    def add_arguments(self, parser: OptionAdder) -> None:
        parser.add_argument("--record", type=Path, metavar="GIF", help="write an animation (.gif)")
        parser.add_argument(
            "--camera",
            choices=("fixed", "follow"),
            default="fixed",
            help="with --record: the camera stays put over a checkered floor and jumps when the robot leaves "
            "the middle of the picture (fixed, the default), or follows the robot",
        )
        parser.add_argument(
            "--record-speed",
            type=float,
            default=1.0,
            metavar="X",
            help="with --record: play back X times faster than simulated time (fewer frames; default 1)",
        )
        parser.add_argument(
            "--plot", type=Path, metavar="PNG", help="plot the path, heading and joint angles (.png, .svg, .pdf)"
        )
        parser.add_argument("--gui", action="store_true", help="open PyBullet's window (needs a display)")

    def check(self, options: argparse.Namespace) -> None:
        """Apply the output rule to the output options before anything runs."""
        if options.record is not None:
            options.record = output_path(options.record, "--record", (".gif",))
        if not (math.isfinite(options.record_speed) and 0.1 <= options.record_speed <= 100.0):
            raise OptionError(f"--record-speed {options.record_speed:g}: must be between 0.1 and 100")
        if options.plot is not None:
            options.plot = output_path(options.plot, "--plot", PLOT_SUFFIXES)

    def run(self, robot: Robot, options: argparse.Namespace, events: list[Event]) -> int:
        return run_physics(robot, options, events)


#: What the ``pybullet`` entry point of ``dh2rt.simulators`` names.
PYBULLET = PybulletSimulator()


def traced(run: PhysicsRun, module: int, pos: list[float]) -> dict[str, object]:
    """A module's extra trace fields: its position and, in the cycle a docking motion of its
    latched, ``dock``: where both faces were at that moment (:meth:`sim.motion_readings.Contact.as_dict`)."""
    out: dict[str, object] = {"pos": pos}
    for contact in run.contacts:
        if contact.asking[0] == module and contact.cycle == run.robot.cycle - 1:
            out["dock"] = contact.as_dict()
    return out


def run_physics(robot: Robot, ns: argparse.Namespace, events: list[Event]) -> int:
    """``dh2rt run ... --sim pybullet``: run, record, plot, trace, summarise."""
    from sim.record import Recorder, plot_run, sample_world
    from sim.runner import STEPS_PER_CYCLE, PhysicsRun

    steps = STEPS_PER_CYCLE
    run = PhysicsRun(robot, gui=bool(getattr(ns, "gui", False)), steps_per_cycle=steps)
    trace = None
    if ns.trace:
        world = run.world
        trace = TraceWriter.open(ns.trace, robot, extra=lambda m: traced(run, m, list(world.module_position(m))))
    recorder = Recorder(run.world, Path(ns.record), camera=ns.camera, speed=ns.record_speed) if ns.record else None
    samples = run.samples = []  # filled here: sample_world adds the head and its heading

    def on_cycle(c: int) -> None:
        if trace is not None:
            trace.write_cycle()
        if ns.plot:
            samples.append(sample_world(run.world))
        if recorder is not None and recorder.due():
            recorder.capture(f"cycle {c + 1}")

    try:
        elapsed, interrupted = timed_run(lambda: run.run(ns.cycles, events, on_cycle), trace)
    except DH2Error as exc:  # an event that the robot's own docking made impossible
        if recorder is not None:
            recorder.abandon()
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
    if recorder is not None:
        if recorder.frame_count:
            print(f"animation: {recorder.save()} ({recorder.frame_count} frames)", file=out)
        else:
            recorder.abandon()
    if ns.plot and samples:
        title = f"{robot.program.name} on {robot.topology.spec}"
        names = list(robot.topology.names)
        print(f"plot: {plot_run(samples, Path(ns.plot), title=title, names=names)}", file=out)
    run.close()
    return EXIT_INTERRUPTED if interrupted else EXIT_OK
