"""What every command that reads a capture does first: parse its options (argparse's exit
turned into the command's exit code), and find the program(s) that name the hormones: the
``--program`` given (a ``.dh2`` source, or an image as ``dh2rt image`` writes it), or else the
images the capture carries (:func:`open_capture`). And what every tools command does last:
Ctrl-C ends it with exit 130 (:func:`interruptible`)."""

from __future__ import annotations

import argparse
import functools
import re
import sys
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ParamSpec

from dh2rt.cmdline import EXIT_INTERRUPTED, EXIT_USAGE, err, load_program
from dh2rt.compiler import load_image
from dh2rt.errors import CaptureError, DH2Error, ImageError, OptionError, ProgramError
from dh2rt.events import parse_hormone
from dh2rt.program import CompiledProgram
from tools.capture_reader import capture_programs, read_records
from tools.decode import Hop, decode

#: The arguments of a command's ``main`` (whatever they are: the decorator passes them on).
P = ParamSpec("P")
PROGRAM_HELP = "the .dh2 program the robot ran, or its image (default: the program images the capture carries)"
#: A hormone as a command's option names it: NAME, or NAME(...) (checked by the program's parser).
_HORMONE_TEXT = re.compile(r"\s*([A-Za-z_][A-Za-z0-9_]*)\s*(\(.*\))?\s*", re.DOTALL)


def interruptible(main: Callable[P, int]) -> Callable[P, int]:
    """A command's ``main`` that Ctrl-C ends with exit 130 and one line, wherever it was."""

    @functools.wraps(main)
    def run(*args: P.args, **kwargs: P.kwargs) -> int:
        try:
            return main(*args, **kwargs)
        except KeyboardInterrupt:
            err("interrupted")
            return EXIT_INTERRUPTED

    return run


def program_file(path: Path) -> CompiledProgram:
    """The program ``--program`` names: a ``.dh2`` source, or an image (signed or not, as
    ``dh2rt image`` writes it), told apart by its first bytes. Raises ProgramError (a source
    that does not compile) or CaptureError (an image that does not load, or no file)."""
    from dh2rt.signed_image import is_image_file, parse

    if not is_image_file(path):
        return load_program(path)

    try:
        return load_image(parse(path.read_bytes()).program())
    except (DH2Error, OSError) as exc:
        raise CaptureError(f"--program {path}: a program image that does not load ({exc})") from None


@dataclass(frozen=True)
class Capture:
    """A capture file and the programs that name its hormones (the first is the default)."""

    path: Path
    programs: tuple[CompiledProgram, ...]

    @property
    def program(self) -> CompiledProgram:
        return self.programs[0]

    def hormone_names(self) -> list[str]:
        """Every hormone the programs declare, sorted."""
        return sorted({name for p in self.programs for name in p.vocabulary.by_name})

    def hormone(self, text: str, option: str) -> str:
        """``text`` as a hormone of the programs: a ``NAME``, or a content ``NAME(args)``
        written as the frames' text has it (``X(A)``). Raises OptionError naming ``option``,
        the text and why: malformed, or no hormone of the program."""
        match = _HORMONE_TEXT.fullmatch(text)
        if match is None:
            raise OptionError(f"{option} {text!r}: malformed; a hormone is NAME or NAME(arg, ...), e.g. X or X(A)")
        name = match.group(1)
        if name not in self.hormone_names():
            raise OptionError(
                f"{option} {text!r}: no hormone {name} in the program (it has {', '.join(self.hormone_names())})"
            )
        if match.group(2) is None:
            return name
        vocabulary = next(p.vocabulary for p in self.programs if name in p.vocabulary.by_name)
        try:
            return parse_hormone(text, vocabulary, f"{option} {text!r}").content()
        except DH2Error as exc:
            raise OptionError(str(exc)) from None

    def hops(self) -> Iterator[Hop]:
        """The capture's frames as :class:`~tools.decode.Hop` s, streaming."""
        return decode(read_records(self.path), self.programs)


def open_capture(path: Path, program: Path | None = None) -> Capture:
    """``path`` with ``program`` compiled, or with the images it carries; raises CaptureError
    (no program anywhere, or an image that does not load) or ProgramError (``program``)."""
    if program is not None:
        return Capture(path, (program_file(program),))
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
        except (DH2Error, LookupError, TypeError, ValueError, AttributeError, RecursionError) as exc:
            # an image is checked by its magic only: damaged JSON inside can fail anywhere in the compiler
            why = str(exc) if isinstance(exc, ImageError) else f"{type(exc).__name__}: {exc}"
            raise CaptureError(
                f"{path}: a damaged capture: program image {i + 1} of {len(images)} does not load ({why}); "
                "name the program the robot ran with --program"
            ) from None
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
