"""Loop runs judged against this machine's own timer: for tests and benchmarks that launch the
robot in the loop to check what it does, not how fast the machine is.

A loop run whose modules start more than a tenth of their cycles late fails, and the launcher
says so with its own exit code, :data:`hil.launcher.EXIT_TOO_SLOW` (a typed verdict, not a
line of text): late modules hear their neighbours a cycle later than the robot would, and a
module stalled for longer than its silence bound loses its links. Whose fault is it, dh2rt's
or the machine's? :class:`LoopPace` asks the machine: it runs a bare sleep loop at the same
period (:func:`measure`), scheduled as a module's loop is (a cycle that starts more than
``LATE_TOLERANCE`` periods after its deadline is late, and the schedule restarts from now), in
this process, right then.

* The bare loop kept the period (at most ``LATE_SHARE`` of its cycles late): the machine could
  and dh2rt could not. The run is returned as it is, with a line saying what the bare loop
  measured added to its stderr, and the test fails: a slowdown in dh2rt fails.
* The bare loop could not keep it either: the period is stretched by the factor the bare loop
  needs (:meth:`Baseline.stretch`) and the run is made again; the run that counts is judged
  like any other. The stretch holds for every later run of the session. If the bare loop
  needs more than :data:`MAX_FACTOR`, :class:`~dh2rt.errors.MachineTooSlow` is raised, and
  that is a failure too (tests/conftest.py): no test is skipped because the machine is slow.

On a machine that keeps the periods the tests ask for, nothing changes and no run is repeated.

A run is only as steady as the machine was while it ran, and a bare loop measured after it
cannot see a stall that came and went during it (another test's processes booting on the same
cores). So a :class:`Witness`, a bare loop in a process of its own, runs beside every loop
run. When the launcher calls a run too slow while the bare loop measured after it kept the
period, the witness says whether the machine stalled a bare loop during the run: if it did
(at least one of its cycles late), the run is made again once at the same period
(``WITNESS_RETRIES``); if it did not, or the run made again is too slow as well, the run
counts and fails.

A test that judges timing itself (how late a cycle may start, the order of two processes'
clock reads) allows dh2rt no more than the bare loop's own lateness: :func:`baseline` (measured
once a session, at the default period) and :meth:`Baseline.allowance_s`.
"""

from __future__ import annotations

import contextlib
import functools
import io
import itertools
import math
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dh2rt.errors import MachineTooSlow
from dh2rt.runtime import CYCLE_PERIOD_S, LATE_TOLERANCE, s_to_ms
from hil.bare_loop import lateness
from hil.launcher import EXIT_TOO_SLOW, LATE_SHARE

#: How long the bare loop runs to judge one period (s): long enough for a tenth of its cycles to mean something.
MEASURE_S = 3.0
#: At least this many cycles, however long the period.
MEASURE_MIN_CYCLES = 60
#: The pace never stretches periods more than this.
MAX_FACTOR = 8
#: A timing allowance is this many times the bare loop's p99 lateness, plus ALLOWANCE_FLOOR_S.
ALLOWANCE_FACTOR = 3.0
ALLOWANCE_FLOOR_S = 0.001
_OPTION = "--cycle-ms"
#: The checkout hil/ is in (the witness imports hil.bare_loop from it with no site).
ROOT = Path(__file__).resolve().parents[1]
#: Runs made again at the same period because the witness saw the machine stall during them.
WITNESS_RETRIES = 1


@dataclass(frozen=True)
class Baseline:
    """What a bare sleep loop at one period did on this machine: how late each cycle started."""

    period_s: float
    #: each cycle's lateness (s), sorted
    late_s: tuple[float, ...]

    def share_late(self, factor: float = 1.0) -> float:
        """Share of cycles a loop at ``factor`` times this period would have started late."""
        bound = LATE_TOLERANCE * self.period_s * factor
        return sum(1 for x in self.late_s if x > bound) / max(1, len(self.late_s))

    def kept(self) -> bool:
        """The bare loop kept its period as the launcher asks modules to."""
        return self.share_late() <= LATE_SHARE

    def stretch(self) -> int:
        """The smallest whole factor whose longer period the bare loop would have kept with
        half the launcher's share to spare (1: it kept this one)."""
        if self.kept():
            return 1
        worst = self.late_s[-1] if self.late_s else 0.0
        for factor in range(2, MAX_FACTOR + 1):
            if self.share_late(factor) <= LATE_SHARE / 2:
                return factor
        return max(MAX_FACTOR + 1, math.ceil(worst / (LATE_TOLERANCE * self.period_s)))

    def quantile_s(self, q: float) -> float:
        if not self.late_s:
            return 0.0
        return self.late_s[min(len(self.late_s) - 1, int(q * len(self.late_s)))]

    def allowance_s(self) -> float:
        """How late (s) a test lets a dh2rt cycle or clock read be beyond what it expects:
        ALLOWANCE_FACTOR times the bare loop's p99 lateness, plus ALLOWANCE_FLOOR_S."""
        return ALLOWANCE_FACTOR * self.quantile_s(0.99) + ALLOWANCE_FLOOR_S

    def describe(self) -> str:
        ms = [self.quantile_s(q) * 1000 for q in (0.5, 0.9, 0.99, 1.0)]
        return (
            f"a bare loop at {self.period_s * 1000:g} ms started {self.share_late():.0%} of {len(self.late_s)} "
            f"cycles late; lateness {ms[0]:.1f} ms (median), {ms[1]:.1f} ms (p90), {ms[2]:.1f} ms (p99), "
            f"{ms[3]:.1f} ms (worst)"
        )


def measure(period_s: float = CYCLE_PERIOD_S, seconds: float = MEASURE_S) -> Baseline:
    """Run a bare sleep loop at ``period_s`` for about ``seconds`` and record its lateness,
    scheduled as dh2rt.runtime.ModuleRuntime.run schedules a module's cycles."""
    cycles = max(MEASURE_MIN_CYCLES, round(seconds / period_s))
    late = list(itertools.islice(lateness(period_s, LATE_TOLERANCE), cycles))
    return Baseline(period_s, tuple(sorted(late)))


class Witness:
    """A bare loop at ``period_s`` in a process of its own, beside a loop run: how late the
    machine let a loop that does nothing start its cycles while the run ran."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        # no site, no dh2rt imported (hil.bare_loop): it starts in tens of ms and sleeps through the run
        env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
        self.proc = subprocess.Popen(
            [sys.executable, "-S", "-m", "hil.bare_loop", repr(period_s), repr(LATE_TOLERANCE)],
            stdout=subprocess.PIPE,
            text=True,
            env=env,
        )
        assert self.proc.stdout is not None
        self.proc.stdout.readline()  # "ready": its loop runs from here

    def stop(self) -> Baseline:
        """End the witness (by its pid) and return what its loop measured."""
        try:
            self.proc.send_signal(signal.SIGTERM)
            out, _ = self.proc.communicate(timeout=10)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()
        late = [int(x) / 1e6 for x in out.split()]
        return Baseline(self.period_s, tuple(sorted(late)))


@functools.cache
def baseline() -> Baseline:
    """The bare loop at the default cycle period, measured once per process (a session)."""
    return measure()


def realtime_problem() -> str | None:
    """Why this machine keeps no real time at the default period (the bare loop did not keep
    it), or None. Measured once per process."""
    b = baseline()
    return None if b.kept() else b.describe()


class LoopPace:
    """How much longer than asked every loop run's period is, learned from the bare loop."""

    def __init__(self) -> None:
        self.factor = 1
        #: the bare loop measured at the last run the launcher called too slow (None: none was)
        self.last: Baseline | None = None

    def ms(self, asked: float = s_to_ms(CYCLE_PERIOD_S)) -> float:
        """The period in ms a run asking for ``asked`` ms runs at now."""
        return asked * self.factor

    def argv(self, argv: Sequence[str], *, again: bool = False) -> list[str]:
        """The launcher's arguments with their period stretched by the factor; a run made
        ``again`` writes over the outputs the first one left (``--force``)."""
        out = list(argv)
        if again and "--force" not in out:
            out.append("--force")
        if _OPTION in out:
            at = out.index(_OPTION) + 1
            out[at] = f"{self.ms(float(out[at])):g}"
        elif self.factor != 1:
            out += [_OPTION, f"{self.ms():g}"]
        return out

    def run(self, cmd: Sequence[str], *, timeout: float, **kwargs: Any) -> subprocess.CompletedProcess[Any]:
        """``subprocess.run`` of a launcher command line, with its output captured; made again
        at a longer period while the launcher says the modules could not keep it and a bare
        loop could not either, or once at the same period when the witness saw the machine
        stall during the run. The time limit stretches with the period."""
        runs: list[subprocess.CompletedProcess[Any]] = []

        def attempt(argv: list[str]) -> int:
            runs.append(subprocess.run(argv, capture_output=True, timeout=timeout * self.factor, **kwargs))
            return runs[-1].returncode

        said = self._paced(cmd, attempt)
        proc = runs[-1]
        if said:
            proc.stderr += said if isinstance(proc.stderr, str) else said.encode()
        return proc

    def call(self, main: Callable[[list[str]], int], argv: Sequence[str]) -> int:
        """``main(argv)`` of the launcher in this process, made again as :meth:`run` does;
        what the run that counts wrote to stdout and stderr is passed on."""
        runs: list[tuple[int, io.StringIO, io.StringIO]] = []

        def attempt(stretched: list[str]) -> int:
            out, err = io.StringIO(), io.StringIO()
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                runs.append((main(stretched), out, err))
            return runs[-1][0]

        said = self._paced(argv, attempt)
        code, out, err = runs[-1]
        sys.stdout.write(out.getvalue())
        sys.stderr.write(err.getvalue() + said)
        return code

    def _paced(self, argv: Sequence[str], attempt: Callable[[list[str]], int]) -> str:
        """``attempt`` the launcher's ``argv`` (stretched, and with ``--force`` when made
        again) with a witness beside each run, until a run counts: what the pace says of it
        ("" for a run the launcher did not call too slow)."""
        retries = WITNESS_RETRIES
        again = False
        while True:
            stretched = self.argv(argv, again=again)
            again = True
            witness = Witness(_period_s(stretched))
            try:
                code = attempt(stretched)
            finally:
                beside = witness.stop()
            if code != EXIT_TOO_SLOW:
                return ""
            factor = self.factor
            said = self._judge(stretched, beside, retries)
            if said is not None:
                return said
            retries -= self.factor == factor  # made again at the same period: the witness's retry

    def _judge(self, argv: Sequence[str], beside: Baseline, retries: int) -> str | None:
        """After a run the launcher called too slow: measure a bare loop at its period. If the
        bare loop kept it and so did the witness ``beside`` the run (no cycle of its late), or
        no retry is left, what they measured (the run counts, and failed). If the witness was
        late, None at the same factor (make the run again). Otherwise stretch the factor and
        return None (make the run again).

        Raises MachineTooSlow when the bare loop needs more than MAX_FACTOR."""
        period_ms = s_to_ms(_period_s(argv))
        self.last = b = measure(period_ms / 1000)
        if b.kept():
            stalled = beside.share_late() > 0
            during = f"a bare loop beside the run {beside.describe().removeprefix('a bare loop ')}"
            if stalled and retries > 0:
                sys.stderr.write(
                    f"pace: the modules could not keep {period_ms:g} ms cycles while {during}: the machine "
                    "stalled during the run; it is made again at the same period\n"
                )
                return None
            return (
                f"pace: the modules could not keep {period_ms:g} ms cycles, yet {b.describe()}, and {during}: "
                "dh2rt is too slow\n"
            )
        factor = self.factor * b.stretch()
        if factor > MAX_FACTOR:
            raise MachineTooSlow(
                f"{b.describe()}: it would need periods {factor}x those asked for, more than {MAX_FACTOR}x"
            )
        self.factor = factor
        sys.stderr.write(
            f"pace: {b.describe()}; loop runs now take {self.factor}x the period asked for "
            f"({self.ms():g} ms for the default)\n"
        )
        return None


def _period_s(argv: Sequence[str]) -> float:
    """The cycle period (s) a launcher command line asks for."""
    return float(argv[argv.index(_OPTION) + 1]) / 1000 if _OPTION in argv else CYCLE_PERIOD_S


#: The one pace every loop run of a test session shares.
PACE = LoopPace()
