"""The ``dh2rt`` command's front door: a registered command starts with its own imports only.

``dh2rt module`` is what a module processor runs at power-up, and it pays for every module
imported before it starts cycling (time and resident memory on a small board). The core's
own commands (``check``, ``run``, ``image``, ...) need the compiler, the robot, the trace
writer and the signing code; a registered command (``module``, ``launch``, ``dump``, ...)
needs none of them. So this module looks the command up in the ``dh2rt.commands`` entry
points first and runs it directly; anything else (a core command, ``--help``, an option
first, a command that does not load) goes to :func:`dh2rt.cli.main`, which does the rest and
reports the errors.
"""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Callable, Sequence
from types import FrameType

from dh2rt.plugins import COMMAND_GROUP, CORE_COMMANDS


def registered_command(name: str) -> Callable[[list[str]], int] | None:
    """The ``main(argv)`` registered as ``name``, imported now; None if there is none or it
    does not load (:mod:`dh2rt.cli` then says why)."""
    from importlib.metadata import entry_points

    for ep in entry_points(group=COMMAND_GROUP, name=name):
        try:
            command: Callable[[list[str]], int] = ep.load()
        except ImportError:
            return None
        return command
    return None


def _interrupted_while_starting(_signum: int, _frame: FrameType | None) -> None:
    """Ctrl-C before the command has its own handler (while it imports): exit 130, quietly."""
    raise SystemExit(130)


def main(argv: Sequence[str] | None = None) -> int:
    if argv is None:  # run as the command: no traceback for a Ctrl-C during start-up
        signal.signal(signal.SIGINT, _interrupted_while_starting)
        return _piped(lambda: _main(sys.argv[1:]))
    return _main(argv)


def _piped(run: Callable[[], int]) -> int:
    """Run the command; when its reader went away (``dh2rt image --inspect X | head``), end
    quietly with its exit code (0 if it was cut off mid-output) instead of a traceback, now
    or when the interpreter flushes standard output at exit."""
    code = 0
    try:
        code = run()
        sys.stdout.flush()
    except BrokenPipeError:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # nothing left to flush at exit
    return code


def _main(argv: Sequence[str]) -> int:
    args = list(argv)
    first = args[0] if args else None
    if first is not None and not first.startswith("-") and first not in CORE_COMMANDS:
        command = registered_command(first)
        if command is not None:
            return command(args[1:])
    from dh2rt.cli import main as cli_main

    return cli_main(args)


if __name__ == "__main__":
    sys.exit(main())
