"""Flashing a running robot on a shared bus, in the loop: 8 modules on python-can's ``virtual``
bus (threads of the launcher's process) and on ``udp_multicast`` (processes, inside a private
network namespace the launcher makes) run the caterpillar; at cycle 60 a programming cable
touches the head's free front connector, negotiates a link with it over the connector-local
channel as a module would, and flashes a signed image with another ClockCycle over the bus.

What must hold on any machine: every module commits and runs version 2 (the summary's
version and SHA-256 columns), each named by its path from the cable, and the head's wave goes
on at the new period; every module fixes one switch instant and switches at its first cycle
that begins at or after it.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import pytest

from dh2rt.signed_image import pack, read_private_key, write_key_pair
from hil.netns import namespace_problem
from hil.pace import PACE
from tests.hil.flashing import PERIOD, caterpillar, switch_timing, switches
from tests.marks import sweep

ROOT = Path(__file__).resolve().parents[2]
N = 8
CYCLES = 700


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


@pytest.fixture(scope="module", params=sweep(["virtual", "udp"]))
def bus_run(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    transport = str(request.param)
    if transport == "udp" and (problem := namespace_problem()) is not None:
        pytest.skip(f"udp_multicast runs only in a private network namespace: {problem}")
    tmp = tmp_path_factory.mktemp(f"flash-{transport}")
    key_file = tmp / "robot.key"
    write_key_pair(key_file)
    image = tmp / "v2.img"
    image.write_bytes(pack(caterpillar(20).image, 2, read_private_key(key_file)))
    trace = tmp / "trace.jsonl"
    cmd = [
        sys.executable, "-m", "hil.launcher", "--transport", transport, "--module-count", str(N),
        "--cycles", str(CYCLES), "--cycle-ms", str(round(PERIOD * 1000)), "--stand-in", "recording",
        "--key", str(key_file), "--event", f"60:flash:m0:{image}", "--trace", str(trace), "--json",
    ]  # fmt: skip
    proc = PACE.run(cmd, text=True, timeout=300, cwd=ROOT)
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    records = [json.loads(line) for line in trace.read_text().splitlines()]
    return {"code": proc.returncode, "stderr": proc.stderr, "summary": summary, "records": records}


def test_every_module_on_the_bus_commits_and_is_named_by_its_path(bus_run: dict[str, Any]) -> None:
    summary = bus_run["summary"]
    assert bus_run["code"] == 0, (summary["problems"], bus_run["stderr"][-2000:])
    (rollout,) = summary["rollouts"]
    assert rollout["succeeded"], rollout
    paths = [m["path"] for m in rollout["modules"]]
    assert sorted(len(p.split()) for p in paths) == list(range(1, N + 1)), paths
    assert paths[0].startswith("back>front")  # the cable is a back against the head's free front
    assert sorted(m["module"] for m in rollout["modules"]) == sorted(f"m{i}" for i in range(N))
    sha = hashlib.sha256(caterpillar(20).image).hexdigest()
    assert all(row["version"] == 2 and row["sha256"] == sha for row in summary["modules"]), summary["modules"]
    assert sorted(switches(summary["log"])) == list(range(N)), summary["log"][-30:]


def test_the_wave_goes_on_at_the_new_period_on_the_bus(bus_run: dict[str, Any]) -> None:
    switched = switches(bus_run["summary"]["log"])
    head = sorted(r["cycle"] for r in bus_run["records"] if r["module"] == 0 and r["sent"])
    after = [b - a for a, b in itertools.pairwise(head) if a >= switched[0]]
    assert len(after) > 20 and all(g % 5 == 0 for g in after), after
    assert Counter(after).most_common(1)[0][0] == 5, after


def test_the_switch_is_agreed_on_the_bus(bus_run: dict[str, Any]) -> None:
    timing = switch_timing(bus_run["summary"]["log"], bus_run["records"], N)
    # every module that learned the instant before it passed fixed the same one (the cable's
    # module put it in the middle of its cycle: an error below half a period keeps modules
    # whose cycles are in step at the same cycle)...
    in_time = {m: timing.agreed[m] for m in timing.in_time()}
    assert 0 in in_time, timing.ahead
    spread = (max(in_time.values()) - min(in_time.values())) / PERIOD
    assert spread < 0.5, {m: round((t - min(in_time.values())) / PERIOD, 3) for m, t in in_time.items()}
    # ...and each switched at its first cycle that began at or after it, or, held up, as soon
    # as it had both the image and the instant (module cycles are not in step: all within a
    # period of the instant, plus however late the machine started a module's cycle)
    assert timing.misplaced() == {}, (timing.misplaced(), timing.after())
