"""What every command that reads a capture does first: parse its options (argparse's exit
turned into the command's exit code), and compile the program that names the hormones."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from dh2rt.cmdline import EXIT_USAGE, load_program
from dh2rt.errors import ProgramError
from dh2rt.program import CompiledProgram


def options_and_program(
    parser: argparse.ArgumentParser, argv: Sequence[str] | None
) -> tuple[argparse.Namespace, CompiledProgram] | int:
    """The parsed options and the compiled ``--program``, or the exit code to return (0 after
    ``--help``; 2 for a bad option or a program that does not compile, with FILE:LINE:COL)."""
    try:
        ns = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code) if isinstance(exc.code, int) else EXIT_USAGE
    try:
        return ns, load_program(ns.program)
    except ProgramError as exc:
        print(exc.render(), file=sys.stderr)  # noqa: T201 - a command's error output
        return EXIT_USAGE
