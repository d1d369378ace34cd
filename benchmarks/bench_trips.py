"""A released foot's trip to the tail and its dock, with and without the diagonal.

One round of legs to snake in physics, driven from Python as
tests/sim/test_foot_to_tail_physics.py does: the dragon holds still, a foot lets go of the
spine, comes to tail4's back by its own gaits (firmware.motion.crawl.Trip) and docks by motion. For each
foot and seed, the same world twice in the same run: today's trip, which starts across
``DIAGONAL_M`` before the end of its line and backs diagonally past the face, and the same
trip without the diagonal (``diagonal_m = 0``: along its line to the end, then across, as
the trip before it did; its other rules are today's).
Reported: how many docked, the cycles from the release to the latch (median and range), and
the cycles the feet turned in place (the finished trips' accounts, ``PhysicsRun.docking.trips_done``).

    python -m benchmarks.bench_trips [--seeds 0,1,2,3,4,5] [--legs left_leg0,...] [--jobs 2] [--quick]

The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from collections.abc import Sequence
from typing import Any

from benchmarks import jobs_arg, run_variants, seeds_arg, strict_json
from dh2rt.compiler import compile_source
from dh2rt.profile import CONRO
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from firmware.motion.crawl import DIAGONAL_M
from sim.runner import PhysicsRun

FEET = ("left_leg0", "right_leg0", "left_leg1", "right_leg1")
#: Cycles after the release a round may take (a trip's budget is 2,500, a dock 400, and a
#: trip or a dock that gives up sends the foot round again).
ROUND_CYCLES = 3200


def one_round(seed: int, leg: str, diagonal_m: float) -> dict[str, Any]:
    """Release ``leg`` and bring it to tail4's back; what happened."""
    still = compile_source("program still\nconst ClockCycle = 40\n")
    dragon = parse_spec("dragon")
    run = PhysicsRun(Robot(still, dragon, seed=seed))
    run.docking.options.trip_diagonal_m = diagonal_m
    front, back = CONRO.connector_index("front"), CONRO.connector_index("back")
    foot, tail = dragon.names.index(leg), dragon.names.index("tail4")
    try:
        for _ in range(10):
            run.cycle()
        cycles = run.bring_home(foot, (tail, back), (front, front), ROUND_CYCLES)
        docked = run.robot.peer_of((tail, back)) == (foot, front)
        turning = sum(n for trip in run.docking.trips_done for n in trip.turning.values())
        return {"seed": seed, "leg": leg, "docked": docked, "cycles": cycles, "turning": turning}
    finally:
        run.close()


def summary(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    done = [r for r in rounds if r["docked"]]
    cycles = [r["cycles"] for r in done]
    return {
        "docked": len(done),
        "rounds": len(rounds),
        "median_cycles": statistics.median(cycles) if cycles else None,
        "cycles_range": [min(cycles), max(cycles)] if cycles else None,
        "median_turning": statistics.median(r["turning"] for r in done) if done else None,
        "failed": [f"{r['leg']}@{r['seed']}" for r in rounds if not r["docked"]],
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="A released foot's trip to the tail, with and without the diagonal")
    parser.add_argument("--seeds", default="0,1,2,3,4,5", help="comma-separated seeds (default 0 to 5)")
    parser.add_argument("--legs", default=",".join(FEET), help="comma-separated feet (default all four)")
    parser.add_argument("--jobs", type=int, default=2, help="rounds run at once, one process each (default 2)")
    parser.add_argument("--quick", action="store_true", help="left_leg1, seed 0 (a smoke test)")
    args = parser.parse_args(argv)
    seeds = seeds_arg(parser, args.seeds)
    legs = args.legs.split(",")
    unknown = [leg for leg in legs if leg not in FEET]
    if unknown:
        parser.error(f"--legs: {', '.join(unknown)} not a foot of the dragon ({', '.join(FEET)})")
    jobs = jobs_arg(parser, args.jobs)
    if args.quick:
        seeds, legs = [0], ["left_leg1"]
    variants = {"diagonal": DIAGONAL_M, "to_the_end": 0.0}
    cases = [(name, one_round, (seed, leg, variants[name])) for name in variants for seed in seeds for leg in legs]
    print(f"{len(cases)} rounds, {jobs} at a time (one round: about 10 to 25 s on one core)", flush=True)

    def describe(name: str, r: dict[str, Any]) -> str:
        state = f"docked after {r['cycles']} cycles" if r["docked"] else "did not dock"
        return f"{name:10} {r['leg']:10} seed {r['seed']}: {state}"

    results = run_variants(jobs, cases, describe)
    if results is None:
        print("interrupted", file=sys.stderr)
        return 130
    out: dict[str, Any] = {"bench": "trips", "seeds": seeds, "legs": legs}
    for name in variants:
        s = summary(results[name])
        out[name] = s
        print(
            f"{name:10} docked {s['docked']}/{s['rounds']}, cycles median {s['median_cycles']} "
            f"(range {s['cycles_range']}), turning median {s['median_turning']}, failed {s['failed'] or 'none'}"
        )
    now, before = out["diagonal"]["median_cycles"], out["to_the_end"]["median_cycles"]
    out["median_cycles_ratio"] = round(now / before, 3) if now and before else None
    print(f"median cycles, diagonal / to the end: {out['median_cycles_ratio']}")
    print(json.dumps(strict_json(out)))
    return 0 if out["diagonal"]["docked"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
