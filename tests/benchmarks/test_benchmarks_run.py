"""Every benchmark runs (quick mode) and ends with one JSON object, as docs/figures.md promises."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.marks import LONG

ROOT = Path(__file__).resolve().parents[2]
NAMES = sorted(p.stem for p in (ROOT / "benchmarks").glob("bench_*.py"))
#: benchmarks whose quick run runs modules in real time: make test runs them in the realtime group
REALTIME = {"bench_flash", "bench_footprint", "bench_hil", "bench_hil_reach", "bench_sense_latency",
            "bench_sensor_push", "bench_servo"}  # fmt: skip
#: quick runs of what other tests cover (the footprint's figures: the test below; the loop's
#: modules, sensors and servos: tests/hil, tests/firmware), half a minute or more each, or real
#: time that make test keeps for the loop tests themselves: make test-long runs them
LONG_RUNS = {"bench_footprint", "bench_hil_reach", "bench_legs_to_snake", "bench_trips", "bench_hil",
             "bench_sense_latency", "bench_sensor_push", "bench_servo"}  # fmt: skip


def quick_runs() -> list[object]:
    """Each benchmark's name, marked realtime and long as the sets above say."""
    marks = ((pytest.mark.realtime, REALTIME), (LONG, LONG_RUNS))
    return [pytest.param(name, marks=[mark for mark, names in marks if name in names]) for name in NAMES]


@pytest.mark.parametrize("name", quick_runs())
def test_benchmark_quick_mode_ends_with_json(name: str) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", f"benchmarks.{name}", "--quick"], capture_output=True, text=True, cwd=ROOT, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    last = proc.stdout.strip().splitlines()[-1]
    data = json.loads(last)
    assert isinstance(data, dict) and data


def test_runner_help() -> None:
    proc = subprocess.run([sys.executable, "-m", "benchmarks", "--help"], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0 and "usage: python -m benchmarks" in proc.stdout


def test_decode_benchmark_reports_its_ratios_and_bus_hours() -> None:
    """Issue 12: dump against python-can's LogReader on the same files, in the same run (the
    figures themselves are not asserted: timing belongs to the benchmark, not the tests)."""
    cmd = [sys.executable, "-m", "benchmarks.bench_decode", "--quick"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    data = json.loads(proc.stdout.strip().splitlines()[-1])
    assert data["frames"] == 20_000 and {"hormone", "keepalive", "hello", "segment", "error"} <= set(data["kinds"])
    for fmt in ("log", "blf"):
        assert data[f"dump_vs_read_{fmt}"] > 0 and data[f"read_{fmt}_frames_per_s"] > 0
    for fmt in ("log", "blf", "pcapng"):
        assert data[f"dump_{fmt}_frames_per_s"] > 0 and data[f"dump_{fmt}_bus_hours_per_min"] > 0


@pytest.mark.realtime
def test_footprint_benchmark_reports_each_figure_against_its_bare_loop() -> None:
    """Issue 10: 8 dh2rt modules on serial links against 8 bare pyserial loops in the same run;
    every figure with its baseline, ratio and target verdict (the figures are not asserted)."""
    cmd = [sys.executable, "-m", "benchmarks.bench_footprint", "--quick", "--only", "serial"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    data = json.loads(proc.stdout.strip().splitlines()[-1])
    serial = data["transports"][0]
    assert serial["transport"] == "serial" and set(data["met"]["serial"]) == set(data["targets"])
    for key in ("rss_mb", "cpu_percent", "cpu_ms_per_cycle", "lateness_p99_ms", "first_cycle_s"):
        for who in ("dh2rt", "baseline"):
            assert serial[who][key]["max"] >= serial[who][key]["median"] > 0, (who, key)
        assert serial["ratio"][key]["median"] > 0
    assert serial["dh2rt"]["checks"]["types"] == ["head"] + ["body"] * 6 + ["tail"]
    assert all(serial[who]["checks"]["frames_received_min"] > 0 for who in ("dh2rt", "baseline"))


@pytest.mark.parametrize(
    ("args", "names"),
    [
        (["--legs", "left_leg0,tail4"], "--legs: tail4 not a foot"),
        (["--seeds", "0,x"], "--seeds: expected"),
        (["--jobs", "0"], "--jobs"),
    ],
)
def test_trips_benchmark_refuses_bad_arguments_with_a_usage_error(args: list[str], names: str) -> None:
    """A field given wrong is named, and the exit is argparse's 2, before any world is built."""
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.bench_trips", *args], capture_output=True, text=True, cwd=ROOT, timeout=60
    )
    assert proc.returncode == 2 and names in proc.stderr, proc.stderr[-500:]
    assert proc.stdout == ""


def test_trips_benchmark_help() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.bench_trips", "--help"], capture_output=True, text=True, cwd=ROOT, timeout=60
    )
    assert proc.returncode == 0 and "--seeds" in proc.stdout and "diagonal" in proc.stdout


@pytest.mark.parametrize(
    ("args", "names"),
    [
        (["--kills", "none,late"], "--kills: late not one of none, trip, dock"),
        (["--seeds", "1;2"], "--seeds: expected"),
        (["--jobs", "-1"], "--jobs"),
        (["--tracker", "1,2,3"], "--tracker: four numbers"),
        (["--tracker", "1,2,3,1.5"], "dropout in [0, 1)"),
        (["--variants", "straight"], "--variants: each one of free_distance, standoff"),
    ],
)
def test_legs_to_snake_benchmark_refuses_bad_arguments_with_a_usage_error(args: list[str], names: str) -> None:
    assert_usage_error("bench_legs_to_snake", args, names)


def assert_usage_error(bench: str, args: list[str], names: str) -> None:
    """``benchmarks.<bench> args`` exits 2 naming ``names`` on stderr, and prints nothing else."""
    proc = subprocess.run(
        [sys.executable, "-m", f"benchmarks.{bench}", *args], capture_output=True, text=True, cwd=ROOT, timeout=60
    )
    assert proc.returncode == 2 and names in proc.stderr, proc.stderr[-500:]
    assert proc.stdout == ""


def test_legs_to_snake_benchmark_help() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.bench_legs_to_snake", "--help"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )
    assert proc.returncode == 0 and "--kills" in proc.stdout and "free_distance" in proc.stdout


def test_footprint_baseline_loop_compiles_and_cycles(tmp_path: Path) -> None:
    """The footprint benchmark's bare loop (benchmarks/bare_loop.py) is a program of its own,
    which the linters see: it compiles, imports nothing of dh2rt, cycles and writes its status."""
    import time

    from benchmarks.bench_footprint import Child

    script = ROOT / "benchmarks" / "bare_loop.py"
    source = script.read_text()
    compile(source, str(script), "exec")
    imports = [line for line in source.splitlines() if line.lstrip().startswith(("import ", "from "))]
    assert imports and not any("dh2rt" in line for line in imports)
    status = tmp_path / "status.json"
    spec = {"kind": "serial", "period": 0.01, "status": str(status), "status_every": 5, "ports": [],
            "edges_ms": [1.0, 10.0]}  # fmt: skip
    loop = Child("b0", [sys.executable, str(script), json.dumps(spec)], status, tmp_path / "log.txt")
    loop.spawn()
    try:
        deadline = time.monotonic() + 30
        while loop.read_status() is None and loop.alive() and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        code = loop.stop()
    assert code == 0, (tmp_path / "log.txt").read_text()[-2000:]
    final = loop.read_status()
    assert final is not None and final["final"] and final["cycle"] >= 5
    assert sum(final["lateness_hist"]["counts"]) == final["cycle"]


@pytest.mark.parametrize(
    ("args", "names"),
    [
        (["--arms", "modules,robot"], "--arms: each one of world, modules"),
        (["--only", "t,snake"], "--only: each one of"),
        (["--kills", "late"], "--kills: each one of none, trip, dock"),
    ],
)
def test_motions_in_modules_benchmark_refuses_bad_arguments_with_a_usage_error(args: list[str], names: str) -> None:
    assert_usage_error("bench_motions_in_modules", args, names)
