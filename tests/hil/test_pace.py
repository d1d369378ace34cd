"""hil.pace: a loop run the machine could not keep is made again at twice the period, and the
longer period holds for every later run; any other failure is returned as it is."""

from __future__ import annotations

import sys
import time

import pytest

from dh2rt.errors import MachineTooSlow
from hil import launcher
from hil import pace as pace_module
from hil.launcher import TOO_SLOW
from hil.pace import MAX_FACTOR, LoopPace

#: A launcher stand-in that keeps any period of at least 50 ms and says, as the launcher
#: does, that it cannot keep a shorter one; it prints the period it was given.
KEEPS_50_MS = (
    "import sys\n"
    "ms = float(sys.argv[sys.argv.index('--cycle-ms') + 1]) if '--cycle-ms' in sys.argv else 20.0\n"
    "print(ms)\n"
    "if ms < 50:\n"
    f"    print('dh2rt: module m0 started 40% of its cycles late: {TOO_SLOW} ' + str(ms), file=sys.stderr)\n"
    "    sys.exit(1)\n"
)


def stand_in(*args: str) -> list[str]:
    return [sys.executable, "-c", KEEPS_50_MS, *args]


#: the real-time probe itself (the fixture below stands in for it)
PROBE = pace_module.realtime_problem


@pytest.fixture(autouse=True)
def keeps_time(monkeypatch: pytest.MonkeyPatch) -> None:
    """These tests are about the pace's doubling: the machine is taken to keep time."""
    monkeypatch.setattr(pace_module, "realtime_problem", lambda: None)


def test_a_period_the_machine_cannot_keep_is_doubled_until_it_can_and_stays_doubled() -> None:
    pace = LoopPace()
    proc = pace.run(stand_in("--cycle-ms", "15"), text=True, timeout=30)
    assert proc.returncode == 0 and float(proc.stdout) == 60.0 and pace.factor == 4 == MAX_FACTOR
    # the next run starts at the learned pace, the default period stretched too
    assert float(pace.run(stand_in("--cycle-ms", "30"), text=True, timeout=30).stdout) == 120.0
    assert float(pace.run(stand_in(), text=True, timeout=30).stdout) == 80.0
    assert pace.ms(20) == 80.0 and pace.given_up is None


def test_other_failures_and_periods_beyond_the_cap_are_returned_as_they_are() -> None:
    pace = LoopPace()
    failing = pace.run([sys.executable, "-c", "import sys; sys.exit(3)", "--cycle-ms", "1"], timeout=30)
    assert failing.returncode == 3 and pace.factor == 1
    with pytest.raises(MachineTooSlow, match=f"up to {MAX_FACTOR}x .*{TOO_SLOW} 4.0"):
        pace.run(stand_in("--cycle-ms", "1"), text=True, timeout=30)  # 4 ms at most: never kept
    assert pace.factor == MAX_FACTOR
    # from then on the session's loop runs are not made at all, even one the machine would keep
    with pytest.raises(MachineTooSlow, match="kept no period"):
        pace.run(stand_in("--cycle-ms", "50"), text=True, timeout=30)


def test_the_launcher_in_this_process_is_paced_and_its_errors_pass_through(capsys: pytest.CaptureFixture[str]) -> None:
    pace = LoopPace()
    assert pace.call(launcher.main, ["--transport", "inproc", "--module-count", "0"]) == 2
    assert "--module-count 0" in capsys.readouterr().err and pace.factor == 1


def test_a_machine_that_keeps_no_time_runs_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pace_module, "realtime_problem", lambda: "sleeps ended 480 ms late (p99)")
    with pytest.raises(MachineTooSlow, match="480 ms late"):
        LoopPace().run([sys.executable, "-c", "raise SystemExit(7)"], timeout=30)


def test_the_real_time_probe_measures_sleeps(monkeypatch: pytest.MonkeyPatch) -> None:
    real = PROBE.__wrapped__  # measured afresh, not the session's cached answer
    # a clock read twice per sleep: 6 ms apart is 1 ms late (kept); 35 ms apart is 30 ms late
    monkeypatch.setattr(time, "sleep", lambda s: None)
    ticks = iter(range(10**6))
    monkeypatch.setattr(time, "monotonic", lambda: next(ticks) * 0.006)
    assert real() is None
    ticks = iter(range(10**6))
    monkeypatch.setattr(time, "monotonic", lambda: next(ticks) * 0.035)
    why = real()
    assert why is not None and "late by 30.0 ms (median)" in why and "p99" in why
