"""Loop runs at a period this machine can keep: for tests and benchmarks that launch the
robot in the loop to check what it does, not how fast the machine is.

A loop run whose modules start more than a tenth of their cycles late fails and says so
("this machine cannot keep 20 ms cycles with 8 modules"): late modules hear their neighbours
a cycle later than the robot would, and a module the machine stalls for longer than its
silence bound loses its links, so what such a run shows is the machine, not dh2rt. A test
that checks behaviour runs through one shared :class:`LoopPace`: when the launcher says the
machine could not keep the period, the pace doubles every period asked for from then on
(up to :data:`MAX_FACTOR`) and the run is made again; the run that counts is the one at a
period the machine kept. Every other failure is the test's to judge. When even the longest
period is not kept, :class:`MachineTooSlow` is raised: the test's premise, a machine that
keeps time, does not hold (tests/conftest.py turns it into a skip that says so). On a
machine that keeps the periods the tests ask for, nothing changes and no run is repeated.

A test that is about timing itself (lateness, the first cycle after a restart) does not
use this: it sets its own period and judges it.
"""

from __future__ import annotations

import contextlib
import io
import subprocess
import sys
from collections.abc import Callable, Sequence
from typing import Any

from hil.config import CYCLE_PERIOD_S

#: What the launcher says (hil.launcher.problems) when modules could not keep the period.
TOO_SLOW = "this machine cannot keep"
#: The pace never stretches periods more than this: a machine that cannot keep 8x the
#: period a test asks for fails that test.
MAX_FACTOR = 8
_OPTION = "--cycle-ms"


class MachineTooSlow(RuntimeError):
    """The machine kept no period up to MAX_FACTOR times the one asked for."""


class LoopPace:
    """How much longer than asked every loop run's period is, learned from the runs."""

    def __init__(self) -> None:
        self.factor = 1

    def ms(self, asked: float = CYCLE_PERIOD_S * 1000) -> float:
        """The period in ms a run asking for ``asked`` ms runs at now."""
        return asked * self.factor

    def argv(self, argv: Sequence[str]) -> list[str]:
        """The launcher's arguments with their period stretched by the factor."""
        out = list(argv)
        if _OPTION in out:
            at = out.index(_OPTION) + 1
            out[at] = f"{self.ms(float(out[at])):g}"
        elif self.factor != 1:
            out += [_OPTION, f"{self.ms():g}"]
        return out

    def run(self, cmd: Sequence[str], *, timeout: float, **kwargs: Any) -> subprocess.CompletedProcess[Any]:
        """``subprocess.run`` of a launcher command line, with its output captured; made again
        at a longer period while the launcher says the machine could not keep it. The time
        limit stretches with the period."""
        while True:
            proc = subprocess.run(self.argv(cmd), capture_output=True, timeout=timeout * self.factor, **kwargs)
            err = proc.stderr.decode(errors="replace") if isinstance(proc.stderr, bytes) else proc.stderr
            if proc.returncode == 0 or not self._slower(err):
                return proc

    def call(self, main: Callable[[list[str]], int], argv: Sequence[str]) -> int:
        """``main(argv)`` of the launcher in this process, made again as :meth:`run` does;
        what it wrote to stderr is passed on."""
        while True:
            err = io.StringIO()
            with contextlib.redirect_stderr(err):
                code = main(self.argv(argv))
            sys.stderr.write(err.getvalue())
            if code == 0 or not self._slower(err.getvalue()):
                return code

    def _slower(self, stderr: str) -> bool:
        """Double the factor if ``stderr`` says the machine could not keep the period; True
        when the run is to be made again, False when it did not say so.

        Raises MachineTooSlow when the factor is already MAX_FACTOR."""
        said = [line for line in stderr.splitlines() if TOO_SLOW in line]
        if not said:
            return False
        if self.factor * 2 > MAX_FACTOR:
            raise MachineTooSlow(
                f"the machine kept no period up to {MAX_FACTOR}x the one asked for; the launcher said: "
                f"{said[0].removeprefix('dh2rt: ')} ({len(said)} such line(s))"
            )
        self.factor *= 2
        sys.stderr.write(
            f"pace: this machine could not keep the period; loop runs now take {self.factor}x the period "
            f"asked for ({self.ms():g} ms for the default)\n"
        )
        return True


#: The one pace every loop run of a test session shares.
PACE = LoopPace()
