"""The three reconfigurations in physics, the docking motions run by the world against run by
the modules themselves, in one sitting (issue 28's done-when).

Each case runs twice on the same seed: ``world``, the physics runner's own docking sequence
(``PhysicsRun.docking``, which plans every motion from what the modules sense); ``modules``,
every module's own ``firmware.motion.host.MotionHost`` over the robot's links
(``PhysicsRun(modules_move=True)``, sim.module_motions), the runner playing only physics,
links and sensors. Reported for each reconfiguration and arm: how many formed, the cycle
they formed at (median and range), the docks given up; and the ratio of the median cycles,
modules / world (the done-when asks at most 1.3).

- snake to T on snake:8, STT at m4, m0 or m7 (by seed); formed: m2 released its back;
- snake to quadruped on snake:9, QSS at m4; formed: the fifth release;
- legs to snake on the dragon, LTS at spine0 (benchmarks.bench_legs_to_snake's run), with
  each of ``--kills``.

    python -m benchmarks.bench_motions_in_modules [--seeds 0,1,2] [--kills none,trip,dock] [--jobs 2]
        [--only t,quadruped,legs_to_snake] [--arms world,modules] [--quick]

One legs to snake run is 60 to 120 s on one core, a quadruped 40 to 60 s, a T 3 s. The last
line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from benchmarks import jobs_arg, run_variants, seeds_arg, strict_json
from benchmarks.bench_legs_to_snake import one_run as legs_run
from dh2rt.compiler import compile_file
from dh2rt.events import parse_event
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from sim.legs_to_snake import KILLS
from sim.runner import PhysicsRun

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
ARMS = ("world", "modules")
RECONFIGURATIONS = ("t", "quadruped", "legs_to_snake")
#: (program, topology, hormone, where it is injected by seed, releases that mean formed, budget)
SETUPS = {
    "t": ("snake_to_t.dh2", "snake:8", "STT", ("m4", "m0", "m7"), 1, 1500),
    "quadruped": ("snake_to_quadruped.dh2", "snake:9", "QSS", ("m4",), 5, 8000),
}


def released_run(kind: str, seed: int, modules_move: bool) -> dict[str, Any]:
    """Snake to T or to quadruped: the cycle the last release came (None: not within budget)."""
    program_file, spec, hormone, places, releases, budget = SETUPS[kind]
    prog = compile_file(str(EXAMPLES / program_file))
    topo = parse_spec(spec)
    robot = Robot(prog, topo, seed=seed)
    run = PhysicsRun(robot, modules_move=modules_move)
    try:
        at = places[seed % len(places)]
        run.run(50)
        run.run(1, [parse_event(f"50:inject:{at}:{hormone}", topo, prog.vocabulary)])
        while sum(line.endswith("released") for line in robot.log) < releases and robot.cycle < budget:
            run.run(1)
        formed = robot.cycle if sum(line.endswith("released") for line in robot.log) >= releases else None
        gave_up = len(run.failed) + (run.module_motions.given_up() if run.module_motions else 0)
        return {"seed": seed, "kill": "none", "formed": formed, "gave_up": gave_up, "latches": len(run.contacts)}
    finally:
        run.close()


def one_case(kind: str, seed: int, kill: str, modules_move: bool) -> dict[str, Any]:
    if kind == "legs_to_snake":
        r = legs_run(seed, kill, (True, None), modules_move=modules_move)
        return {
            "seed": seed,
            "kill": kill,
            "formed": r["formed"],
            "gave_up": r["gave_up"],
            "latches": len(r["latch_mm"]),
        }
    return released_run(kind, seed, modules_move)


def summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    formed = [r["formed"] for r in runs if r["formed"] is not None]
    return {
        "formed": len(formed),
        "runs": len(runs),
        "median": statistics.median(formed) if formed else None,
        "range": [min(formed), max(formed)] if formed else None,
        "docks_gave_up": sum(r["gave_up"] for r in runs),
        "not_formed": [f"{r['kill']}@{r['seed']}" for r in runs if r["formed"] is None],
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="The reconfigurations in physics: docking motions run by the world against by the modules"
    )
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default 0,1,2)")
    parser.add_argument(
        "--kills", default="none", help=f"legs to snake's interruptions, of {', '.join(KILLS)} (default none)"
    )
    parser.add_argument(
        "--only", default=",".join(RECONFIGURATIONS), help=f"comma-separated, of {', '.join(RECONFIGURATIONS)}"
    )
    parser.add_argument("--jobs", type=int, default=2, help="runs at once, one process each (default 2)")
    parser.add_argument(
        "--arms",
        default=",".join(ARMS),
        help="comma-separated, of world, modules (default both; one alone prints no ratio: the "
        "done-when's ratio is of both measured in one sitting)",
    )
    parser.add_argument("--quick", action="store_true", help="snake to T at seed 0 (a smoke test)")
    args = parser.parse_args(argv)
    arms_run = args.arms.split(",")
    if not arms_run or [a for a in arms_run if a not in ARMS]:
        parser.error(f"--arms: each one of {', '.join(ARMS)}, got {args.arms!r}")
    seeds = seeds_arg(parser, args.seeds)
    kills = args.kills.split(",")
    if [k for k in kills if k not in KILLS]:
        parser.error(f"--kills: each one of {', '.join(KILLS)}, got {args.kills!r}")
    only = args.only.split(",")
    if [k for k in only if k not in RECONFIGURATIONS]:
        parser.error(f"--only: each one of {', '.join(RECONFIGURATIONS)}, got {args.only!r}")
    jobs = jobs_arg(parser, args.jobs)
    if args.quick:
        seeds, kills, only = [0], ["none"], ["t"]
    cases = [
        (f"{kind}/{arm}", one_case, (kind, seed, kill, arm == "modules"))
        for kind in only
        for seed in seeds
        for kill in (kills if kind == "legs_to_snake" else ["none"])
        for arm in ARMS
        if arm in arms_run
    ]
    print(f"{len(cases)} runs, {jobs} at a time", flush=True)

    def describe(name: str, r: dict[str, Any]) -> str:
        state = f"formed at cycle {r['formed']}" if r["formed"] is not None else "did not form"
        return f"{name:24} seed {r['seed']} kill {r['kill']:4}: {state}, {r['gave_up']} docks given up"

    results = run_variants(jobs, cases, describe)
    if results is None:
        print("interrupted", file=sys.stderr)
        return 130
    out: dict[str, Any] = {"bench": "motions_in_modules", "seeds": seeds, "kills": kills}
    for kind in only:
        arms = {arm: summary(results[f"{kind}/{arm}"]) for arm in ARMS if arm in arms_run}
        world, modules = (arms[a]["median"] if a in arms else None for a in ARMS)
        ratio = round(modules / world, 3) if world and modules else None
        out[kind] = {**arms, "median_ratio": ratio}
        for arm in arms:
            s = arms[arm]
            print(
                f"{kind:14} {arm:8} formed {s['formed']}/{s['runs']}, cycle median {s['median']} "
                f"(range {s['range']}), docks given up {s['docks_gave_up']}, not formed {s['not_formed'] or 'none'}"
            )
        print(f"{kind:14} median cycle formed, modules / world: {ratio}")
    print(json.dumps(strict_json(out)))
    return 0 if all(arm["formed"] for k in only for arm in arms_of(out[k])) else 1


def arms_of(case: dict[str, Any]) -> list[dict[str, Any]]:
    """The arms run of one reconfiguration's summary."""
    return [case[a] for a in ARMS if a in case]


if __name__ == "__main__":
    raise SystemExit(main())
