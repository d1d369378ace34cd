"""The caterpillar with one OS process per module, over real links, against the in-process Robot.

Each module process keeps its own clock and cycle count, so HIL traces are compared with the
Robot's by order, not by cycle: module k must receive the same sequence of hormones as in
the Robot run (same program, topology and seed), each after module k-1 got (or, for the
head, sent) the matching one, and set Table I's angle for it. Trace records carry ``t``
(CLOCK_MONOTONIC, one clock for every process on the machine).
"""

from __future__ import annotations

import itertools
import json
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from dh2rt.compiler import compile_file
from dh2rt.events import parse_event
from dh2rt.robot import Robot
from dh2rt.runtime import SILENCE_CYCLES
from dh2rt.topology import parse_spec
from hil.netns import namespace_problem
from hil.pace import ALLOWANCE_FLOOR_S, PACE, Baseline
from hil.world import World, module_pids
from tests.hil.holds import assert_no_module_held_itself

ROOT = Path(__file__).resolve().parents[2]
PROGRAM = ROOT / "examples" / "caterpillar.dh2"
TABLE_I = {"A": -45.0, "B": -45.0, "C": 45.0, "D": 45.0}
NEXT = {"A": "B", "B": "C", "C": "D", "D": "A"}
N = 8
PERIOD_MS = 20


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


def launch(transport: str, cycles: int, tmp_path: Path, *extra: str) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Run the launcher as a subprocess; its JSON summary and merged trace.

    These tests are about links and liveness: the modules record their angles (the physics
    body, the launcher's default, is tested in test_launcher.py)."""
    trace = tmp_path / f"{transport}.jsonl"
    cmd = [
        sys.executable, "-m", "hil.launcher", "--transport", transport, "--module-count", str(N),
        "--cycles", str(cycles), "--cycle-ms", str(PERIOD_MS), "--trace", str(trace), "--json",
        "--stand-in", "recording", *extra,
    ]  # fmt: skip
    proc = PACE.run(cmd, text=True, timeout=90, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr + proc.stdout[-2000:]
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    records = [json.loads(line) for line in trace.read_text().splitlines()]
    return summary, records


def robot_receptions(cycles: int, seed: int = 0) -> dict[int, list[str]]:
    program = compile_file(str(PROGRAM))
    robot = Robot(program, parse_spec(f"snake:{N}"), seed=seed, record=True)
    robot.run(cycles)
    got: dict[int, list[str]] = {m: [] for m in range(N)}
    for rec in robot.records:
        got[rec.module].extend(a.hormone.content() for a in rec.received)
    return got


def steady(records: list[dict[str, Any]], period: float) -> list[dict[str, Any]]:
    """Records before any module stopped (modules finish their cycles at slightly different
    times and their neighbours then see silence)."""
    last: dict[int, float] = {}
    for r in records:
        last[r["module"]] = max(last.get(r["module"], 0.0), r["t"])
    cutoff = min(last.values()) - (SILENCE_CYCLES + 1) * period
    return [r for r in records if r["t"] <= cutoff]


def receptions(records: list[dict[str, Any]], module: int) -> list[dict[str, Any]]:
    out = []
    for r in records:
        if r["module"] == module:
            for a in r["received"]:
                out.append({"hormone": a["hormone"], "at": a["at"], "t": r["t"], "DOF1": r["actuators"]["DOF1"]})
    return out


def emissions(records: list[dict[str, Any]], module: int) -> list[dict[str, Any]]:
    return [{"hormone": s["hormone"], "t": r["t"]} for r in records if r["module"] == module for s in r["sent"]]


def check_wave_matches_robot(
    records: list[dict[str, Any]], cycles: int, summary: dict[str, Any], timer: Baseline
) -> None:
    period = PACE.ms(PERIOD_MS) / 1000
    slack = clock_read_slack(summary, timer)
    records = steady(records, period)
    reference = robot_receptions(cycles + 40)
    for k in range(1, N):
        got = receptions(records, k)
        seq = [g["hormone"] for g in got]
        assert len(seq) >= 4, f"module {k} got only {seq}"
        assert seq == reference[k][: len(seq)], f"module {k}: {seq} vs Robot {reference[k][: len(seq)]}"
        for g in got:
            assert g["at"] == "front"
            assert g["DOF1"] == TABLE_I[g["hormone"][2]], g  # Table I's angle for what it got
        # per-hop order: module k acts on hop i after module k-1 did, and before module k-1's
        # next hop (a quarter ClockCycle later), so no hop is skipped or taken out of turn.
        # Hop latency itself is measured in benchmarks/bench_hil.py, not asserted here.
        before = emissions(records, 0) if k == 1 else receptions(records, k - 1)
        quarter = caterpillar_quarter() * period
        for i, g in enumerate(got):
            # `t` is each process's cycle-start clock read, taken before it reads what arrived:
            # a module held off the processor between the two reads gets a hop sent after its `t`
            assert g["t"] > before[i]["t"] - slack[k], (
                f"module {k} hop {i} came {before[i]['t'] - g['t']:.4f} s before its predecessor's "
                f"(allowed {slack[k]:.4f} s)"
            )
            assert g["t"] - before[i]["t"] < quarter, f"module {k} hop {i} took {g['t'] - before[i]['t']:.3f} s"


def clock_read_slack(summary: dict[str, Any], timer: Baseline) -> dict[int, float]:
    """Per module, how far (s) its cycle-start clock read may come before a hop it took in that
    cycle was sent: as long as the machine held it off the processor between that read and
    reading its links. Bounded by the longest it was held at a cycle start in this run (its
    worst lateness, measured by the module), plus a millisecond; never less than a bare
    loop's allowance (hil.pace)."""
    out = {}
    for row in summary["modules"]:
        worst_ms = float((row.get("lateness_ms") or {}).get("max", 0.0))
        out[int(row["module"])] = max(timer.allowance_s(), ALLOWANCE_FLOOR_S + worst_ms / 1000)
    return out


def caterpillar_quarter() -> int:
    """Cycles between two hormones from the head: a quarter of the caterpillar's ClockCycle."""
    return compile_file(str(ROOT / "examples" / "caterpillar.dh2")).clock_cycle // 4


def check_clean_links(summary: dict[str, Any]) -> None:
    for row in summary["modules"]:
        c = row["counters"]
        assert row["state"] == "done", row
        assert c["frames_dropped"] == 0 and c["frames_corrupted"] == 0, row
        assert c["beacons_missed"] == 0, row  # no keep-alive lost on any link
        assert c["refused"] == 0 and c["engine_faults"] == 0, row


#: Runs a wave test may take when the machine held a module past its liveness bound
WAVE_ATTEMPTS = 3


def launch_unheld(transport: str, cycles: int, tmp_path: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """A run in which no link was lost. A run that lost one is judged (tests/hil/holds.py): the
    module's own work must not have held it, and the machine's holds must explain the loss;
    then the robot legitimately split for a moment, the wave is not the in-process one, and
    the run is made again (at most WAVE_ATTEMPTS runs, then the test fails)."""
    held: list[dict[str, float]] = []
    for _ in range(WAVE_ATTEMPTS):
        summary, records = launch(transport, cycles, tmp_path)
        if not any(r["counters"]["links_lost"] for r in summary["modules"]):
            return summary, records
        assert_no_module_held_itself(summary)
        held.append({r["name"]: (r["lateness_ms"] or {}).get("max", 0.0) for r in summary["modules"]})
    pytest.fail(f"a link lost in each of {WAVE_ATTEMPTS} runs, each time with a module held by the machine: {held}")


def test_serial_processes_reproduce_the_robot_wave(tmp_path: Path, timer_baseline: Baseline) -> None:
    summary, records = launch_unheld("serial", 150, tmp_path)
    check_clean_links(summary)
    check_wave_matches_robot(records, 150, summary, timer_baseline)


def test_udp_processes_reproduce_the_robot_wave(tmp_path: Path, timer_baseline: Baseline) -> None:
    problem = namespace_problem()
    if problem is not None:
        pytest.skip(f"udp_multicast runs only in a private network namespace: {problem}")
    # the launcher re-executes itself (and so every module process) under unshare -rn
    summary, records = launch_unheld("udp", 150, tmp_path)
    check_clean_links(summary)
    check_wave_matches_robot(records, 150, summary, timer_baseline)


def test_killed_module_splits_the_snake_in_two(tmp_path: Path) -> None:
    summary, records = launch("serial", 160, tmp_path, "--event", "60:kill:m3")
    period = PACE.ms(PERIOD_MS) / 1000
    (kill,) = summary["events"]
    t_kill = kill["t"]
    states = {row["name"]: row["state"] for row in summary["modules"]}
    assert states["m3"] == "killed" and all(s == "done" for n, s in states.items() if n != "m3")
    bound = (SILENCE_CYCLES + 1) * period + 3 * period  # the documented bound plus scheduling slack
    for module, conn in ((2, "back"), (4, "front")):
        fell = [r["t"] for r in records if r["module"] == module and r["t"] > t_kill and r["status"][conn] == "0"]
        assert fell, f"m{module}.{conn} never fell to 0"
        assert fell[0] - t_kill <= bound, f"m{module}.{conn} fell {fell[0] - t_kill:.3f} s after the kill"
    after = steady([r for r in records if r["t"] > t_kill + bound], period)
    # the front half: m2 is its tail and still gets the head's wave
    assert {r["T"] for r in after if r["module"] == 2} == {2}
    assert len(receptions(after, 2)) >= 3
    # the back half: m4 is a head and starts its own wave, which m5..m7 carry in order
    assert {r["T"] for r in after if r["module"] == 4} == {1}
    sent = [e["hormone"] for e in emissions(after, 4)]
    assert len(sent) >= 3
    for k in (5, 6, 7):
        got = receptions(after, k)
        assert len(got) >= 2, f"m{k} got nothing from the new head"
        for prev, nxt in itertools.pairwise(got):
            assert nxt["hormone"][2] == NEXT[prev["hormone"][2]], f"m{k}: {prev} then {nxt}"


@pytest.mark.realtime
def test_impaired_serial_links_never_feed_a_corrupted_hormone_and_recover() -> None:
    program = compile_file(str(PROGRAM))
    topology = parse_spec(f"snake:{N}")
    period = PERIOD_MS / 1000
    world = World(
        program, topology, "serial", cycle_period=period, cycles=260, trace=True,
        frame_loss=0.05, bit_error=0.0005, emulator_seed=7, stand_in="recording",
    )  # fmt: skip
    try:
        world.start()
        while world.cycle < 130:
            world.tick()
            time.sleep(0.02)
        assert world.emulator is not None
        for link_id in world.links:
            world.emulator.set_impairments(link_id, frame_loss=0.0, bit_error=0.0)
        t_clean = time.monotonic()
        stats = [world.emulator.stats(link_id) for link_id in world.links]
        deadline = time.monotonic() + 30
        while not world.done() and time.monotonic() < deadline:
            world.tick()
            time.sleep(0.02)
        assert world.done()
        pids = module_pids(world)
    finally:
        world.stop()
    for pid in pids:
        assert not Path(f"/proc/{pid}").exists() or "zombie" in Path(f"/proc/{pid}/status").read_text().lower()
    rows = world.rows()
    assert all(r["state"] == "done" for r in rows), rows
    # the medium lost and damaged frames; the modules counted what reached them
    assert sum(s.frames_lost for s in stats) > 0 and sum(s.bits_flipped for s in stats) > 0
    assert sum(r["counters"]["frames_corrupted"] for r in rows) > 0
    assert sum(r["counters"]["beacons_missed"] for r in rows) > 0
    records = world.sorted_records()
    # every hormone an engine received is one its neighbour sent, in order
    for k in range(1, N):
        got = [g["hormone"] for g in receptions(records, k)]
        sent = iter(e["hormone"] for e in emissions(records, k - 1))
        assert all(any(h == s for s in sent) for h in got), f"m{k} received a hormone m{k - 1} never sent"
    # once the faults stop, the wave runs whole again: no phase skipped anywhere
    settled = steady([r for r in records if r["t"] > t_clean + (SILENCE_CYCLES + 3) * period], period)
    for k in range(1, N):
        got = receptions(settled, k)
        assert len(got) >= 4, f"m{k} got {len(got)} hormones after recovery"
        for prev, nxt in itertools.pairwise(got):
            assert nxt["hormone"][2] == NEXT[prev["hormone"][2]], f"m{k}: {prev} then {nxt}"
            assert nxt["DOF1"] == TABLE_I[nxt["hormone"][2]]


#: Cycles from a dock on a bus to a verified link: the negotiation's 8, a Hello, and the
#: contact's debounce and the scheduling of threads on a busy machine.
NEGOTIATION_CYCLES = 16
#: Cycles from a cut to a released link: the contact's debounce (20 ms) and the scheduling.
CUT_CYCLES = 8


@pytest.mark.realtime
def test_world_events_change_links() -> None:
    """cut, dock and inject over CAN-style link ids (python-can virtual, modules as threads)."""
    program = compile_file(str(PROGRAM))
    topology = parse_spec("snake:3")
    period = 0.01
    events = [
        parse_event(text, topology, program.vocabulary)
        for text in ("20:cut:m1.back", "50:dock:m1.back-m2.front", "70:inject:m2:X(C)")
    ]
    world = World(program, topology, "virtual", cycle_period=period, cycles=110, trace=True, stand_in="recording")
    try:
        world.start()
        applied: set[int] = set()
        deadline = time.monotonic() + 20
        while not world.done() and time.monotonic() < deadline:
            world.run_events(events, applied)
            world.tick()
            time.sleep(0.005)
    finally:
        world.stop()
    assert applied == {0, 1, 2}
    times = dict(world.event_times)
    records = world.sorted_records()

    def types(module: int, start: float, end: float, settle: int = 3) -> set[int]:
        return {r["T"] for r in records if r["module"] == module and start + settle * period < r["t"] < end}

    t_cut, t_dock, t_inject = times["20:cut:m1.back"], times["50:dock:m1.back-m2.front"], times["70:inject:m2:X(C)"]
    # alone after the cut: a head, once it sensed the contact broken (debounced) and let go
    assert types(2, t_cut, t_dock, settle=CUT_CYCLES) == {1}
    # docked again: the tail, once the pair has negotiated a link over its connectors'
    # channels (8 cycles without loss, docs/link-layer.md) and verified each other's Hello
    assert types(2, t_dock, t_inject, settle=NEGOTIATION_CYCLES) == {2}
    became_tail = min(r["t"] for r in records if r["module"] == 2 and r["t"] > t_dock and r["T"] == 2)
    assert became_tail - t_dock < NEGOTIATION_CYCLES * period
    injected = [r for r in records if r["module"] == 2 and r["t"] >= t_inject for a in r["received"] if a["at"] is None]
    assert injected and injected[0]["received"][0]["hormone"] == "X(C)"
    assert injected[0]["actuators"]["DOF1"] == TABLE_I["C"]
