"""The launcher's ``--event CYCLE:flash:M:IMAGE``: a signed image flashed into the running
robot through a cable on module M, the rollout report in the summary, and bad flash events
refused before anything starts (exit 2, naming the event)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import pytest

from dh2rt import cli
from dh2rt.signed_image import new_private_key, pack, read_private_key, write_key_pair
from hil.pace import PACE
from tests.hil.flashing import caterpillar, robot_key_and_image
from tests.hil.frames import adds_up
from tests.hil.holds import assert_no_module_held_itself
from tests.marks import sweep

#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


def _image(tmp_path: Path, key: bytes, version: int, clock_cycle: int = 20) -> Path:
    path = tmp_path / f"v{version}.img"
    path.write_bytes(pack(caterpillar(clock_cycle).image, version, key))
    return path


def _flash_four(tmp_path: Path, capsys: pytest.CaptureFixture[str], cycles: int) -> tuple[int, dict[str, Any]]:
    """A snake of 4 on serial links for ``cycles`` cycles, version 2 flashed at cycle 40 through
    m0; the exit code and the summary."""
    key_file = tmp_path / "robot.key"
    write_key_pair(key_file)
    image = _image(tmp_path, read_private_key(key_file), 2)
    code = PACE.call(
        cli.main,
        ["--transport", "serial", "--module-count", "4", "--cycles", str(cycles), "--cycle-ms", "20",
         "--stand-in", "recording", "--key", str(key_file), "--event", f"40:flash:m0:{image}", "--json"]
    )  # fmt: skip
    return code, json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_a_flash_event_switches_every_module_and_the_summary_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, summary = _flash_four(tmp_path, capsys, 250)
    assert code == 0, summary["problems"]
    adds_up(summary["frames"])  # every frame of the rollout accounted for (issue 27)
    (rollout,) = summary["rollouts"]
    assert rollout["succeeded"] and rollout["failure"] is None
    paths = sorted(m["path"] for m in rollout["modules"])
    assert len(paths) == 4 and len({len(p) for p in paths}) == 4, paths  # one hop further each
    assert sorted(m["module"] for m in rollout["modules"]) == ["m0", "m1", "m2", "m3"]
    sha = hashlib.sha256(caterpillar(20).image).hexdigest()
    for row in summary["modules"]:
        assert row["version"] == 2, row
        assert row["sha256"] == sha, (row["name"], row["sha256"], sha)


@pytest.mark.parametrize(
    ("event", "needle"),
    [
        ("40:flash:m9:{image}", "m9"),
        ("40:flash:m0:{missing}", "cannot read the image"),
        ("40:flash:m0:{garbage}", "garbage.img"),
        ("x:flash:m0:{image}", "expected CYCLE:flash:MODULE:IMAGE"),
        ("900:flash:m0:{image}", "never happens"),
    ],
)
def test_a_bad_flash_event_exits_2_naming_it(
    event: str, needle: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    image = _image(tmp_path, new_private_key(), 2)
    garbage = tmp_path / "garbage.img"
    garbage.write_bytes(b"not an image at all")
    text = event.format(image=image, missing=tmp_path / "missing.img", garbage=garbage)
    code = cli.main(["--transport", "serial", "--module-count", "4", "--cycles", "500", "--event", text])
    err = capsys.readouterr().err
    assert code == 2
    assert needle in err and "Traceback" not in err, err


def test_a_flash_event_needs_cables(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    image = _image(tmp_path, new_private_key(), 2)
    code = cli.main(["--transport", "inproc", "--module-count", "4", "--cycles", "500",
                     "--event", f"40:flash:m0:{image}"])  # fmt: skip
    assert code == 2
    assert "a programming cable needs links it can join" in capsys.readouterr().err


@pytest.mark.parametrize(("seed", "at"), sweep([(0, 100), (3, 60)]))
def test_the_docs_example_the_same_program_at_version_2_names_all_8_modules(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], seed: int, at: int
) -> None:
    """docs/flashing.md's example with the image unedited (issue 27): the program the robot
    runs, signed again at version 2. Every one of the 8 modules is in the report, with version
    2 and its SHA-256, and no link was lost to the rollout's loading."""
    key_file, image = robot_key_and_image(tmp_path, 40)
    code = PACE.call(
        cli.main,
        ["--transport", "serial", "--module-count", "8", "--cycles", "320", "--cycle-ms", "20", "--seed", str(seed),
         "--stand-in", "recording", "--key", str(key_file), "--event", f"{at}:flash:m0:{image}", "--json"]
    )  # fmt: skip
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0, summary["problems"]
    (rollout,) = summary["rollouts"]
    assert rollout["succeeded"], rollout
    sha = hashlib.sha256(caterpillar(40).image).hexdigest()
    rows = {m["module"]: m for m in rollout["modules"]}
    assert sorted(rows) == [f"m{i}" for i in range(8)], rows
    for name, m in rows.items():
        assert (m["outcome"], m["version"], m["sha256"]) == ("committed", 2, sha), (name, m)
    # no module held itself (by its rollout's work) as long as its liveness bound, and any link
    # lost is one the machine's holds explain (tests/hil/holds.py)
    assert_no_module_held_itself(summary)


def test_a_run_that_ends_before_its_flasher_is_done_says_so_and_stops_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The modules' last cycle comes 5 cycles after the cable goes in: the run fails (exit 1)
    naming why, and the flasher's thread is stopped before its transport closes (closed under
    it, the thread once died mid-send: an unhandled thread exception, which pytest reports)."""
    code, summary = _flash_four(tmp_path, capsys, 45)
    assert code == 1, summary["problems"]
    (rollout,) = summary["rollouts"]
    assert not rollout["succeeded"]
    assert rollout["failure"].startswith("the run ended before the flasher was done"), rollout["failure"]
