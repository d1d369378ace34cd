"""A rollout at every quarter of a ClockCycle, in the loop: the switch may fall at any phase of
the head's LocalTimer, and the wave must go on at the new period whatever the phase.

4 modules on python-can's virtual bus (threads: quick), the launcher's flash event at world
cycles 40, 50, 60 and 70 (the caterpillar's ClockCycle is 40: its four quarters), two seeds
(the modules' LocalTimer phases differ by seed).
"""

from __future__ import annotations

import itertools
import json
from collections import Counter
from pathlib import Path

import pytest

from dh2rt import cli
from dh2rt.signed_image import pack, read_private_key, write_key_pair
from hil.pace import PACE
from tests.hil.flashing import caterpillar, switches
from tests.marks import sweep

#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


@pytest.mark.parametrize("seed", sweep([0, 5]))
@pytest.mark.parametrize("at", sweep([40, 50, 60, 70]))
def test_a_rollout_at_any_phase_of_the_clock_cycle(
    at: int, seed: int, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    key_file = tmp_path / "robot.key"
    write_key_pair(key_file)
    image = tmp_path / "v2.img"
    image.write_bytes(pack(caterpillar(20).image, 2, read_private_key(key_file)))
    trace = tmp_path / "trace.jsonl"
    code = PACE.call(
        cli.main,
        ["--transport", "virtual", "--module-count", "4", "--cycles", "320", "--cycle-ms", "20", "--seed", str(seed),
         "--stand-in", "recording", "--key", str(key_file), "--event", f"{at}:flash:m0:{image}",
         "--trace", str(trace), "--json"],
    )  # fmt: skip
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0, summary["problems"]
    assert all(row["version"] == 2 for row in summary["modules"]), summary["modules"]
    switched = switches(summary["log"])
    assert sorted(switched) == [0, 1, 2, 3], summary["log"][-20:]
    records = [json.loads(line) for line in trace.read_text().splitlines()]
    head = sorted(r["cycle"] for r in records if r["module"] == 0 and r["sent"])
    after = [b - a for a, b in itertools.pairwise(head) if a >= switched[0]]
    assert len(after) > 10 and Counter(after).most_common(1)[0][0] == 5, after
    assert all(g % 5 == 0 for g in after), after
    # and the tail keeps receiving the wave after the switch
    assert any(r["module"] == 3 and r["received"] and r["cycle"] > switched[3] + 10 for r in records)
