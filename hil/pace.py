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
keeps time, does not hold (tests/conftest.py turns it into a skip that says so), and every
later run of the session raises it at once without running: a machine that stalls for
hundreds of milliseconds at a time keeps no period, and running every loop test at many
times its length to find that out again would take hours. On a machine that keeps the
periods the tests ask for, nothing changes and no run is repeated.

Before all that, :func:`realtime_problem` measures once whether this machine keeps time at
all: a virtual machine whose processors are taken away for hundreds of milliseconds at a time
(seen here: a 5 ms sleep 80 ms late one time in ten and 480 ms late one time in a hundred,
with nothing else running) keeps no period of tens of milliseconds, however long. There every
loop run raises :class:`MachineTooSlow` at once, with the measured figures.

A test that is about timing itself (lateness, the first cycle after a restart) does not
use this: it sets its own period and judges it.
"""

from __future__ import annotations

import contextlib
import functools
import io
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

from dh2rt.errors import MachineTooSlow
from firmware.config import CYCLE_PERIOD_S
from hil.launcher import TOO_SLOW

#: Sleeps the real-time probe makes, and how long each asks for (s).
PROBE_SLEEPS = 200
PROBE_SLEEP_S = 0.005
#: A machine whose 99th-percentile sleep ends later than this (ms) keeps no real time.
REALTIME_P99_MS = 20.0
#: The pace never stretches periods more than this.
MAX_FACTOR = 4
_OPTION = "--cycle-ms"


@functools.cache
def realtime_problem() -> str | None:
    """Why this machine keeps no real time (its sleeps end far later than asked), or None.
    Measured once per process, in about a second."""
    late = []
    for _ in range(PROBE_SLEEPS):
        start = time.monotonic()
        time.sleep(PROBE_SLEEP_S)
        late.append((time.monotonic() - start - PROBE_SLEEP_S) * 1000.0)
    ordered = sorted(late)
    p50, p90, p99 = (ordered[min(len(ordered) - 1, len(ordered) * q // 100)] for q in (50, 90, 99))
    if p99 <= REALTIME_P99_MS:
        return None
    return (
        f"this machine's {PROBE_SLEEP_S * 1000:g} ms sleeps ended late by {p50:.1f} ms (median), {p90:.0f} ms "
        f"(p90), {p99:.0f} ms (p99), {ordered[-1]:.0f} ms (worst) in {PROBE_SLEEPS} tries; real-time loop runs "
        f"need p99 within {REALTIME_P99_MS:g} ms (its processors are taken away for long stretches)"
    )


class LoopPace:
    """How much longer than asked every loop run's period is, learned from the runs."""

    def __init__(self) -> None:
        self.factor = 1
        #: why the session gave up on loop runs (None: it has not)
        self.given_up: str | None = None

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
            self._check_given_up()
            proc = subprocess.run(self.argv(cmd), capture_output=True, timeout=timeout * self.factor, **kwargs)
            err = proc.stderr.decode(errors="replace") if isinstance(proc.stderr, bytes) else proc.stderr
            if proc.returncode == 0 or not self._slower(err):
                return proc

    def call(self, main: Callable[[list[str]], int], argv: Sequence[str]) -> int:
        """``main(argv)`` of the launcher in this process, made again as :meth:`run` does;
        what the run that counts wrote to stdout and stderr is passed on (each run made
        again says so on stderr)."""
        while True:
            self._check_given_up()
            out, err = io.StringIO(), io.StringIO()
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                code = main(self.argv(argv))
            if code == 0 or not self._slower(err.getvalue()):
                sys.stdout.write(out.getvalue())
                sys.stderr.write(err.getvalue())
                return code

    def _slower(self, stderr: str) -> bool:
        """Double the factor if ``stderr`` says the machine could not keep the period; True
        when the run is to be made again, False when it did not say so.

        Raises MachineTooSlow when the factor is already MAX_FACTOR."""
        said = [line for line in stderr.splitlines() if TOO_SLOW in line]
        if not said:
            return False
        if self.factor * 2 > MAX_FACTOR:
            self.given_up = (
                f"a loop run kept no period up to {MAX_FACTOR}x the one asked for; the launcher said: "
                f"{said[0].removeprefix('dh2rt: ')} ({len(said)} such line(s))"
            )
            self._check_given_up()
        self.factor *= 2
        sys.stderr.write(
            f"pace: this machine could not keep the period; loop runs now take {self.factor}x the period "
            f"asked for ({self.ms():g} ms for the default)\n"
        )
        return True

    def _check_given_up(self) -> None:
        if self.given_up is None:
            self.given_up = realtime_problem()
        if self.given_up is not None:
            raise MachineTooSlow(self.given_up)


#: The one pace every loop run of a test session shares.
PACE = LoopPace()
