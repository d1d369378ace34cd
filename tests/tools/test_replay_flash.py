"""``dh2rt replay`` on the capture of a flash run: four modules over serial links, the
caterpillar flashed with another ClockCycle through m0 in the middle. Each module's Hello
names its new program when it switches; replay rebuilds every module's trace records across
the switch from the capture alone (the image joined from its transfer frames), or with the
flashed image given (``--flashed``), stops at a receptor of the new program where the run's
own trace says, and where a segment of the image is missing from the capture says so and
which module switched to which program at which cycle, rebuilds the rest and exits 2."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from dh2rt.signed_image import write_key_pair
from hil import launcher
from hil.pace import PACE
from tests.hil.flashing import PROGRAM, robot_key_and_image
from tests.tools.test_replay import key, replay, rewrite
from tools.reading import open_capture

pytestmark = pytest.mark.realtime
Record = dict[str, Any]

NEW_DIGEST_LEN = 12  # hex of a Hello's 6-byte digest


@pytest.fixture(scope="module")
def flashed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, list[Record]]:
    """The run's capture, the flashed image and the run's own trace records."""
    folder = tmp_path_factory.mktemp("replay_flash")
    key, image = robot_key_and_image(folder, 20)  # the caterpillar's ClockCycle 40 -> 20
    capture, trace = folder / "flash.pcapng", folder / "flash.jsonl"
    code = PACE.call(
        launcher.main,
        ["--transport", "serial", "--module-count", "4", "--cycles", "120", "--stand-in", "none",
         "--key", str(key), "--event", f"30:flash:m0:{image}", "--capture", str(capture), "--trace", str(trace)],
    )  # fmt: skip
    assert code == 0
    return capture, image, [json.loads(line) for line in trace.read_text().splitlines()]


def notes(err: str, kind: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith(f"replay: {kind}: ")]


def switch_cycles(err: str, kind: str) -> dict[str, int]:
    """module name -> the cycle a ``kind`` note (switch, program) names."""
    found = {}
    for line in notes(err, kind):
        name, _, rest = line.split(": ", 2)[2].partition(" ")
        found[name] = int(rest.split("cycle ")[1].split(":")[0])
    return found


def test_replay_rebuilds_every_record_across_the_switch(
    flashed: tuple[Path, Path, list[Record]], capsys: pytest.CaptureFixture[str]
) -> None:
    capture, image, records = flashed
    out, err = replay(capsys, capture, "--flashed", image)
    rebuilt = [json.loads(line) for line in out.splitlines()]
    assert {key(r): r for r in rebuilt} == {key(r): r for r in records}
    assert len(rebuilt) == len(records)
    switched = switch_cycles(err, "switch")
    assert sorted(switched) == ["m0", "m1", "m2", "m3"], err
    # the new program's ClockCycle (20) shows in the trace from the switch on: the records agree
    for name, cycle in switched.items():
        later = [r for r in records if r["name"] == name and r["cycle"] >= cycle]
        assert later and max(r["timer"] for r in later) < 20, (name, cycle)
    assert [line for line in err.splitlines() if "diverged" in line or "missing" in line] == []


def test_a_receptor_breakpoint_of_the_new_program_stops_where_the_trace_says(
    flashed: tuple[Path, Path, list[Record]], capsys: pytest.CaptureFixture[str]
) -> None:
    capture, image, records = flashed
    _, err = replay(capsys, capture, "--flashed", image)
    switch_at = switch_cycles(err, "switch")["m0"]
    out, _ = replay(capsys, capture, "--flashed", image, "--json", "--break", "receptor head_a fires")
    stops = [s for s in json.loads(out)["stops"] if s["record"]["cycle"] >= switch_at]
    # the head runs head_a when its LocalTimer is 0: under the new ClockCycle, every 20 cycles
    expected = [
        (r["module"], r["cycle"]) for r in records if r["module"] == 0 and r["cycle"] >= switch_at and r["timer"] == 0
    ]
    assert expected
    assert [(s["record"]["module"], s["record"]["cycle"]) for s in stops] == expected
    assert all(s["fired"] == ["head_a"] for s in stops)


def test_the_capture_alone_carries_the_flashed_image_and_replay_runs_it(
    flashed: tuple[Path, Path, list[Record]], capsys: pytest.CaptureFixture[str]
) -> None:
    capture, image, records = flashed
    out, err = replay(capsys, capture)
    assert {key(r): r for r in map(json.loads, out.splitlines())} == {key(r): r for r in records}
    (said,) = notes(err, "image")
    assert "program caterpillar version 2, rebuilt from 5 segments" in said and "signature not checked" in said
    assert sorted(switch_cycles(err, "switch")) == ["m0", "m1", "m2", "m3"]
    # under --trust: the right key runs it, another key does not (and replay says the rest is incomplete)
    _, err = replay(capsys, capture, "--trust", image.parent / "robot.key.pub")
    assert "signature not checked" not in notes(err, "image")[0]
    write_key_pair(image.parent / "stranger.key")
    _, err = replay(capsys, capture, "--trust", image.parent / "stranger.key.pub", code=2)
    assert notes(err, "image")[0].endswith("wrong key under the --trust keys: not run")


def test_without_the_flashed_program_replay_names_module_cycle_and_digest_and_exits_2(
    flashed: tuple[Path, Path, list[Record]], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    capture, _, records = flashed
    # every copy of the image's second segment taken out of the capture: the image is not whole
    serial = [h for h in open_capture(capture).hops() if h.medium == "serial"]
    second = {
        i for i, h in enumerate(serial) if h.kind == "transfer" and h.text.startswith("SEGMENT ") and " #1 " in h.text
    }
    assert second
    cut = rewrite(capture, tmp_path / "cut.pcapng", lambda i: i not in second)
    out, err = replay(capsys, cut, code=2)
    (said,) = notes(err, "image")
    assert "4 of its 5 segments are in the capture: not rebuilt (give it with --flashed FILE)" in said
    missing = switch_cycles(err, "program")
    assert sorted(missing) == ["m0", "m1", "m2", "m3"], err
    digests = {line.split("runs program ")[1].split()[0] for line in notes(err, "program")}
    assert len(digests) == 1 and len(digests.pop()) == NEW_DIGEST_LEN
    assert "give it with --flashed FILE" in err
    # the cycles before each module's switch are rebuilt as the run's own trace has them
    rebuilt = {key(r): r for r in map(json.loads, out.splitlines())}
    before = {key(r): r for r in records if r["cycle"] < missing[r["name"]]}
    assert rebuilt == before


def test_with_trust_keys_the_flashed_image_must_be_signed_by_one(
    flashed: tuple[Path, Path, list[Record]], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    capture, image, _ = flashed
    _, err = replay(capsys, capture, "--flashed", image, "--trust", image.parent / "robot.key.pub")
    assert len(notes(err, "switch")) == 4
    write_key_pair(tmp_path / "other.key")
    _, err = replay(capsys, capture, "--flashed", image, "--trust", tmp_path / "other.key.pub", code=2)
    assert f"--flashed {image}: wrong key under the --trust keys: a module would refuse it" in err
    assert "Traceback" not in err


def test_a_flashed_program_no_hello_names_exits_2(
    flashed: tuple[Path, Path, list[Record]], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    capture, _, _ = flashed
    other = tmp_path / "cat7.dh2"
    text = PROGRAM.read_text(encoding="utf-8")
    other.write_text(text.replace("const ClockCycle = 40", "const ClockCycle = 7"), encoding="utf-8")
    _, err = replay(capsys, capture, "--flashed", other, code=2)
    assert f"--flashed {other}: digest " in err and "no module ran it" in err
