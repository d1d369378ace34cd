"""Flashing a running robot in the loop: 8 module processes on serial links run the
caterpillar, a signed image with another ClockCycle comes in through a programming cable on
the head's free front connector mid-run, and every module switches to it.

What the tests read is what the modules say: their trace records (``t`` on CLOCK_MONOTONIC,
one clock for every process), their log lines, their status, and the flasher's report. One
rollout per seed is run once (a module-scoped fixture) and read by several tests:

- what must hold on any machine: every module commits version 2 and confirms it after its
  trial, the report names each by its path from the cable, the head's wave goes on at the new
  period, and every module sets Table I's angle for what it receives;
- what needs a machine that keeps real time (``realtime``, skipped here with the figures):
  one agreed switch cycle for all 8, and Table I's order hop by hop within HOP periods.
"""

from __future__ import annotations

import itertools
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any

import pytest

from dh2rt.compiler import compile_file
from dh2rt.signed_image import pack
from dh2rt.topology import parse_spec
from dh2rt.wire.transfer import Outcome
from firmware.flash.cable import FlashResult
from hil.link_emulator import held_within
from hil.pace import Baseline
from hil.world import World, module_pids
from tests.hil.flashing import PERIOD, PROGRAM, caterpillar, flash_through_cable, run_world, switch_timing, switches
from tests.hil.processes import alive
from tests.marks import sweep

TABLE_I = {"A": -45.0, "B": -45.0, "C": 45.0, "D": 45.0}
NEXT = {"A": "B", "B": "C", "C": "D", "D": "A"}
ORDER = "ABCD"  # the body receptors' order in the program: the last one that fires sets DOF1
N = 8
HOP = 3  # periods a hormone may take over one serial hop
AFTER = 150  # cycles every module runs the new program before the run ends
WAIT = 240.0  # seconds the rollout and the confirmations may take on a loaded machine


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


def settled(world: World) -> bool:
    """Every module switched, confirmed version 2 and ran AFTER cycles on it."""
    switched = switches(world.log)
    if len(switched) < N:
        return False
    for v in world.views:
        program = v.status.get("program", {})
        if program.get("version") != 2 or program.get("trial", True):
            return False
        if int(v.status.get("cycle", 0)) < switched[v.module] + AFTER:
            return False
    return True


def run_until_confirmed(world: World) -> None:
    deadline = time.monotonic() + WAIT
    while time.monotonic() < deadline and not world.done() and not settled(world):
        world.tick()
        time.sleep(0.01)


@dataclass
class Run:
    """One rollout, as the modules and the flasher reported it."""

    seed: int
    result: FlashResult
    switched: dict[int, int]
    records: list[dict[str, Any]]
    statuses: list[dict[str, Any]]
    log: list[str]
    go_at: float
    pids: list[int]
    #: when the machine held the link emulator's relay, and how long: (ended, seconds)
    relay_holds: list[tuple[float, float]]


@pytest.fixture(scope="module", params=sweep([0, 3]), ids=["seed0", "seed3"])
def rollout(request: pytest.FixtureRequest) -> Run:
    seed = int(request.param)
    old, new = compile_file(str(PROGRAM)), caterpillar(20)
    world = World(old, parse_spec(f"snake:{N}"), "serial", seed=seed, cycle_period=PERIOD, cycles=100_000,
                  trace=True, stand_in="recording")  # fmt: skip
    try:
        world.start()
        run_world(world, 60)
        assert world.signer is not None
        result = flash_through_cable(world, 0, pack(new.image, 2, world.signer))
        run_until_confirmed(world)
        statuses = [dict(v.status) for v in world.views]
        go_at = world.go_at
        assert go_at is not None and world.emulator is not None
        holds = world.emulator.holds()
    finally:
        world.stop()
    return Run(seed, result, switches(world.log), list(world.records), statuses, list(world.log), go_at,
               list(module_pids(world)), holds)  # fmt: skip


def test_every_module_commits_and_is_named_by_its_path(rollout: Run) -> None:
    result = rollout.result
    assert result.succeeded, (result.failure, [m.describe() for m in result.modules], rollout.log[-40:])
    report = {m.path: m for m in result.modules}
    # every module named by its path from the cable: front>front ... one hop further each
    assert sorted(len(p) for p in report) == list(range(1, N + 1))
    assert all(m.outcome in (Outcome.COMMITTED, Outcome.CONFIRMED) and m.version == 2 for m in report.values())
    assert sorted(rollout.switched) == list(range(N)), rollout.log[-40:]
    for i, status in enumerate(rollout.statuses):
        program = status.get("program", {})
        assert program.get("version") == 2 and not program.get("trial"), (i, program)
        assert int(status.get("cycle", 0)) >= rollout.switched[i] + AFTER, (i, status.get("cycle"))
    assert not any(alive(p) for p in rollout.pids)


def head_emissions(records: list[dict[str, Any]]) -> list[int]:
    return [r["cycle"] for r in sorted(records, key=lambda r: r["cycle"]) if r["module"] == 0 and r["sent"]]


def test_the_wave_goes_on_at_the_new_period(rollout: Run) -> None:
    """The head emits every ClockCycle/4 cycles of its own count: 10 before the switch, 5
    after (a cycle the loaded machine skipped makes a multiple; most gaps are the period)."""
    emitted = head_emissions(rollout.records)
    switch = rollout.switched[0]
    # the pair across the switch may be any gap: the new program's timer starts where it starts
    before = [b - a for a, b in itertools.pairwise(emitted) if b < switch]
    after = [b - a for a, b in itertools.pairwise(emitted) if a >= switch]
    assert before and all(g % 10 == 0 for g in before), before
    assert len(after) > 20 and all(g % 5 == 0 for g in after), after
    assert Counter(after).most_common(1)[0][0] == 5, after
    assert Counter(before).most_common(1)[0][0] == 10, before


def test_every_module_sets_table_i_for_what_it_receives(rollout: Run) -> None:
    """After the switch each body module receives the wave and sets the angle Table I gives
    the phase it passes on; two hormones in one cycle: the receptor last in the program wins."""
    for m in range(1, N):
        mine = [r for r in rollout.records if r["module"] == m and r["cycle"] > rollout.switched[m]]
        got = [(r, [a["hormone"][2] for a in r["received"]]) for r in mine]
        got = [(r, phases) for r, phases in got if phases]
        assert len(got) > 20, (m, len(got))
        for r, phases in got:
            last = max(phases, key=ORDER.index)
            assert r["actuators"]["DOF1"] == TABLE_I[last], (m, r["cycle"], phases, r["actuators"])


@pytest.mark.realtime
def test_one_agreed_switch_cycle_and_table_i_hop_by_hop(rollout: Run, timer_baseline: Baseline) -> None:
    # one agreed instant: modules keep no common clock, so each switches at its own first cycle
    # boundary at or after it (or, held up by the machine, as soon as it has the image and the
    # instant); those boundaries lie within one period, plus however late a module's cycle began
    timing = switch_timing(rollout.log, [r for r in rollout.records if r.get("life", 0) == 0], N)
    assert timing.misplaced() == {}, (timing.misplaced(), timing.after())
    emitted = head_emissions(rollout.records)
    switch = rollout.switched[0]
    assert {b - a for a, b in itertools.pairwise(emitted) if b < switch} == {10}
    assert {b - a for a, b in itertools.pairwise(emitted) if a >= switch} == {5}
    records = rollout.records
    for m in range(1, N):
        mine = sorted((r for r in records if r["module"] == m and r["cycle"] > rollout.switched[m]),
                      key=lambda r: r["cycle"])  # fmt: skip
        got = [(r, a["hormone"][2]) for r in mine for a in r["received"]]
        phases = [p for _, p in got]
        assert all(NEXT[p] == q for p, q in itertools.pairwise(phases)), (m, phases)
        # one hop behind the module before it: the phase m got, the head sent (m = 1) or
        # m-1 passed on (the next of what m-1 got), less than HOP periods earlier
        if m == 1:
            upstream = [(r["t"], e["hormone"][2]) for r in records if r["module"] == 0 for e in r["sent"]]
        else:
            upstream = [(r["t"], NEXT[a["hormone"][2]]) for r in records if r["module"] == m - 1
                        for a in r["received"]]  # fmt: skip
        # plus as long as the machine held either end back (their worst lateness in this run,
        # or a bare loop's allowance): a module started late reads its link late; and as long
        # as it held the link between them (the test bench's relay, which carries every byte)
        hop = HOP + max(timer_baseline.allowance_s(), worst_lateness_s(rollout, m - 1, m)) / PERIOD
        # a record's t is its cycle's start, and the module reads its links a little after it:
        # a receiver the machine held in between reads what the sender sent after that start
        # (a lag just below 0, by up to the bare loop's own jitter)
        early = -timer_baseline.allowance_s() / PERIOD
        for r, p in got:
            crossings = [(t, round((r["t"] - t) / PERIOD, 2)) for t, q in upstream
                         if q == p and abs(r["t"] - t) < 10 * PERIOD]  # fmt: skip
            allowed = [round(hop + held_within(rollout.relay_holds, t, r["t"]) / PERIOD, 2) for t, _ in crossings]
            lags = [lag for _, lag in crossings]
            assert any(early < lag < limit for lag, limit in zip(lags, allowed, strict=True)), (
                m, r["cycle"], p, "lags in periods:", lags, "allowed", (early, allowed))  # fmt: skip


def worst_lateness_s(run: Run, *modules: int) -> float:
    """The latest any of ``modules`` started a cycle in the run (s), as each measured it."""
    return max(float((run.statuses[m].get("lateness_ms") or {}).get("max", 0.0)) for m in modules) / 1000
