"""What every command that reads a capture does first: parse its options (argparse's exit
turned into the command's exit code), and find the program(s) that name the hormones: the
``--program`` given, or else the images the capture carries (:func:`open_capture`)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from dh2rt.cmdline import EXIT_USAGE, err, load_program
from dh2rt.compiler import load_image
from dh2rt.errors import CaptureError, DH2Error, ProgramError
from dh2rt.program import CompiledProgram
from tools.capture_reader import capture_programs, read_records
from tools.decode import Hop, decode

PROGRAM_HELP = "the .dh2 program the robot ran (default: the program images the capture carries)"


@dataclass(frozen=True)
class Capture:
    """A capture file and the programs that name its hormones (the first is the default)."""

    path: Path
    programs: tuple[CompiledProgram, ...]

    @property
    def program(self) -> CompiledProgram:
        return self.programs[0]

    def hops(self) -> Iterator[Hop]:
        """The capture's frames as :class:`~tools.decode.Hop` s, streaming."""
        return decode(read_records(self.path), self.programs)


def open_capture(path: Path, program: Path | None = None) -> Capture:
    """``path`` with ``program`` compiled, or with the images it carries; raises CaptureError
    (no program anywhere, or an image that does not load) or ProgramError (``program``)."""
    if program is not None:
        return Capture(path, (load_program(program),))
    images = capture_programs(path)
    if not images:
        raise CaptureError(
            f"{path}: carries no program image (captures by `dh2rt --capture` and `dh2rt capture --program` do); "
            "name the program the robot ran with --program"
        )
    loaded = []
    for i, image in enumerate(images):
        try:
            loaded.append(load_image(image))
        except DH2Error as exc:
            raise CaptureError(f"{path}: program image {i + 1} does not load: {exc}") from None
    return Capture(path, tuple(loaded))


def options_and_capture(
    parser: argparse.ArgumentParser, argv: Sequence[str] | None
) -> tuple[argparse.Namespace, Capture] | int:
    """The parsed options and the opened ``capture`` (with ``--program`` if given), or the exit
    code to return (0 after ``--help``; 2 for a bad option, a program that does not compile,
    with FILE:LINE:COL, or a capture with no program)."""
    try:
        ns = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code) if isinstance(exc.code, int) else EXIT_USAGE
    try:
        return ns, open_capture(ns.capture, ns.program)
    except ProgramError as exc:
        print(exc.render(), file=sys.stderr)  # noqa: T201 - a command's error output
        return EXIT_USAGE
    except CaptureError as exc:
        err(str(exc))
        return EXIT_USAGE
