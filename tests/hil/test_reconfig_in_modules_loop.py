"""Snake to quadruped and legs to snake, whole, in the loop with the motions in the modules and
the latch emulator (``--motions-in-modules --latch-emulator``, issue 28's done-when): each
module process plans and runs its own docking motions, closes its own latch servo (real
dynamixel-sdk over a pty to the world's emulated servo, real PyBullet), and the world sends no
joint target (``reaches.holds_sent`` is 0); the motion frames are in the capture.

Each run is minutes of real time (a quadruped 350 s, legs to snake 450 s at 50 ms), and the
loop's timing decides some runs (docs/hil.md): they run with ``DH2RT_LONG_LOOP=1``, as the
world-run loop reconfigurations do (tests/hil/test_hil_reconfig_physics.py)."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Any

import pytest

from hil.pace import PACE
from sim.runner import DOCK_TOLERANCE_DEG, DOCK_TOLERANCE_M
from tests.hil.test_hil_reconfig_physics import links_after
from tests.marks import LONG
from tools.reading import open_capture

ROOT = Path(__file__).resolve().parents[2]
#: World cycles: the quadruped formed at 2,790 to 5,867 in physics with the modules' motions
#: (seeds 0-2, docs/physics.md); legs to snake at 5,525 to 7,928. In the loop, seed 2: the fourth
#: dock at world cycle 4,199.
QUAD_CYCLES = 7000
LTS_CYCLES = 9000

#: module processes run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = [
    pytest.mark.realtime,
    pytest.mark.skipif(
        os.environ.get("DH2RT_LONG_LOOP") != "1",
        reason="whole reconfigurations in the loop, minutes each (docs/hil.md); DH2RT_LONG_LOOP=1 runs them",
    ),
]


def _run(tmp_path: Path, program: str, topology: str, cycles: int, event: str, seed: int) -> dict[str, Any]:
    capture = tmp_path / "run.pcapng"
    argv = [sys.executable, "-m", "hil.launcher", "--transport", "serial",
            "--program", str(ROOT / "examples" / program), "--topology", topology,
            "--cycles", str(cycles), "--cycle-ms", "50", "--silence-cycles", "6", "--event", event,
            "--seed", str(seed), "--json", "--stand-in", "pybullet", "--motions-in-modules", "--latch-emulator",
            "--capture", str(capture)]  # fmt: skip
    proc = PACE.run(argv, timeout=cycles * 0.05 * 3 + 120, text=True, cwd=ROOT)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    summary: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    texts = [h.text for h in open_capture(capture).hops() if h.kind == "control" and " motion " in h.text]
    summary["motion_frames"] = {
        kind: sum(t.startswith(f"{kind} motion") for t in texts) for kind in ("ASK", "ANGLES", "TARGETS", "END")
    }
    return summary


def _is_one_snake(links: set[tuple[str, str, str, str]], modules: int) -> bool:
    """Every link joins a back to a front, and they chain all ``modules`` into one line."""
    pairs = {}  # a module -> the module whose front is docked to its back
    for a, ac, b, bc in links:
        if {ac, bc} != {"front", "back"}:
            return False
        back, front = (a, b) if ac == "back" else (b, a)
        pairs[back] = front
    if len(pairs) != modules - 1 or len(set(pairs.values())) != modules - 1:
        return False
    heads = set(pairs) - set(pairs.values())  # nothing docked to its front
    if len(heads) != 1:
        return False
    (head,) = heads
    seen, at = {head}, head
    while at in pairs:
        at = pairs[at]
        seen.add(at)
    return len(seen) == modules


def _own_and_within_tolerance(summary: dict[str, Any]) -> None:
    reaches = summary["reaches"]
    assert reaches["holds_sent"] == 0, reaches["holds_sent"]  # the world moved no joint
    for contact in reaches["contacts"]:
        assert contact["distance_mm"] <= DOCK_TOLERANCE_M * 1000, contact
        assert contact["attitude_deg"] <= DOCK_TOLERANCE_DEG, contact
    frames = summary["motion_frames"]
    assert all(frames[k] > 0 for k in ("ASK", "ANGLES", "TARGETS", "END")), frames


@LONG
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_snake_to_quadruped_forms_on_the_modules_own_motions_and_latches(tmp_path: Path, seed: int) -> None:
    """QSS at m4 on snake:9: the four docks are the asking modules' own, each closed by the
    asking module's latch servo (the front: CONRO's female face), and the five releases."""
    summary = _run(tmp_path, "snake_to_quadruped.dh2", "snake:9", QUAD_CYCLES, "50:inject:m4:QSS", seed)
    log = summary["log"]
    docked = [line for line in log if "docked to" in line]
    assert len(docked) == 4 and all("by its latch's horn" in line for line in docked), docked
    assert sum(line.endswith("released") for line in log) == 5, [x for x in log if "release" in x]
    assert summary["reaches"]["latch_answers"] == 0
    _own_and_within_tolerance(summary)


@LONG
@pytest.mark.xfail(
    reason="measured once, seed 0 (2026-11-28): not formed in 9,000 world cycles. The first foot arrived 2.4 cm "
    "aside, its creep did not square it (no latch asked), and its trip round again turned in place behind the "
    "tail (1,715 of 2,501 cycles); the tail took it for stuck (docs/hil.md)",
    strict=False,
)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_legs_to_snake_forms_on_the_modules_own_motions(tmp_path: Path, seed: int) -> None:
    """LTS at spine0 on the dragon: each tail asks its foot over the links (SET_OFF), the foot
    trips and creeps by the tracker, the tail squares up and latches; all eleven modules end
    in one snake. The tail's back is male: the world latches it (the foot's own latch would
    have to close on the tail's pins, not modelled)."""
    summary = _run(tmp_path, "legs_to_snake.dh2", "dragon", LTS_CYCLES, "50:inject:spine0:LTS", seed)
    log = summary["log"]
    links = links_after("dragon", log, "legs_to_snake.dh2")
    assert _is_one_snake(links, 11), (sorted(links), [x for x in log if "dock" in x or "release" in x][-30:])
    _own_and_within_tolerance(summary)
