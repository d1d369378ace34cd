"""The loop's overhead tracker over UDP (``--tracker-udp``): each module hears the tracker
itself through its ``[tracker]`` (firmware/tracker_floor.py), the world sending the stand-in
tracker's report as ``dh2rt tracker``'s datagrams to each module's own port on 127.0.0.1
(hil.tracker_udp) instead of in its ``Floor`` command.

Real parts: the launcher in a process of its own, module processes, real UDP sockets on
loopback, real PyBullet."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import pytest

from hil import launcher
from hil.pace import PACE
from sim.runner import DOCK_TOLERANCE_DEG, DOCK_TOLERANCE_M
from tests.marks import LONG

ROOT = Path(__file__).resolve().parents[2]
PROGRAM = str(ROOT / "examples" / "snake_to_t.dh2")
#: World cycles for snake_to_t with the motion in the modules (as tests/hil/test_hil_reach_physics.py)
OWN_T_CYCLES = 1000

#: module processes run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


@pytest.mark.parametrize(
    "extra",
    [
        ["--stand-in", "pybullet"],  # the world runs the motions: no module reads the floor
        ["--stand-in", "recording", "--motions-in-modules"],
        ["--stand-in", "recording"],
    ],
)
def test_the_option_needs_pybullet_and_the_motions_in_the_modules(
    extra: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["--transport", "serial", "--program", PROGRAM, "--topology", "snake:2", "--cycles", "5", "--tracker-udp"]
    code = launcher.main(argv + extra)
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err, err
    if "--motions-in-modules" in extra and "recording" in extra:  # refused first for --motions-in-modules
        assert "--motions-in-modules" in err and "--stand-in pybullet" in err, err
    else:
        assert "--tracker-udp" in err and "--stand-in pybullet and --motions-in-modules" in err, err


def test_help_says_what_it_does(capsys: pytest.CaptureFixture[str]) -> None:
    assert launcher.main(["--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--tracker-udp" in text and "needs --stand-in pybullet and --motions-in-modules" in text


@LONG  # a whole reconfiguration in the loop
def test_snake_to_t_forms_with_the_modules_hearing_the_tracker() -> None:
    """--motions-in-modules --tracker-udp, seed 0: m0's own reach steers by the poses its own
    feed took from the world's datagrams (its log says so, its final status counts them); the
    T forms within the docking tolerance, as with the world's Floor."""
    cmd = [
        sys.executable, "-m", "hil.launcher", "--transport", "serial", "--program", PROGRAM,
        "--topology", "snake:8", "--cycles", str(OWN_T_CYCLES), "--cycle-ms", "50", "--silence-cycles", "6",
        "--event", "50:inject:m4:STT", "--seed", "0", "--json", "--stand-in", "pybullet",
        "--motions-in-modules", "--tracker-udp",
    ]  # fmt: skip
    proc = PACE.run(cmd, text=True, timeout=240, cwd=ROOT)
    out = proc.stdout
    assert proc.returncode == 0, (out[-2000:], proc.stderr[-2000:])
    summary: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
    log = summary["log"]
    docking = [line for line in log if "dock" in line or "tracker" in line or "release" in line]
    assert any(line.startswith("m0: tracker: the floor from UDP 127.0.0.1:") for line in log), docking
    assert any("m0: " in line and "tracker: the floor from the feed: modules [" in line for line in log), docking
    rows = {m["name"]: m for m in summary["modules"]}
    assert rows["m0"]["tracker"]["datagrams"] > 0 and rows["m0"]["tracker"]["rejected"] == 0, rows["m0"]
    assert all(r["tracker"] is not None for r in rows.values())  # every module had a [tracker]
    sent = summary["reaches"]["tracker_udp"]
    assert sent["sent"] >= rows["m0"]["tracker"]["datagrams"] and sent["failed"] == 0, sent
    types = {name: r["type"] for name, r in rows.items()}
    assert types["m3"] == "head" and types["m2"] == "tail" and types["m7"] == "tail", (types, docking)
    docked = [line for line in log if "m0.front docked to m5.left" in line]
    assert len(docked) == 1 and "by motion, the module's own" in docked[0], docking
    (contact,) = summary["reaches"]["contacts"]
    assert contact["distance_mm"] <= DOCK_TOLERANCE_M * 1000 and contact["attitude_deg"] <= DOCK_TOLERANCE_DEG
