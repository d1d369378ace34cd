"""What every dh2rt command shares: exit codes, error output, the run options, the bus and
cycle options, progress, Ctrl-C handling and the run summary (as python-can's ``can/cli.py``
serves its tools).

The umbrella command (:mod:`dh2rt.cli`) and the commands that live in upper layers (the
launcher in ``hil``, the physics runner in ``sim``, the tools in ``tools``) all build on this
module; none of them imports another's command module.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import IO, Any

from dh2rt.compiler import compile_file
from dh2rt.errors import OptionError
from dh2rt.events import Event, check_events, parse_event
from dh2rt.output_paths import check_output
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.runtime import CYCLE_PERIOD_S, MAX_CYCLE_PERIOD_S, s_to_ms
from dh2rt.topology import BUILTIN_NAMES, parse_spec
from dh2rt.trace import TraceWriter

#: Exit codes of every dh2rt command.
EXIT_OK, EXIT_FAIL, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


def err(message: str) -> None:
    """An error or notice for the user, on stderr, prefixed with the command's name."""
    print(f"dh2rt: {message}", file=sys.stderr)


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
        "CYCLE:kill:M | CYCLE:restart:M | CYCLE:sense:M:NAME=VALUE (sensor S.NAME of M reads VALUE from then "
        "on, e.g. 30:sense:m2:roll=90) (repeatable)",
    )
    p.add_argument(
        "--trace",
        type=Path,
        metavar="FILE",
        help="write a JSON Lines trace (.jsonl; - for standard output), one object per module per cycle",
    )


#: The robot's CAN bus bit rate: every command's ``--bitrate`` default (module.toml's too).
CAN_BITRATE = 1_000_000
#: The bit rates a CAN bus may have (bit/s), nominal or CAN FD's data phase.
BITRATES = (10_000, 12_000_000)


def add_bus_arguments(
    parser: argparse.ArgumentParser, *, group_title: str | None = None, required: bool = False
) -> argparse._ArgumentGroup:
    """``-i/--interface``, ``-c/--channel`` and ``-b/--bitrate`` of a python-can bus, named as
    python-can's own tools name them (its ``can/cli.py`` ``add_bus_arguments``), with one
    default bit rate for every dh2rt command. Returns their argument group, for a command's
    own bus options (``--fd``, ``--contact``)."""
    group = parser.add_argument_group(group_title or "the CAN bus, as python-can's own tools name it")
    group.add_argument(
        "-i",
        "--interface",
        required=required,
        help="python-can interface: socketcan, slcan, pcan, kvaser, gs_usb, virtual, udp_multicast, ...",
    )
    group.add_argument(
        "-c", "--channel", required=required, help="its channel: can0, vcan0, /dev/ttyACM0, PCAN_USBBUS1, ..."
    )
    group.add_argument(
        "-b",
        "--bitrate",
        type=int_in(*BITRATES),
        default=CAN_BITRATE,
        help=f"the bus's bit rate in bit/s, where the interface sets one (default: {CAN_BITRATE})",
    )
    return group


def bus_options(ns: argparse.Namespace) -> dict[str, Any]:
    """The python-can ``Bus`` arguments of :func:`add_bus_arguments`' options."""
    return {"interface": ns.interface, "channel": ns.channel, "bitrate": ns.bitrate}


def float_in(low: float, high: float, *, low_open: bool = False) -> Callable[[str], float]:
    """An argparse ``type``: a finite number from ``low`` (excluded when ``low_open``) to
    ``high``. argparse turns a refusal into exit 2 naming the option
    (``argument --cycle-ms: expected a number more than 0 and at most 60000, got 'nan'``)."""
    bounds = f"{'more than' if low_open else 'from'} {low:g} {'and at most' if low_open else 'to'} {high:g}"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not math.isfinite(value) or value > high or value < low or (low_open and value == low):
            raise argparse.ArgumentTypeError(f"expected a number {bounds}, got {text!r}")
        return value

    parse.__name__ = "number"  # what argparse says it expected, should it ever say so
    return parse


def int_in(low: int, high: int) -> Callable[[str], int]:
    """An argparse ``type``: a whole number from ``low`` to ``high`` (exit 2 naming the option)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number {low}..{high}, got {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected a whole number {low}..{high}, got {text!r}")
        return value

    parse.__name__ = "whole number"
    return parse


#: The longest cycle period any command accepts (ms).
MAX_CYCLE_MS = s_to_ms(MAX_CYCLE_PERIOD_S)
#: ``--cycle-ms``'s type: a finite period, more than 0 and at most MAX_CYCLE_MS.
positive_finite_ms = float_in(0.0, MAX_CYCLE_MS, low_open=True)
#: A probability option's type (``--frame-loss``): finite, 0 to 1.
probability = float_in(0.0, 1.0)


def add_cycle_argument(parser: argparse.ArgumentParser | argparse._ArgumentGroup, what: str) -> None:
    """``--cycle-ms``: the robot's cycle period in milliseconds (``ns.cycle_ms``; in seconds:
    :func:`dh2rt.runtime.ms_to_s`), whose default is the core's one (CYCLE_PERIOD_S)."""
    default = s_to_ms(CYCLE_PERIOD_S)
    parser.add_argument(
        "--cycle-ms",
        type=positive_finite_ms,
        default=default,
        help=f"{what}, more than 0 and at most {MAX_CYCLE_MS:g} (default: {default:g})",
    )


def load_program(path: Path) -> CompiledProgram:
    return compile_file(str(path))


def prepare_run(ns: argparse.Namespace) -> tuple[CompiledProgram, Robot, list[Event]]:
    """Load program, topology and events for ``run`` (and the launcher); raises DH2Error."""
    cp = load_program(ns.program)
    topo = parse_spec(ns.topology, cp.profile)
    if ns.cycles < 0:
        raise OptionError(f"--cycles {ns.cycles}: must be 0 or more")
    robot = Robot(cp, topo, seed=ns.seed)
    events = [parse_event(e, topo, cp.vocabulary) for e in ns.event]
    check_events(events, topo, ns.cycles, sensors=cp.sensor_names)
    return cp, robot, events


#: What ``-`` stands for in an output option: standard output.
STDOUT = Path("-")
#: Formats of the output options: a JSON Lines trace; a plot as matplotlib writes it.
TRACE_SUFFIXES = (".jsonl", ".ndjson")
PLOT_SUFFIXES = (".png", ".svg", ".pdf")


def output_path(
    path: Path, option: str, suffixes: tuple[str, ...] = (), *, stdout: bool = False, force: bool = False
) -> Path:
    """Every output file a command writes (``--trace``, ``--record``, ``--plot``, ``--capture``,
    ``-o``) goes by the one rule of :func:`dh2rt.output_paths.check_output`, checked before
    any work starts: ``-`` is standard output where ``stdout`` allows it, the suffix is one of
    ``suffixes`` when given, the file is writable, an existing capture or key is kept unless
    ``force``, and no folder is made outside the current one. Raises OutputError (exit 2)."""
    return check_output(path, option, suffixes, stdout=stdout, force=force)


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


#: The help of ``--vars`` (``dh2rt run`` and the launcher)
VARS_HELP = (
    "after the summary's table, each module's variables (V.*) and sensors (S.*) by name (--json always has them)"
)


def variable_lines(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """Each module's variables and sensors, ``m0: V.waiting=0 V.quiet=3 S.roll=0``, for a text
    summary (``--vars``): as it left them (a robot's stopped module has none; a module process
    that ended, as every one at a run's end, has those of its last status); none when the
    program declares neither."""
    out: list[str] = []
    for r in rows:
        values = [f"V.{k}={v}" for k, v in r.get("variables", {}).items()]
        values += [f"S.{k}={v}" for k, v in r.get("sensors", {}).items()]
        if values:
            out.append(f"  {r['name']}: {' '.join(values)}")
    return (["variables and sensors:", *out]) if out else []


def print_summary(
    robot: Robot, elapsed: float, as_json: bool = False, out: IO[str] | None = None, *, show_vars: bool = False
) -> None:
    out = out or sys.stdout
    rows = robot.summary()
    if as_json:
        faults = [
            {"cycle": f.cycle, "module": robot.topology.names[f.module], "source": f.source, "message": f.message}
            for f in robot.faults
        ]
        json.dump(
            {
                "cycles": robot.cycle,
                "seconds": elapsed,
                "lost_in_flight": robot.lost_in_flight,
                "modules": rows,
                "faults": faults,
            },
            out,
        )
        out.write("\n")
        return
    rate = robot.cycle * robot.size / elapsed if elapsed > 0 else 0.0
    print(
        f"{robot.program.name} on {robot.topology.spec}: {robot.size} modules, {robot.cycle} cycles "
        f"in {elapsed:.3f} s ({rate:,.0f} module-cycles/s), seed {robot.seed}"
        + (f", {robot.lost_in_flight} hormone(s) lost in flight across cut links" if robot.lost_in_flight else ""),
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
    if show_vars:
        for line in variable_lines(rows):
            print(line, file=out)
    faulted = [r for r in rows if r.get("faults")]
    if faulted:
        print(f"receptor faults in {len(faulted)} module(s):", file=out)
        for r in faulted:
            print(f"  {r['name']}: {r['faults']} fault(s), the last at {r['last_fault']}", file=out)
    for line in robot.log[-20:]:
        print(f"  {line}", file=out)
