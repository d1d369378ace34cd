"""Careless input never crashes: every case exits 2 with a message naming the culprit (the
event, the key, the file and position, the option), and no traceback.

The cases run through ``dh2rt.cli.main`` in this process, so an exception that escaped would
fail the test with its traceback; one case also goes through the console script.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from dh2rt.cli import main
from dh2rt.errors import TopologyError
from dh2rt.profile import CONRO

ROOT = Path(__file__).resolve().parents[2]
CATERPILLAR = str(ROOT / "examples" / "caterpillar.dh2")


def files(tmp: Path) -> dict[str, Path]:
    """Bad inputs written to disk: name -> path."""
    out = {
        "latin1.dh2": b"program x\nconst ClockCycle = 4\n# caf\xe9\n",
        "deep.dh2": (
            "program deep\nconst ClockCycle = 4\nreceptor r when " + "(" * 10_000 + "true" + ")" * 10_000 + " { }\n"
        ).encode(),
        "zero.toml": b"modules = 0\n",
        "negative.toml": b"modules = -3\n",
        "misspelled.toml": b'modules = 3\n[[link]]\nlinks = ["0.back <-> 1.front"]\n',
        "latin1.toml": b"modules = 2 # \xe9\n",
        "empty.toml": b"modules = []\n",
        # a flat sum of 1,000 terms and a 10,000-term `and`: refused at the operator one too many
        "sum.dh2": ("program s\nconst ClockCycle = 4\nconst X = " + " + ".join(["1"] * 1_000) + "\n").encode(),
        "and.dh2": (
            "program a\nconst ClockCycle = 4\nreceptor r when " + " and ".join(["LocalTimer == 0"] * 10_000) + " { }\n"
        ).encode(),
        "noclock.dh2": b"program n\n\nhormone X\nreceptor r when H == X { DOF1(10) }\n",
        "hugeclock.dh2": b"program h\nconst ClockCycle = 10000000\n",
    }
    for name, data in out.items():
        (tmp / name).write_bytes(data)
    return {name: tmp / name for name in out}


# (argv with {tmp} and {name.ext} placeholders, words the error must contain)
CASES = [
    (["run", CATERPILLAR, "--event", "0:cut:m0.front"], ["0:cut:m0.front", "nothing is docked"]),
    (["run", CATERPILLAR, "--event", "5:cut:m3.back", "--event", "6:cut:m3.back"], ["6:cut:m3.back", "nothing"]),
    (["run", CATERPILLAR, "--event", "10:dock:m0.back-m7.back"], ["10:dock:m0.back-m7.back", "male"]),
    (["run", CATERPILLAR, "--event", "10:dock:m0.front-m0.back"], ["10:dock:m0.front-m0.back", "itself"]),
    (["run", CATERPILLAR, "--cycles", "100", "--event", "300:kill:m1"], ["300:kill:m1", "last cycle is 99"]),
    (["run", CATERPILLAR, "--event", "10:kill:m2", "--event", "20:inject:m2:X(A)"], ["20:inject:m2:X(A)", "stopped"]),
    (["run", CATERPILLAR, "--event", "10:cut:m1.side"], ["10:cut:m1.side", "unknown connector 'side'"]),
    (["run", CATERPILLAR, "--topology", "{zero.toml}"], ["zero.toml", "'modules'", "at least 1"]),
    (["run", CATERPILLAR, "--topology", "{negative.toml}"], ["negative.toml", "'modules'"]),
    (["run", CATERPILLAR, "--topology", "{misspelled.toml}"], ["misspelled.toml", "unknown key", "'link'"]),
    (["run", CATERPILLAR, "--topology", "{latin1.toml}"], ["latin1.toml", "UTF-8"]),
    (["run", CATERPILLAR, "--topology", "{empty.toml}"], ["empty.toml", "no module"]),
    (["check", "{latin1.dh2}"], ["latin1.dh2:3:6", "not UTF-8"]),
    (["check", "{deep.dh2}"], ["deep.dh2:3:", "nested more than 100"]),
    (["check", "{tmp}/nowhere.dh2"], ["nowhere.dh2", "cannot read"]),
    (["run", CATERPILLAR, "--trace", "{tmp}/t.txt"], ["--trace", "t.txt", ".jsonl"]),
    (["run", CATERPILLAR, "--trace", "{tmp}"], ["--trace", "folder"]),
    (["run", CATERPILLAR, "--sim", "pybullet", "--record", "{tmp}/x.png"], ["--record", "x.png", ".gif"]),
    (["run", CATERPILLAR, "--sim", "pybullet", "--plot", "{tmp}/x.gif"], ["--plot", "x.gif", ".png"]),
    (["run", CATERPILLAR, "--record", "{tmp}/x.gif"], ["--record", "--sim pybullet"]),
    (["run", CATERPILLAR, "--cycles", "-1"], ["--cycles"]),
    (["check", "{sum.dh2}"], ["sum.dh2:3:1037:", "more than 256 operators"]),
    (["check", "{and.dh2}"], ["and.dh2:3:5153:", "more than 256 operators"]),
    (["check", "{noclock.dh2}"], ["noclock.dh2:3:9:", "const ClockCycle = N"]),
    (["check", "{hugeclock.dh2}"], ["hugeclock.dh2:2:7:", "ClockCycle must be 1..100000"]),
    (["run", CATERPILLAR, "--trace", "/proc/no-such-dir/t.jsonl"], ["--trace", "t.jsonl"]),
]


@pytest.mark.parametrize(("argv", "words"), CASES, ids=lambda v: " ".join(v)[-60:] if isinstance(v, list) else "")
def test_careless_input_exits_2_naming_the_culprit(
    argv: list[str], words: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    paths = files(tmp_path)
    args = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    for name, path in paths.items():
        args = [a.replace("{" + name + "}", str(path)) for a in args]
    assert main(args) == 2
    err = capsys.readouterr().err
    for word in words:
        assert word in err, (word, err)
    assert "Traceback" not in err


def test_outputs_create_missing_folders_inside_the_current_one_and_dash_is_stdout(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "here").mkdir()
    monkeypatch.chdir(tmp_path / "here")
    outside = tmp_path / "elsewhere" / "t.jsonl"  # no folder is made outside the current one unasked
    assert main(["run", CATERPILLAR, "--cycles", "3", "--trace", str(outside)]) == 2
    assert "does not exist" in capsys.readouterr().err and not outside.parent.exists()
    image = Path("missing") / "dir" / "x.img"
    assert main(["image", CATERPILLAR, "-o", str(image)]) == 0
    assert image.exists()
    capsys.readouterr()
    trace = Path("new") / "t.jsonl"
    assert main(["run", CATERPILLAR, "--cycles", "3", "--trace", str(trace)]) == 0
    assert len(trace.read_text().splitlines()) == 3 * 8
    capsys.readouterr()
    assert main(["run", CATERPILLAR, "--cycles", "3", "--trace", "-"]) == 0
    out, err = capsys.readouterr()
    assert len(out.splitlines()) == 3 * 8 and all(line.startswith("{") for line in out.splitlines())
    assert "caterpillar on snake:8" in err  # the summary keeps out of the trace's way
    assert main(["image", CATERPILLAR, "-o", "-"]) == 0
    out, err = capsys.readouterr()
    assert out == image.read_text() and "sha256" in err
    assert not (Path.cwd() / "-").exists()


def test_check_warns_about_angles_and_missing_natives(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    prog = tmp_path / "warn.dh2"
    prog.write_text(
        "program w\nconst ClockCycle = 4\nconst Big = 700\nnative zap()\n"
        "receptor r when true { DOF1(Big + 20); DOF2(-45); zap() }\n"
    )
    assert main(["check", str(prog)]) == 0  # warnings do not fail the check
    err = capsys.readouterr().err
    assert f"{prog}:4:8: warning: native zap" in err
    assert f"{prog}:5:24: warning: receptor r sets DOF1 to 720 degrees" in err
    assert "DOF2" not in err


def test_the_console_script_prints_no_traceback() -> None:
    exe = Path(sys.executable).with_name("dh2rt")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "dh2rt"]
    proc = subprocess.run(
        [*cmd, "run", CATERPILLAR, "--event", "0:cut:m0.front"], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and "m0.front" in proc.stderr


def test_python_api_names_unknown_connectors() -> None:
    with pytest.raises(TopologyError, match=r"unknown connector 'fornt' \(profile conro: front, back"):
        CONRO.connector_index("fornt")


def test_long_source_lines_are_shown_around_the_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    prog = tmp_path / "long.dh2"
    # 200 operators (800 characters on the line): within the bound on operators per expression
    prog.write_text("program p\nconst ClockCycle = 4\nconst X = " + "1 + " * 200 + "?\n")
    assert main(["check", str(prog)]) == 2
    err = capsys.readouterr().err
    source, caret = err.splitlines()[1:3]
    assert len(source) < 120 and source.strip().startswith("...")
    assert source[caret.index("^")] == "?"  # the caret still points at the culprit


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--transport", "inproc", "--frame-loss", "0.1"], ["--frame-loss 0.1", "serial link emulator"]),
        (["--transport", "serial", "--bit-error", "2"], ["--bit-error 2.0", "probability"]),
        (["--transport", "inproc", "--cycles", "50", "--event", "80:kill:m1"], ["80:kill:m1", "last cycle is 49"]),
        (["--transport", "inproc", "--event", "5:cut:m0.front", "--cycles", "20"], ["5:cut:m0.front", "nothing"]),
        (["--transport", "inproc", "--cycle-ms", "nan"], ["--cycle-ms", "'nan'", "at most 60000"]),
        (["--transport", "inproc", "--cycle-ms", "inf"], ["--cycle-ms", "'inf'"]),
        (["--transport", "inproc", "--cycle-ms", "1e12"], ["--cycle-ms", "'1e12'"]),
        (["--transport", "inproc", "--cycle-ms", "0"], ["--cycle-ms", "more than 0"]),
        (["--transport", "inproc", "--module-count", "100000"], ["--module-count", "100000", "at most"]),
        (["--transport", "inproc", "--topology", "snake:100000"], ["--topology snake:100000", "at most"]),
        (["--transport", "inproc", "--frame-loss", "nan"], ["--frame-loss nan", "probability"]),
        (["--transport", "inproc", "--silence-cycles", "0"], ["--silence-cycles", "1..10000"]),
        (["--transport", "inproc", "--sensor-every", "-3"], ["--sensor-every"]),
        (["--transport", "can", "-i", "virtual", "-c", "x", "--bitrate", "nan"], ["--bitrate", "'nan'"]),
        (["--transport", "inproc", "--trace", "{tmp}"], ["--trace", "folder"]),
        (["--transport", "inproc", "--trace", "/proc/no-such-dir/t.jsonl"], ["--trace", "does not exist"]),
        (["--transport", "inproc", "--trace", "/proc/t.jsonl"], ["--trace", "/proc/t.jsonl"]),
        (["--transport", "inproc", "--trace", "{tmp}/t.txt"], ["--trace", ".jsonl"]),
        (["--transport", "inproc", "--log", "/proc/no-such-dir/run.log"], ["--log", "does not exist"]),
    ],
)
def test_launcher_careless_input(
    argv: list[str], words: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Refused before any work starts: no module, no world (the run would take seconds)."""
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    started = time.monotonic()
    assert main(argv) == 2
    assert time.monotonic() - started < 10
    err = capsys.readouterr().err
    for word in words:
        assert word in err, (word, err)
    assert "Traceback" not in err
