"""The launcher's flash event on 8 module processes over serial links when things go wrong,
and the agreed switch instant, read from what the modules say (issue 27):

- 5 % of the link frames lost, or m3 killed mid-transfer and restarted: every module ends on
  version 2, and the rollout report names every one of them (its path, as the modules' logs
  name themselves, its version, its program's SHA-256 and its outcome);
- every module starts the new program at its first cycle at or after the instant the COMMIT
  agreed (docs/flashing.md, "The switch"), or, held up by the shared machine, as soon as it
  has both the image and the instant.

Two seeds and two flash cycles each (the modules' phases and the state of the head's wave
differ), few cycles per run.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path
from typing import Any

import pytest

from dh2rt import cli
from hil.pace import PACE
from tests.hil.flashing import PERIOD, caterpillar, robot_key_and_image, switch_timing
from tests.marks import sweep

#: modules run in real time: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime

N = 8


def launch(tmp_path: Path, capsys: pytest.CaptureFixture[str], seed: int, *extra: str) -> tuple[int, dict[str, Any]]:
    key_file, image = robot_key_and_image(tmp_path, 20)
    code = PACE.call(
        cli.main,
        ["--transport", "serial", "--module-count", str(N), "--cycles", "360", "--cycle-ms", "20",
         "--seed", str(seed), "--stand-in", "recording", "--key", str(key_file), "--json",
         *(e.replace("IMAGE", str(image)) for e in extra)],
    )  # fmt: skip
    return code, json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def names_in_logs(log: list[str]) -> dict[str, str]:
    """Module -> the name its log gave itself (its last life's)."""
    out: dict[str, str] = {}
    for line in log:
        m = re.match(r"(m\d+): cycle \d+: rollout: named (.+)$", line)
        if m:
            out[m.group(1)] = m.group(2)
    return out


def assert_every_module_named(summary: dict[str, Any]) -> None:
    (rollout,) = summary["rollouts"]
    sha = hashlib.sha256(caterpillar(20).image).hexdigest()
    rows = {m["module"]: m for m in rollout["modules"]}
    assert sorted(rows) == [f"m{i}" for i in range(N)], rows
    for name, m in rows.items():
        assert (m["outcome"], m["version"], m["sha256"]) == ("committed", 2, sha), (name, m)
    assert rollout["succeeded"] and rollout["failure"] is None, rollout
    for row in summary["modules"]:
        assert (row["version"], row["sha256"]) == (2, sha), row
    # one name for a module's place: the report's path is the name its own log gave itself
    logged = names_in_logs(summary["log"])
    assert {name: m["path"] for name, m in rows.items()} == logged, logged
    assert sorted(len(p.split()) for p in logged.values()) == list(range(1, N + 1)), logged


@pytest.mark.parametrize(("seed", "at"), sweep([(0, 60), (1, 100), (0, 100), (1, 60)]))
def test_a_flash_under_5_percent_loss_names_every_module(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], seed: int, at: int
) -> None:
    code, summary = launch(tmp_path, capsys, seed, "--frame-loss", "0.05", "--event", f"{at}:flash:m0:IMAGE")
    assert code == 0, summary["problems"]
    assert_every_module_named(summary)


@pytest.mark.parametrize(("seed", "at"), sweep([(0, 60), (1, 100), (0, 100), (1, 60)]))
def test_m3_killed_mid_transfer_and_restarted_every_module_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], seed: int, at: int
) -> None:
    events = ["--event", f"{at}:flash:m0:IMAGE", "--event", f"{at + 6}:kill:m3", "--event", f"{at + 30}:restart:m3"]
    code, summary = launch(tmp_path, capsys, seed, *events)
    assert code == 0, summary["problems"]
    assert any("kill:m3" in line for line in summary["log"]), summary["log"][-20:]
    assert_every_module_named(summary)


@pytest.mark.parametrize(("seed", "at"), sweep([(0, 60), (1, 100), (0, 100), (1, 60)]))
def test_every_module_switches_at_its_first_cycle_after_the_agreed_instant(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], seed: int, at: int
) -> None:
    trace = tmp_path / "trace.jsonl"
    code, summary = launch(tmp_path, capsys, seed, "--event", f"{at}:flash:m0:IMAGE", "--trace", str(trace))
    assert code == 0, summary["problems"]
    timing = switch_timing(summary["log"], [json.loads(line) for line in trace.read_text().splitlines()], N)
    agreed = timing.agreed
    # the instant the module at the cable fixed (the middle of its cycle), carried hop by hop;
    # each hop adds the error of its transit estimate (on the loop's emulated lines of a loaded
    # machine up to 0.6 periods: not judged here, shown when something else fails)
    skew = {m: round((agreed[m] - agreed[m - 1]) / PERIOD, 3) for m in range(1, N)}
    # each at its first cycle at or after its instant (or, held up, as soon as it was ready)
    assert timing.misplaced() == {}, (timing.misplaced(), timing.after(), skew)
    # (that the cable's module puts the instant in the middle of its cycle, so that modules in
    # step switch at one cycle, is test_rollout's test_every_module_stages_commits_and_switches_at_one_cycle:
    # here a late cycle that restarts a module's schedule moves its cycles after the fact)
