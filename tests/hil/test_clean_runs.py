"""Runs in a row with the default body (PyBullet joints through emulated servos): a clean
run must stay clean. Before the health reads were spread over the cycles, modules running as
threads all read their servos in the same cycle, the SDK's busy waits starved the emulators
of the GIL, PINGs went unanswered and links were lost."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import pytest

from hil.pace import PACE
from tests.hil.holds import assert_no_module_held_itself
from tests.marks import LONG

ROOT = Path(__file__).resolve().parents[2]
#: 8 module processes, 16 emulated servos and PyBullet share 2 cores here: 40 ms cycles keep
#: their period with margin when the machine is also busy with other work (20 ms, the
#: default, does on an idle machine: `make demo`).
CYCLE_MS = 40
#: A liveness bound of 6 cycles (240 ms): a module process that the scheduler leaves out for
#: a quarter of a second on a machine busy with other work is not a lost link. The systematic
#: losses this test found (synchronised servo reads, modules stopping one by one) showed at
#: any bound.
SILENCE = 6


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


def launch(transport: str, tmp_path: Path, run: int) -> tuple[int, dict[str, Any], str]:
    cmd = [
        sys.executable, "-m", "hil.launcher", "--transport", transport, "--module-count", "8",
        "--cycles", "300", "--cycle-ms", str(CYCLE_MS), "--silence-cycles", str(SILENCE),
        "--json", "--log", str(tmp_path / f"{transport}-{run}.log"),
    ]  # fmt: skip
    proc = PACE.run(cmd, text=True, timeout=120, cwd=ROOT)
    return proc.returncode, json.loads(proc.stdout), proc.stderr


@pytest.mark.slow
@LONG  # three runs of each transport: a soak (the default body in the loop: test_launcher.py)
@pytest.mark.parametrize("transport", ["virtual", "inproc", "serial"])
def test_three_clean_runs_in_a_row(transport: str, tmp_path: Path) -> None:
    for run in range(3):
        code, summary, err = launch(transport, tmp_path, run)
        assert code == 0, (run, summary["problems"], err[-2000:])
        rows = summary["modules"]
        assert [r["type"] for r in rows] == ["head"] + ["body"] * 6 + ["tail"], run
        assert_no_module_held_itself(summary, SILENCE)  # no link lost that the machine did not cause
        assert not any(r["actuator_fault"] for r in rows), run
        # a servo read that misses now and then on a busy machine is reported and recovered
        # (the log says so); none may be left at the end, and the run must still be clean
        assert summary["displacement_m"] > 0.2, run  # the snake crawled
        frames = summary["frames"]  # every frame accounted for, where it happened
        assert frames["unaccounted"] == 0 and frames["sent"] == frames["received"] > 4000, frames
