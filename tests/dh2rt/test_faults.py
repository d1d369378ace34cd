"""Receptor faults are visible: module, receptor, cycle and message in the summary (a count
and the last message per module), in --json, and in the trace record of the cycle."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dh2rt.cli import main

DIVIDING = """program dividing
const ClockCycle = 10
var x = 0
receptor divide when T == T1 and LocalTimer == 3 {
    V.x = 10 / V.x; keep_alive()
}
"""


@pytest.fixture
def program(tmp_path: Path) -> Path:
    path = tmp_path / "dividing.dh2"
    path.write_text(DIVIDING)
    return path


@pytest.mark.expect_faults
def test_faults_in_summary_json_and_trace(program: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    trace = tmp_path / "t.jsonl"
    argv = ["run", str(program), "--topology", "snake:3", "--cycles", "25", "--seed", "1"]
    assert main([*argv, "--trace", str(trace)]) == 0
    out = capsys.readouterr().out
    assert "receptor faults in 1 module(s):" in out
    assert "m0: " in out and "receptor divide: division by zero in a DH2 expression" in out
    faulted = [json.loads(line) for line in trace.read_text().splitlines() if '"faults"' in line]
    assert faulted and all(r["name"] == "m0" for r in faulted)
    assert faulted[0]["faults"] == ["receptor divide: division by zero in a DH2 expression"]
    assert all(r["timer"] == 3 for r in faulted)  # the cycle the receptor ran in

    assert main([*argv, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert [f["cycle"] for f in summary["faults"]] == [r["cycle"] for r in faulted]
    assert {f["module"] for f in summary["faults"]} == {"m0"}
    head = summary["modules"][0]
    assert head["faults"] == len(faulted)
    last = faulted[-1]["cycle"]
    assert head["last_fault"] == f"cycle {last}: m0: receptor divide: division by zero in a DH2 expression"
    assert summary["modules"][1]["last_fault"] is None
