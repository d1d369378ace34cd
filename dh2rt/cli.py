"""The ``dh2rt`` command.

``dh2rt check PROGRAM``          exit 0 if valid, else 2 with FILE:LINE:COL, the line and a caret
``dh2rt run PROGRAM ...``        run a robot headless in one process; per-module summary
``dh2rt image PROGRAM -o FILE``  write the program's image (what is flashed) and print its hash
``dh2rt types``                  the topology profile's types and their status tuples
``dh2rt demo``                   the embedded default demo (no hardware, no SocketCAN)
``dh2rt [--transport ...]``      the hardware-in-the-loop launcher (hil.launcher), when installed

Exit codes: 0 success, 1 a run failed, 2 bad input (program, topology, event, option),
130 interrupted (Ctrl-C; the summary so far is still printed).
"""

from __future__ import annotations

import argparse
import gc
import importlib
import json
import signal
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, Any

from dh2rt import __version__
from dh2rt.compiler import CompiledProgram, compile_file
from dh2rt.errors import DH2Error, ProgramError
from dh2rt.events import Event, parse_event
from dh2rt.profile import CONRO
from dh2rt.robot import Robot
from dh2rt.topology import BUILTIN_NAMES, parse_spec
from dh2rt.trace import TraceWriter

EXIT_OK, EXIT_FAIL, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130

#: Lazily imported extensions (python-can style registry: nothing is imported until chosen).
#: They live in higher layers, so the core names them but never imports them statically.
PHYSICS_RUNNERS = {"pybullet": "sim.runner:run_physics"}
LAUNCHER = "hil.launcher:main"
SUBCOMMANDS = ("check", "run", "image", "types", "demo")


def _load(ref: str) -> Callable[..., Any]:
    module, _, attr = ref.partition(":")
    fn: Callable[..., Any] = getattr(importlib.import_module(module), attr)
    return fn


def _err(message: str) -> None:
    print(f"dh2rt: {message}", file=sys.stderr)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dh2rt",
        description="Run DH2 hormone programs on modular self-reconfigurable robots.",
        epilog="With no subcommand, dh2rt starts the hardware-in-the-loop launcher "
        "(see `dh2rt --transport inproc --help`).",
    )
    parser.add_argument("--version", action="version", version=f"dh2rt {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    check = sub.add_parser("check", help="check a program; exit 2 with FILE:LINE:COL on error")
    check.add_argument("program", type=Path, help="a .dh2 file")

    run = sub.add_parser("run", help="run a robot in one process and print a per-module summary")
    add_run_options(run)
    run.add_argument("--sim", choices=sorted(PHYSICS_RUNNERS), help="run the modules' joints in physics")
    run.add_argument("--record", type=Path, metavar="GIF", help="with --sim: write an animation")
    run.add_argument("--plot", type=Path, metavar="PNG", help="with --sim: plot joint angles and displacement")
    run.add_argument("--gui", action="store_true", help="with --sim: open PyBullet's window (needs a display)")
    run.add_argument("--json", action="store_true", help="print the summary as JSON")

    image = sub.add_parser("image", help="write a program's image (what gets flashed) and print its hash")
    image.add_argument("program", type=Path)
    image.add_argument("-o", "--output", type=Path, required=True, help="image file to write")

    sub.add_parser("types", help="list the CONRO profile's topological types")

    demo = sub.add_parser("demo", help="run the embedded demo: caterpillar, live surgery, legs to snake")
    demo.add_argument("--cycles", type=int, default=240)
    return parser


def add_run_options(p: argparse.ArgumentParser, program_required: bool = True) -> None:
    """Options shared by ``dh2rt run`` and the hardware-in-the-loop launcher."""
    if program_required:
        p.add_argument("program", type=Path, help="a .dh2 file")
    p.add_argument(
        "--topology",
        default="snake:8",
        help=f"built-in ({', '.join(BUILTIN_NAMES)}) or a .toml file (default: snake:8)",
    )
    p.add_argument("--cycles", type=int, default=200, help="cycles to run (default: 200)")
    p.add_argument("--seed", type=int, default=0, help="seed for LocalTimer phases (default: 0)")
    p.add_argument(
        "--event",
        action="append",
        default=[],
        metavar="EV",
        help="CYCLE:cut:M.CONN | CYCLE:dock:M.CONN-M2.CONN2 | CYCLE:inject:M:HORMONE | "
        "CYCLE:kill:M | CYCLE:restart:M (repeatable)",
    )
    p.add_argument(
        "--trace", type=Path, metavar="FILE", help="write a JSON Lines trace, one object per module per cycle"
    )


def main(argv: Sequence[str] | None = None) -> int:
    args_list = list(sys.argv[1:] if argv is None else argv)
    if args_list and args_list[0] not in SUBCOMMANDS and args_list[0] not in ("-h", "--help", "--version"):
        return _launcher(args_list)
    if not args_list:
        return _launcher(args_list)
    parser = build_parser()
    ns = parser.parse_args(args_list)
    try:
        if ns.command == "check":
            return cmd_check(ns.program)
        if ns.command == "run":
            return cmd_run(ns)
        if ns.command == "image":
            return cmd_image(ns.program, ns.output)
        if ns.command == "types":
            return cmd_types(sys.stdout)
        if ns.command == "demo":
            return cmd_demo(ns.cycles)
    except KeyboardInterrupt:
        _err("interrupted")
        return EXIT_INTERRUPTED
    parser.print_help()
    return EXIT_USAGE


def _launcher(argv: list[str]) -> int:
    try:
        launch = _load(LAUNCHER)
    except ImportError as exc:
        _err(f"the hardware-in-the-loop launcher is not available ({exc}); try `dh2rt run --help`")
        return EXIT_USAGE
    code: int = launch(argv)
    return code


def load_program(path: Path) -> CompiledProgram:
    return compile_file(str(path))


def cmd_check(path: Path) -> int:
    try:
        cp = load_program(path)
    except ProgramError as exc:
        print(exc.render(), file=sys.stderr)
        return EXIT_USAGE
    print(
        f"{path}: ok: program {cp.name}, {len(cp.receptors)} receptors, {len(cp.vocabulary.by_index)} hormones, "
        f"ClockCycle {cp.clock_cycle}, image {len(cp.image)} bytes, sha256 {cp.hash[:16]}"
    )
    return EXIT_OK


def cmd_image(path: Path, output: Path) -> int:
    try:
        cp = load_program(path)
    except ProgramError as exc:
        print(exc.render(), file=sys.stderr)
        return EXIT_USAGE
    output.write_bytes(cp.image)
    print(f"{output}: {len(cp.image)} bytes, sha256 {cp.hash}")
    return EXIT_OK


def cmd_types(out: IO[str]) -> int:
    p = CONRO
    print(
        f"profile {p.name}: connectors "
        + ", ".join(f"{c} ({g})" for c, g in zip(p.connectors, p.genders, strict=True)),
        file=out,
    )
    for t in p.types:
        alias = f"T{t.alias}" if t.alias is not None else "-"
        tuples = "  ".join(p.describe(s) for s in sorted(t.statuses))
        print(f"  {t.name:<12} {alias:<4} {tuples}", file=out)
    return EXIT_OK


def prepare_run(ns: argparse.Namespace) -> tuple[CompiledProgram, Robot, list[Event]]:
    """Load program, topology and events for ``run`` (and the launcher); raises DH2Error."""
    cp = load_program(ns.program)
    topo = parse_spec(ns.topology, cp.profile)
    robot = Robot(cp, topo, seed=ns.seed)
    events = [parse_event(e, topo, cp.vocabulary) for e in ns.event]
    if ns.cycles < 0:
        raise DH2Error("--cycles must be 0 or more")
    return cp, robot, events


def cmd_run(ns: argparse.Namespace) -> int:
    try:
        _cp, robot, events = prepare_run(ns)
    except ProgramError as exc:
        print(exc.render(), file=sys.stderr)
        return EXIT_USAGE
    except (DH2Error, OSError) as exc:
        _err(str(exc))
        return EXIT_USAGE
    if ns.sim:
        runner = _load(PHYSICS_RUNNERS[ns.sim])
        code: int = runner(robot, ns, events)
        return code
    if ns.record or ns.plot or ns.gui:
        _err("--record, --plot and --gui need --sim pybullet")
        return EXIT_USAGE
    trace = TraceWriter.open(ns.trace, robot) if ns.trace else None
    robot.record = trace is not None
    # Everything built so far lives as long as the run: keep it out of the collector's
    # generations, so full collections do not keep scanning thousands of engines.
    gc.collect()
    gc.freeze()

    progress = Progress(ns.cycles, robot.size)
    stop = StopAtCycleEnd()

    def body() -> None:
        with stop:
            # without a trace nobody looks at single cycles: let the robot run in skewed windows
            for cycle in robot.run(ns.cycles, events, every_cycle=trace is not None):
                if trace is not None:
                    trace.write_cycle()
                progress.update(cycle + 1)
                stop.check()
        progress.done()

    elapsed, interrupted = timed_run(body, trace)
    print_summary(robot, elapsed, as_json=ns.json)
    if interrupted:
        if stop.forced:
            _err(f"interrupted during cycle {robot.cycle}: modules may be at different cycles")
        else:
            _err(f"interrupted at cycle {robot.cycle}")
        return EXIT_INTERRUPTED
    return EXIT_OK


class Progress:
    """A one-line progress report on stderr, redrawn at most twice a second; silent unless
    stderr is a terminal (pipes and logs get only the summary)."""

    def __init__(self, total: int, modules: int, stream: IO[str] | None = None) -> None:
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty() and total > 0
        self.total = total
        self.modules = modules
        self.started = self.last = time.perf_counter()
        self.last_cycle = 0
        self.shown = False

    def update(self, cycle: int) -> None:
        if not self.enabled or cycle - self.last_cycle < 64:
            return
        self.last_cycle = cycle
        now = time.perf_counter()
        if now - self.last < 0.5:
            return
        self.last = now
        rate = cycle * self.modules / (now - self.started)
        self.stream.write(f"\rcycle {cycle}/{self.total} ({cycle * 100 // self.total}%), {rate:,.0f} module-cycles/s ")
        self.stream.flush()
        self.shown = True

    def done(self) -> None:
        if self.shown:
            self.stream.write("\r" + " " * 72 + "\r")
            self.stream.flush()


class StopAtCycleEnd:
    """Ctrl-C stops the run at the end of the cycle (or skewed window) being computed, so the
    summary shows every module at the same cycle; a second Ctrl-C stops at once."""

    def __init__(self) -> None:
        self.requested = False
        self.forced = False  # the second Ctrl-C: stopped wherever the run was
        self._old: Any = None

    def __enter__(self) -> StopAtCycleEnd:
        try:
            self._old = signal.signal(signal.SIGINT, self._on_sigint)
        except ValueError:  # not the main thread: Ctrl-C is not ours to handle
            self._old = None
        return self

    def __exit__(self, *_exc: object) -> None:
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)

    def _on_sigint(self, _signum: int, _frame: object) -> None:
        if self.requested:
            self.forced = True
            raise KeyboardInterrupt
        self.requested = True

    def check(self) -> None:
        if self.requested:
            raise KeyboardInterrupt


def timed_run(body: Callable[[], None], trace: TraceWriter | None = None) -> tuple[float, bool]:
    """Run ``body`` until it ends or Ctrl-C; close the trace either way.

    Returns (seconds, interrupted): an interrupted run still gets its summary printed.
    """
    interrupted = False
    started = time.perf_counter()
    try:
        body()
    except KeyboardInterrupt:
        interrupted = True
    finally:
        if trace is not None:
            trace.close()
    return time.perf_counter() - started, interrupted


def print_summary(robot: Robot, elapsed: float, as_json: bool = False, out: IO[str] | None = None) -> None:
    out = out or sys.stdout
    rows = robot.summary()
    if as_json:
        json.dump({"cycles": robot.cycle, "seconds": elapsed, "modules": rows}, out)
        out.write("\n")
        return
    rate = robot.cycle * robot.size / elapsed if elapsed > 0 else 0.0
    print(
        f"{robot.program.name} on {robot.topology.spec}: {robot.size} modules, {robot.cycle} cycles "
        f"in {elapsed:.3f} s ({rate:,.0f} module-cycles/s), seed {robot.seed}",
        file=out,
    )
    print(
        f"{'module':<12} {'type':<12} {'T':>3} {'DOF1':>6} {'DOF2':>6} "
        f"{'recv':>6} {'sent':>6} {'fwd':>5} {'faults':>6}",
        file=out,
    )
    for r in rows:
        if not r["alive"]:
            print(f"{r['name']:<12} {'(stopped)':<12}", file=out)
            continue
        alias = "" if r["T"] is None else str(r["T"])
        print(
            f"{r['name']:<12} {r['type']:<12} {alias:>3} {r['DOF1']:>6.0f} {r['DOF2']:>6.0f} {r['received']:>6} "
            f"{r['sent']:>6} {r['forwarded']:>5} {r['faults']:>6}",
            file=out,
        )
    for line in robot.log[-20:]:
        print(f"  {line}", file=out)


def cmd_demo(cycles: int) -> int:
    from dh2rt.demo import run_demo

    return run_demo(cycles, sys.stdout)


if __name__ == "__main__":
    sys.exit(main())
