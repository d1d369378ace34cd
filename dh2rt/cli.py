"""The ``dh2rt`` command: the core's subcommands, and those that upper layers register.

``dh2rt check PROGRAM``          exit 0 if valid, else 2 with FILE:LINE:COL, the line and a caret
``dh2rt run PROGRAM ...``        run a robot headless in one process; per-module summary
``dh2rt image PROGRAM -o FILE``  write the program's image (what is flashed) and print its hash;
                                 ``--sign KEY --version N``: a signed image (dh2rt.signed_image)
``dh2rt image --inspect IMAGE``  an image's fields, signer's key id and (``--trust PUBKEY``)
                                 verification: exit 1 if it does not verify, 2 if no image
``dh2rt keys new -o KEY``        a signing key pair: KEY (private, mode 0600) and KEY.pub
``dh2rt types``                  the topology profile's types and their status tuples
``dh2rt demo``                   the embedded default demo (no hardware, no SocketCAN)
``dh2rt COMMAND ...``            a command registered by an upper layer (``launch``: the
                                 hardware-in-the-loop launcher); ``dh2rt --transport ...``
                                 with no command is ``dh2rt launch --transport ...``

Upper layers register through entry points in ``pyproject.toml``, so the core never imports
them (python-can finds its interfaces the same way): the group ``dh2rt.commands`` maps a
command name to ``module:main`` (``main(argv) -> exit code``), and ``dh2rt.simulators`` maps
a ``run --sim`` name to a :class:`~dh2rt.plugins.Simulator`, which declares its own ``run``
options and runs the robot (:mod:`dh2rt.plugins`).

Exit codes: 0 success, 1 a run failed, 2 bad input (program, topology, event, option),
130 interrupted (Ctrl-C; the summary so far is still printed).
"""

from __future__ import annotations

import argparse
import gc
import importlib
import re
import sys
from collections.abc import Sequence
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import IO, Any

from dh2rt import __version__
from dh2rt.cmdline import (
    EXIT_FAIL,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    STDOUT,
    TRACE_SUFFIXES,
    VARS_HELP,
    Progress,
    StopAtCycleEnd,
    add_run_options,
    err,
    load_program,
    output_path,
    prepare_run,
    print_summary,
    timed_run,
)
from dh2rt.compiler import load_image
from dh2rt.errors import DH2Error, ImageError, KeyFileError, OptionError, OutputError, ProgramError
from dh2rt.lint import lint
from dh2rt.natives import STANDARD_NATIVES
from dh2rt.output_paths import check_output
from dh2rt.plugins import COMMAND_GROUP, CORE_COMMANDS, SIMULATOR_GROUP, Simulator, registered
from dh2rt.profile import CONRO
from dh2rt.signed_image import (
    SignedImage,
    Verdict,
    describe_key_id,
    examine,
    is_image_file,
    key_id,
    pack,
    parse,
    public_key,
    public_key_path,
    read_private_key,
    read_public_key,
    write_key_pair,
)
from dh2rt.trace import TraceWriter

#: What ``dh2rt`` runs when its first argument is an option (``dh2rt --transport vcan0``).
DEFAULT_COMMAND = "launch"


def _summary_line(ep: EntryPoint) -> str:
    """The first line of a registered command's module docstring, for ``--help``."""
    try:
        module = importlib.import_module(ep.module)
    except ImportError as exc:
        return f"(not available: {exc})"
    doc = " ".join((module.__doc__ or "").strip().split("\n\n")[0].split())
    if not doc:
        return ep.value
    # "``dh2rt dump CAPTURE``: a robot's traffic, one line per frame, ..." -> "a robot's traffic"
    doc = re.sub(r"^``[^`]*``:\s*", "", doc)
    first = re.split(r"(?<=[.:;])\s", doc)[0].rstrip(".:;")
    if len(first) > 80:
        first = first[: first.rfind(" ", 0, 77)].rstrip(",") + " ..."
    return first[:1].upper() + first[1:]


def build_parser(commands: dict[str, EntryPoint] | None = None) -> argparse.ArgumentParser:
    commands = registered(COMMAND_GROUP) if commands is None else commands
    listed = "\n".join(f"  {name:<10} {_summary_line(ep)}" for name, ep in sorted(commands.items()))
    parser = argparse.ArgumentParser(
        prog="dh2rt",
        description="Run DH2 hormone programs on modular self-reconfigurable robots.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=(f"registered commands (dh2rt COMMAND --help):\n{listed}\n\n" if listed else "")
        + f"With no command, or an option first, dh2rt runs `dh2rt {DEFAULT_COMMAND}` "
        f"(see `dh2rt {DEFAULT_COMMAND} --help`).",
    )
    parser.add_argument("--version", action="version", version=f"dh2rt {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    check = sub.add_parser("check", help="check a program; exit 2 with FILE:LINE:COL on error")
    check.add_argument("program", type=Path, help="a .dh2 file")

    run = sub.add_parser("run", help="run a robot in one process and print a per-module summary")
    add_run_options(run)
    simulators = registered(SIMULATOR_GROUP)
    run.add_argument("--sim", choices=sorted(simulators), help="run the modules' joints in physics")
    run.add_argument("--json", action="store_true", help="print the summary as JSON")
    run.add_argument("--vars", action="store_true", help=VARS_HELP)
    add_simulator_options(run, simulators)

    image = sub.add_parser(
        "image",
        help="write a program's image (what gets flashed) and print its hash; or --inspect one",
        usage="dh2rt image PROGRAM -o FILE [--sign KEY --version N]\n"
        "       dh2rt image --inspect IMAGE [--trust PUBKEY ...]",
    )
    image.add_argument("program", type=Path, nargs="?", help="a .dh2 file")
    image.add_argument("-o", "--output", type=Path, help="image file to write (- for standard output)")
    image.add_argument("--force", action="store_true", help="write -o over a capture or a key that is there")
    image.add_argument("--sign", type=Path, metavar="KEY", help="sign the image with this private key (dh2rt keys new)")
    image.add_argument(
        "--version",
        dest="program_version",
        type=int,
        metavar="N",
        help="with --sign: the program version, 0..4294967295; a module refuses one lower than it runs",
    )
    image.add_argument("--inspect", type=Path, metavar="IMAGE", help="describe IMAGE: fields, key id, verification")
    image.add_argument(
        "--trust",
        type=Path,
        action="append",
        default=[],
        metavar="PUBKEY",
        help="with --inspect: verify against this public key (repeatable); exit 1 if the image does not verify",
    )

    keys = sub.add_parser("keys", help="signing keys for program images")
    keys_sub = keys.add_subparsers(dest="keys_command", metavar="ACTION", required=True)
    keys_new = keys_sub.add_parser("new", help="make a key pair: KEY (private, mode 0600) and KEY.pub beside it")
    keys_new.add_argument("-o", "--output", type=Path, required=True, metavar="KEY", help="the private key file")

    sub.add_parser("types", help="list the CONRO profile's topological types")

    demo = sub.add_parser("demo", help="run the embedded demo: caterpillar, live surgery, legs to snake")
    demo.add_argument("--cycles", type=int, default=240)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args_list = list(sys.argv[1:] if argv is None else argv)
    commands = registered(COMMAND_GROUP)
    first = args_list[0] if args_list else None
    if first in commands and first not in CORE_COMMANDS:
        return _registered_command(commands, first, args_list[1:])
    if first is None or (first.startswith("-") and first not in ("-h", "--help", "--version")):
        return _registered_command(commands, DEFAULT_COMMAND, args_list)
    parser = build_parser(commands)
    ns = parser.parse_args(args_list)
    try:
        if ns.command == "check":
            return cmd_check(ns.program)
        if ns.command == "run":
            return cmd_run(ns)
        if ns.command == "image":
            return cmd_image(ns)
        if ns.command == "keys":
            return cmd_keys(ns.output)
        if ns.command == "types":
            return cmd_types(sys.stdout)
        if ns.command == "demo":
            return cmd_demo(ns.cycles)
    except KeyboardInterrupt:
        err("interrupted")
        return EXIT_INTERRUPTED
    parser.print_help()
    return EXIT_USAGE


def _load(ep: EntryPoint, what: str) -> Any:
    """The object ``ep`` names, or None (said on stderr) when it does not load."""
    try:
        return ep.load()
    except ImportError as exc:
        err(f"{what} is installed but cannot be loaded ({exc})")
        return None


def add_simulator_options(run: argparse.ArgumentParser, simulators: dict[str, EntryPoint]) -> None:
    """Each installed simulator declares its own ``run`` options, in a group of its own; the
    run parser's default ``simulator_options`` keeps them by simulator, so that
    :func:`options_without_their_simulator` can refuse them without their ``--sim``. A
    simulator that does not load adds nothing (``--sim NAME`` then says why)."""
    declared: dict[str, list[argparse.Action]] = {}
    for name, ep in sorted(simulators.items()):
        try:
            simulator: Simulator = ep.load()
        except ImportError:
            continue
        group = _RecordedGroup(run.add_argument_group(f"with --sim {name}"))
        simulator.add_arguments(group)
        declared[name] = group.actions
    run.set_defaults(simulator_options=declared)


class _RecordedGroup:
    """An argument group that remembers the options added to it."""

    def __init__(self, group: argparse._ArgumentGroup) -> None:
        self.group = group
        self.actions: list[argparse.Action] = []

    def add_argument(self, *args: Any, **kwargs: Any) -> argparse.Action:
        action = self.group.add_argument(*args, **kwargs)
        self.actions.append(action)
        return action


def options_without_their_simulator(ns: argparse.Namespace) -> None:
    """Raise OptionError when a simulator's option is given but that simulator is not chosen."""
    declared: dict[str, list[argparse.Action]] = getattr(ns, "simulator_options", {})
    for name, actions in declared.items():
        if name == ns.sim:
            continue
        given = [max(a.option_strings, key=len) for a in actions if getattr(ns, a.dest) != a.default]
        if given:
            raise OptionError(f"{', '.join(given)}: these options need --sim {name}")


def _registered_command(commands: dict[str, EntryPoint], name: str, argv: list[str]) -> int:
    ep = commands.get(name)
    if ep is None:
        err(f"no command {name!r} is installed (see `dh2rt --help`); try `dh2rt run --help`")
        return EXIT_USAGE
    command = _load(ep, f"the command {name!r}")
    if command is None:
        return EXIT_USAGE
    code: int = command(argv)
    return code


def cmd_check(path: Path) -> int:
    try:
        cp = load_program(path)
    except ProgramError as exc:
        print(exc.render(), file=sys.stderr)
        return EXIT_USAGE
    for warning in lint(cp.ast, cp.profile, STANDARD_NATIVES):
        print(warning, file=sys.stderr)
    print(
        f"{path}: ok: program {cp.name}, {len(cp.receptors)} receptors, {len(cp.vocabulary.by_index)} hormones, "
        f"ClockCycle {cp.clock_cycle}, image {len(cp.image)} bytes, sha256 {cp.hash[:16]}"
    )
    return EXIT_OK


def cmd_image(ns: argparse.Namespace) -> int:
    """``dh2rt image``: write a program's image, signed with ``--sign``, or ``--inspect`` one."""
    if ns.inspect is not None:
        if ns.program or ns.output or ns.sign or ns.program_version is not None:
            err("--inspect IMAGE takes no PROGRAM, -o, --sign or --version")
            return EXIT_USAGE
        return cmd_inspect(ns.inspect, ns.trust)
    if ns.program is None or ns.output is None:
        err("image: give PROGRAM and -o FILE, or --inspect IMAGE")
        return EXIT_USAGE
    if ns.trust:
        err("--trust goes with --inspect IMAGE")
        return EXIT_USAGE
    if (ns.sign is None) != (ns.program_version is None):
        err("--sign KEY and --version N go together: a signed image carries its program version")
        return EXIT_USAGE
    try:
        output = check_output(ns.output, "-o", stdout=True, force=ns.force)
        if is_image_file(ns.program):
            raise OutputError(f"PROGRAM {ns.program}: is a program image already, not a .dh2 source (--inspect it)")
        cp = load_program(ns.program)
    except ProgramError as exc:
        print(exc.render(), file=sys.stderr)
        return EXIT_USAGE
    except OutputError as exc:
        err(str(exc))
        return EXIT_USAGE
    try:
        data, described = _image_bytes(cp.image, ns.sign, ns.program_version)
        if output == STDOUT:
            sys.stdout.buffer.write(data)
            sys.stdout.flush()
        else:
            output.write_bytes(data)
    except (ImageError, OutputError) as exc:
        err(str(exc))
        return EXIT_USAGE
    except OSError as exc:
        err(f"{exc.filename or ns.output}: {exc.strerror or exc}")
        return EXIT_USAGE
    # with the image on standard output, its description goes to standard error
    print(
        f"{output}: {len(data)} bytes, sha256 {cp.hash}{described}", file=sys.stderr if output == STDOUT else sys.stdout
    )
    return EXIT_OK


def _image_bytes(image: bytes, key: Path | None, version: int | None) -> tuple[bytes, str]:
    """The program image, or (with ``key``) the signed image; and what to add to its line."""
    if key is None or version is None:
        return image, ""
    private = read_private_key(key)
    data = pack(image, version, private)
    kid = key_id(public_key(private)).hex()
    return data, f" (program image {len(image)} bytes), signed: version {version}, key id {kid}"


def cmd_inspect(path: Path, trust_files: Sequence[Path]) -> int:
    """``dh2rt image --inspect``: exit 0 if the image verifies against ``trust_files`` (or
    is intact, with none given), 1 if it does not, 2 if it is no image or a key is unreadable."""
    try:
        trust = [read_public_key(p) for p in trust_files]
        data = path.read_bytes()
    except KeyFileError as exc:  # names its file
        err(str(exc))
        return EXIT_USAGE
    except OSError as exc:
        err(f"{exc.filename or path}: {exc.strerror or exc}")
        return EXIT_USAGE
    try:
        signed = parse(data)
    except ImageError as exc:
        err(f"{path}: {exc}")
        return EXIT_USAGE
    for line in _describe_image(path, signed):
        print(line)
    if not trust:
        body_ok = _print_program(signed)
        print("  verification     not checked: give --trust PUBKEY")
        return EXIT_OK if body_ok else EXIT_FAIL
    exam = examine(data, trust)
    if exam.program is not None:
        _print_program(signed)
    print(f"  verification     {exam.verdict}: {exam.reason}")
    return EXIT_OK if exam.verdict is Verdict.OK else EXIT_FAIL


def _describe_image(path: Path, signed: SignedImage) -> list[str]:
    if not signed.signed:
        return [
            f"{path}: unsigned program image (format {signed.format_version}), {signed.size} bytes",
            f"  program digest   {signed.digest.hex()} (as Hello frames carry it)",
            "  program version  0 (unsigned)",
            "  key id           (none)",
        ]
    return [
        f"{path}: signed image, format {signed.format_version}, {signed.size} bytes",
        f"  program version  {signed.version}",
        f"  program digest   {signed.digest.hex()} (as Hello frames carry it)",
        f"  program length   {signed.program_length} bytes (body {len(signed.body)} bytes, compressed)",
        f"  key id           {describe_key_id(signed.key_id)}",
    ]


def _print_program(signed: SignedImage) -> bool:
    """Print the program the image holds; False if its body does not decode to one."""
    try:
        cp = load_image(signed.program())
    except ProgramError as exc:
        print(f"  program          does not compile: {exc.render()}")
        return False
    except ImageError as exc:
        print(f"  program          corrupt: {exc}")
        return False
    print(f"  program          {cp.name}, {len(cp.receptors)} receptors, sha256 {cp.hash[:16]}")
    return True


def cmd_keys(output: Path) -> int:
    """``dh2rt keys new -o KEY``: a new key pair, never over an existing file."""
    taken = [p for p in (output, output.with_name(output.name + ".pub")) if p.exists()]
    if taken:  # a key is never overwritten: there is no --force for it
        err(f"-o {output}: {taken[0]} exists; a key is never overwritten (remove it first)")
        return EXIT_USAGE
    try:
        output = output_path(output, "-o")
        kid = write_key_pair(output)
    except OutputError as exc:
        err(str(exc))
        return EXIT_USAGE
    except FileExistsError as exc:
        err(f"-o {output}: {exc.filename} exists; a key is never overwritten (remove it first)")
        return EXIT_USAGE
    except OSError as exc:
        err(f"-o {output}: {exc.strerror or exc}")
        return EXIT_USAGE
    print(f"{output}: private key (mode 0600); {public_key_path(output)}: public key; key id {kid.hex()}")
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


def cmd_run(ns: argparse.Namespace) -> int:
    simulator: Simulator | None = None
    if ns.sim:
        simulator = _load(registered(SIMULATOR_GROUP)[ns.sim], f"the simulator {ns.sim!r}")
        if simulator is None:
            return EXIT_USAGE
    try:
        if ns.trace is not None:
            ns.trace = output_path(ns.trace, "--trace", TRACE_SUFFIXES, stdout=True)
        options_without_their_simulator(ns)
        if simulator is not None:
            simulator.check(ns)
        _cp, robot, events = prepare_run(ns)
    except ProgramError as exc:
        print(exc.render(), file=sys.stderr)
        return EXIT_USAGE
    except (DH2Error, OSError) as exc:
        err(str(exc))
        return EXIT_USAGE
    if simulator is not None:
        return simulator.run(robot, ns, events)
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
            for cycle in robot.iter_cycles(ns.cycles, events, every_cycle=trace is not None):
                if trace is not None:
                    trace.write_cycle()
                progress.update(cycle + 1)
                stop.check()
        progress.done()

    try:
        elapsed, interrupted = timed_run(body, trace)
    except DH2Error as exc:  # an event that native actions made impossible (EventError)
        err(str(exc))
        return EXIT_USAGE
    # a trace on standard output keeps it to itself: the summary goes to standard error
    print_summary(robot, elapsed, as_json=ns.json, out=sys.stderr if ns.trace == STDOUT else None, show_vars=ns.vars)
    if interrupted:
        if stop.forced:
            err(f"interrupted during cycle {robot.cycle}: modules may be at different cycles")
        else:
            err(f"interrupted at cycle {robot.cycle}")
        return EXIT_INTERRUPTED
    return EXIT_OK


def cmd_demo(cycles: int) -> int:
    from dh2rt.demo import run_demo

    try:
        return run_demo(cycles, sys.stdout)
    except ProgramError as exc:  # a damaged installation: its shipped programs do not compile
        print(exc.render(), file=sys.stderr)
        return EXIT_FAIL


if __name__ == "__main__":
    sys.exit(main())
