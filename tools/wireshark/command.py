"""``dh2rt wireshark``: write the Wireshark dissector for dh2rt frames.

Frames carry hormone indices; the program gives them names. With ``--capture`` the dissector
knows the programs the capture carries (the images in its section header, each matched to a
link end by the digest its Hellos carry, as ``dh2rt dump`` does); with ``--program`` the ones
named; with neither it is the generic ``tools/wireshark/dh2rt.lua`` (hormones as
``#INDEX``). ``--check`` compares the committed generic file with what this writes.

``-o`` follows the output rule of every command (:func:`dh2rt.output_paths.check_output`):
checked before any work; a capture or a key there is kept unless ``--force``; a folder
outside the current one is not made.

Exit codes: 0 ok, 1 ``--check`` found the committed file out of date, 2 bad input (a program
that does not compile, a capture with no program image, an output that cannot be written),
130 Ctrl-C.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from dh2rt.cmdline import EXIT_FAIL, EXIT_OK, EXIT_USAGE, err
from dh2rt.errors import CaptureError, OutputError, ProgramError
from dh2rt.output_paths import STDOUT, check_output
from dh2rt.program import CompiledProgram
from tools.reading import interruptible, open_capture, program_file
from tools.wireshark.generate import dissector, template


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dh2rt wireshark",
        description="Write the Wireshark Lua dissector for dh2rt frames, knowing a program's hormone names.",
        epilog="Example: dh2rt wireshark --capture robot.pcapng -o ~/.local/lib/wireshark/plugins/dh2rt.lua",
    )
    source = p.add_mutually_exclusive_group()
    source.add_argument("--capture", type=Path, help="name hormones with the program images this pcapng carries")
    source.add_argument(
        "--program", type=Path, action="append", help="name hormones with this .dh2 program (repeatable)"
    )
    p.add_argument("-o", "--output", type=Path, help="write here (default: standard output)")
    p.add_argument("--force", action="store_true", help="write -o over a capture or a key that is there")
    p.add_argument(
        "--check", action="store_true", help="exit 1 unless the committed generic dh2rt.lua is what this writes"
    )
    return p


def programs_for(ns: argparse.Namespace) -> tuple[CompiledProgram, ...]:
    """The programs the options name; raises ProgramError or CaptureError."""
    if ns.capture is not None:
        return open_capture(ns.capture).programs
    return tuple(program_file(path) for path in ns.program or ())


def check_committed() -> int:
    """EXIT_OK when the committed generic dissector is what the generator writes."""
    committed = template()
    if dissector(base=committed) != committed:
        err("tools/wireshark/dh2rt.lua differs from what the codec's layout gives: run dh2rt wireshark -o it")
        return EXIT_FAIL
    return EXIT_OK


@interruptible
def main(argv: Sequence[str] | None = None) -> int:
    try:
        ns = build_parser().parse_args(argv)
    except SystemExit as exc:
        return int(exc.code) if isinstance(exc.code, int) else EXIT_USAGE
    if ns.check:
        return check_committed()
    try:
        output = STDOUT if ns.output is None else check_output(ns.output, "-o", stdout=True, force=ns.force)
        text = dissector(programs_for(ns))
    except ProgramError as exc:
        print(exc.render(), file=sys.stderr)  # noqa: T201 - a command's error output
        return EXIT_USAGE
    except (CaptureError, OutputError) as exc:
        err(str(exc))
        return EXIT_USAGE
    if output == STDOUT:
        sys.stdout.write(text)
        return EXIT_OK
    try:
        output.write_text(text, encoding="utf-8")
    except OSError as exc:  # checked above; a disk full or a folder removed since
        err(f"-o {output}: {exc.strerror or exc}")
        return EXIT_USAGE
    return EXIT_OK
