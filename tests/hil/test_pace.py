"""hil.pace: a loop run the launcher calls too slow is judged against a bare sleep loop at the
same period. If the bare loop kept it, the run counts (and fails), unless the witness (a bare
loop beside the run) saw the machine stall during it: then the run is made again once at the
same period. If the bare loop did not keep it, the period is stretched by the factor the bare
loop needs, for every later run too; past the cap the pace raises MachineTooSlow. Any other
failure is returned as it is."""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import pytest

from dh2rt.errors import MachineTooSlow
from hil import launcher
from hil import pace as pace_module
from hil.launcher import EXIT_TOO_SLOW
from hil.pace import MAX_FACTOR, Baseline, LoopPace, Witness, measure

#: A launcher stand-in whose modules keep any period of at least 50 ms and which exits as the
#: launcher does when they cannot keep a shorter one; it prints the period it was given.
KEEPS_50_MS = (
    "import sys\n"
    "ms = float(sys.argv[sys.argv.index('--cycle-ms') + 1]) if '--cycle-ms' in sys.argv else 20.0\n"
    "print(ms)\n"
    "if ms < 50:\n"
    "    print('dh2rt: module m0 started 40% of its cycles late', file=sys.stderr)\n"
    f"    sys.exit({EXIT_TOO_SLOW})\n"
)


def stand_in(*args: str) -> list[str]:
    return [sys.executable, "-c", KEEPS_50_MS, *args]


def bare_loop(late_ms: float, share: float) -> Baseline:
    """A bare loop's lateness: ``share`` of 100 cycles ``late_ms`` late, the rest on time."""
    late = round(share * 100)
    return Baseline(0.0, tuple(sorted([0.0] * (100 - late) + [late_ms / 1000] * late)))


def machine(monkeypatch: pytest.MonkeyPatch, late_ms: float, share: float) -> list[float]:
    """Make every bare loop the pace measures late as ``bare_loop`` says; the periods (s) measured."""
    asked: list[float] = []

    def fake(period_s: float) -> Baseline:
        asked.append(period_s)
        return Baseline(period_s, bare_loop(late_ms, share).late_s)

    monkeypatch.setattr(pace_module, "measure", fake)
    return asked


def test_a_period_the_bare_loop_cannot_keep_is_stretched_and_stays(monkeypatch: pytest.MonkeyPatch) -> None:
    asked = machine(monkeypatch, late_ms=30, share=0.3)  # 30 ms stalls: 60 ms periods (late past 30 ms) are kept
    pace = LoopPace()
    proc = pace.run(stand_in("--cycle-ms", "15"), text=True, timeout=30)
    assert proc.returncode == 0 and float(proc.stdout) == 60.0 and pace.factor == 4
    assert asked == [0.015]
    # the next run starts at the learned pace, the default period stretched too
    assert float(pace.run(stand_in("--cycle-ms", "30"), text=True, timeout=30).stdout) == 120.0
    assert float(pace.run(stand_in(), text=True, timeout=30).stdout) == 80.0
    assert pace.ms(20) == 80.0 and asked == [0.015]


def test_a_run_too_slow_where_the_bare_loop_kept_the_period_fails(monkeypatch: pytest.MonkeyPatch) -> None:
    machine(monkeypatch, late_ms=30, share=0.05)  # the bare loop is late in 5% of cycles: it kept 15 ms
    pace = LoopPace()
    proc = pace.run(stand_in("--cycle-ms", "15"), text=True, timeout=30)
    assert proc.returncode == EXIT_TOO_SLOW and float(proc.stdout) == 15.0 and pace.factor == 1
    assert "started 40% of its cycles late" in proc.stderr
    assert "a bare loop at 15 ms started 5% of 100 cycles late" in proc.stderr and "dh2rt is too slow" in proc.stderr


def test_a_bare_loop_that_needs_more_than_the_cap_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    machine(monkeypatch, late_ms=1000, share=0.5)  # stalls of a second, every other cycle
    pace = LoopPace()
    with pytest.raises(MachineTooSlow, match=f"more than {MAX_FACTOR}x"):
        pace.run(stand_in("--cycle-ms", "15"), text=True, timeout=30)
    assert pace.factor == 1


def test_other_failures_are_returned_as_they_are_without_measuring(monkeypatch: pytest.MonkeyPatch) -> None:
    asked = machine(monkeypatch, late_ms=30, share=0.3)
    pace = LoopPace()
    failing = pace.run([sys.executable, "-c", "import sys; sys.exit(4)", "--cycle-ms", "1"], timeout=30)
    assert failing.returncode == 4 and pace.factor == 1 and asked == []


def test_the_launcher_in_this_process_is_paced_and_its_errors_pass_through(capsys: pytest.CaptureFixture[str]) -> None:
    pace = LoopPace()
    assert pace.call(launcher.main, ["--transport", "inproc", "--module-count", "0"]) == 2
    assert "--module-count 0" in capsys.readouterr().err and pace.factor == 1


def test_the_baseline_judges_as_the_launcher_does() -> None:
    b = Baseline(0.02, bare_loop(late_ms=15, share=0.2).late_s)  # late past 10 ms in a fifth of cycles
    assert b.share_late() == 0.2 and not b.kept() and b.stretch() == 2  # late past 20 ms: never
    assert Baseline(0.02, bare_loop(late_ms=15, share=0.1).late_s).kept()
    assert b.allowance_s() == pytest.approx(3 * 0.015 + 0.001)  # three times the p99, plus a millisecond
    assert "started 20% of 100 cycles late" in b.describe() and "15.0 ms (worst)" in b.describe()


def test_the_bare_loop_measures_its_own_lateness() -> None:
    b = measure(0.005, seconds=0.1)  # at least 60 cycles, whatever the length asked for
    assert b.period_s == 0.005 and len(b.late_s) == 60
    assert all(x >= 0 for x in b.late_s) and list(b.late_s) == sorted(b.late_s)


#: A launcher stand-in too slow at its first run only (a file counts its runs).
SLOW_ONCE = (
    "import sys, pathlib\n"
    "runs = pathlib.Path(sys.argv[1])\n"
    "n = int(runs.read_text()) if runs.exists() else 0\n"
    "runs.write_text(str(n + 1))\n"
    "pathlib.Path(f'{runs}.{n}').write_text(' '.join(sys.argv[2:]))\n"
    f"sys.exit({EXIT_TOO_SLOW} if n == 0 else 0)\n"
)


def witness_saw(monkeypatch: pytest.MonkeyPatch, late_ms: float, share: float) -> None:
    """Make every witness beside a run report ``bare_loop(late_ms, share)``."""

    class Seen:
        def __init__(self, period_s: float) -> None:
            self.period_s = period_s

        def stop(self) -> Baseline:
            return Baseline(self.period_s, bare_loop(late_ms, share).late_s)

    monkeypatch.setattr(pace_module, "Witness", Seen)


def test_a_run_too_slow_while_the_witness_stalled_is_made_again_at_the_same_period(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    asked = machine(monkeypatch, late_ms=30, share=0.0)  # the bare loop after the run kept the period
    witness_saw(monkeypatch, late_ms=200, share=0.02)  # the one beside it was stalled twice
    pace = LoopPace()
    runs = tmp_path / "runs"
    proc = pace.run([sys.executable, "-c", SLOW_ONCE, str(runs), "--cycle-ms", "15"], text=True, timeout=30)
    assert proc.returncode == 0 and runs.read_text() == "2" and pace.factor == 1 and asked == [0.015]
    # the run made again writes over the outputs the first one left
    assert (tmp_path / "runs.0").read_text() == "--cycle-ms 15"
    assert (tmp_path / "runs.1").read_text() == "--cycle-ms 15 --force"
    err = capsys.readouterr().err
    assert "a bare loop beside the run at 15 ms started 2% of 100 cycles late" in err
    assert "made again at the same period" in err


def test_a_run_too_slow_again_after_the_witness_retry_fails(monkeypatch: pytest.MonkeyPatch) -> None:
    asked = machine(monkeypatch, late_ms=30, share=0.0)
    witness_saw(monkeypatch, late_ms=200, share=0.02)
    pace = LoopPace()
    proc = pace.run(stand_in("--cycle-ms", "15"), text=True, timeout=30)  # too slow every time
    assert proc.returncode == EXIT_TOO_SLOW and pace.factor == 1 and asked == [0.015, 0.015]  # two runs, no more
    assert "dh2rt is too slow" in proc.stderr and "beside the run at 15 ms started 2% of 100" in proc.stderr


def test_a_run_too_slow_while_the_witness_kept_the_period_is_not_made_again(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    asked = machine(monkeypatch, late_ms=30, share=0.0)
    witness_saw(monkeypatch, late_ms=0, share=0.0)
    runs = tmp_path / "runs"
    proc = LoopPace().run([sys.executable, "-c", SLOW_ONCE, str(runs), "--cycle-ms", "15"], text=True, timeout=30)
    assert proc.returncode == EXIT_TOO_SLOW and runs.read_text() == "1" and asked == [0.015]
    assert "beside the run at 15 ms started 0% of 100 cycles late" in proc.stderr and "dh2rt is too slow" in proc.stderr


def test_the_witness_sees_a_stall_of_its_process() -> None:
    """The witness is a real process: stopped for 150 ms (SIGSTOP, by its pid), its loop
    starts a cycle that much late, and it says so when it ends."""
    w = Witness(0.01)
    time.sleep(0.1)
    os.kill(w.proc.pid, signal.SIGSTOP)
    time.sleep(0.15)
    os.kill(w.proc.pid, signal.SIGCONT)
    time.sleep(0.1)
    seen = w.stop()
    assert w.proc.poll() is not None and len(seen.late_s) >= 15
    assert seen.late_s[-1] >= 0.14 and seen.share_late() > 0 and seen.period_s == 0.01
