"""Legs to snake in physics, whole: how often the snake forms, and when.

The dragon runs examples/legs_to_snake.dh2 in PyBullet, LTS at cycle 50
(sim.legs_to_snake.reconfigure), at each seed without an interruption (``none``), with the
first winning foot killed 400 cycles into its trip (``trip``) and killed as its dock begins
(``dock``). Each run twice, in the same benchmark: with today's dock, whose plan leaves the
distance to the creeping foot (``free_distance``), and with the plan before it, which asked
the tail's last two modules to put their face 3 cm in front of the foot
(``PhysicsRun.docking.options.free_distance = False``); and, with ``--variants ...,filtered``,
free_distance with the modules smoothing the tracker's reports (:mod:`firmware.motion.floor_filter`,
``--filter-alpha``). Reported: how many formed the snake, the cycle it
formed (median and range), the docks that gave up, and the latches' distances and attitudes.
``--variants`` runs only some of the two. ``--tracker`` gives the overhead tracker the foot's
trip steers by (sim.tracker.OverheadTracker) noise, latency and dropouts (exact by default);
``--oracle`` makes the docking motions read their faces' relative pose from the world's exact
state instead of the chain's kinematics and the tracker (PhysicsRun.oracle_poses: to measure
what the modules' own sensing costs). ``--camera EVERY`` replaces the tracker by a rendered
overhead camera read by ``dh2rt tracker``'s detector (tools.tracker.sim_camera.CameraTracker:
markers on every part, a frame every EVERY cycles of 50 ms; about half a second of rendering a
frame, so a run takes 15 to 30 minutes): the trip then steers by detections, not by the
simulator's state.

    python -m benchmarks.bench_legs_to_snake [--seeds 0,1,2,3] [--kills none,dock,trip] [--jobs 2] [--quick]
        [--variants free_distance,standoff,filtered] [--filter-alpha 0.3]
        [--tracker NOISE_MM,NOISE_DEG,LATENCY,DROPOUT] [--oracle] [--camera EVERY]

One run is 30 to 45 s on one core. The last line is one JSON object.
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
from dh2rt.compiler import compile_file
from firmware.motion.floor_filter import FloorFilter
from sim.legs_to_snake import KILLS, KillWinner, reconfigure
from sim.runner import PhysicsRun
from sim.tracker import OverheadTracker

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "legs_to_snake.dh2"
#: variant -> (the dock's plan leaves the distance free, the floor filter's alpha or None: raw)
VARIANTS: dict[str, tuple[bool, float | None]] = {
    "free_distance": (True, None),
    "standoff": (False, None),
    "filtered": (True, 0.3),
}
DEFAULT_VARIANTS = ("free_distance", "standoff")


def one_run(
    seed: int,
    kill: str,
    variant: tuple[bool, float | None],
    tracker: tuple[float, float, int, float] = (0, 0, 0, 0),
    oracle: bool = False,
    camera: int = 0,
    modules_move: bool = False,
) -> dict[str, Any]:
    """One whole reconfiguration; what happened. ``tracker``: noise (mm, degrees), latency
    (cycles) and dropout probability of the overhead tracker; ``oracle``: PhysicsRun.oracle_poses."""
    program = compile_file(str(EXAMPLE))
    hook = KillWinner(kill)
    noise_mm, noise_deg, latency, dropout = tracker
    free_distance, alpha = variant

    def setup(run: PhysicsRun) -> None:
        run.docking.options.free_distance = free_distance
        run.motion_sensors.floor_filter = None if alpha is None else FloorFilter(alpha)
        run.oracle_poses = oracle
        if camera:
            from tools.tracker.sim_camera import CameraTracker

            run.motion_sensors.tracker = CameraTracker(run.world, every=camera)
            return
        run.motion_sensors.tracker = OverheadTracker(
            run.world, noise_m=noise_mm / 1000, noise_deg=noise_deg, latency=latency, dropout=dropout, seed=seed
        )

    run, formed = reconfigure(program, seed, hook, setup=setup, modules_move=modules_move)
    try:
        result: dict[str, Any] = {
            "seed": seed,
            "kill": kill,
            "formed": formed,
            "gave_up": len(run.failed) + (run.module_motions.given_up() if run.module_motions else 0),
            "latch_mm": [round(c.distance_m * 1000, 1) for c in run.contacts],
            "latch_deg": [round(c.attitude_deg, 1) for c in run.contacts],
        }
        if camera:
            result["camera"] = camera_figures(run.motion_sensors.tracker)
        return result
    finally:
        run.close()


def camera_figures(tracker: Any) -> dict[str, Any]:
    """What the camera tracker did: frames, parts missed, seconds, its errors against the truth."""
    return {
        "frames": tracker.frames,
        "parts_missed": tracker.dropped,
        "render_s": round(tracker.render_s, 1),
        "detect_s": round(tracker.detect_s, 1),
        "error_mm": quantiles(tracker.errors_mm),
        "error_deg": quantiles(tracker.errors_deg),
    }


def quantiles(values: Sequence[float]) -> dict[str, float] | None:
    """Median, 99th percentile and maximum (None for no values)."""
    if not values:
        return None
    ordered = sorted(values)
    picks = (statistics.median(ordered), ordered[int(0.99 * (len(ordered) - 1))], ordered[-1])
    return {name: round(v, 2) for name, v in zip(("median", "p99", "max"), picks, strict=True)}


def spread(values: Sequence[float]) -> dict[str, Any]:
    if not values:
        return {"median": None, "range": None}
    return {"median": round(statistics.median(values), 2), "range": [min(values), max(values)]}


def summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    formed = [r["formed"] for r in runs if r["formed"] is not None]
    return {
        "formed": len(formed),
        "runs": len(runs),
        "cycles": spread(formed),
        "docks_gave_up": sum(r["gave_up"] for r in runs),
        "latch_mm": spread([v for r in runs for v in r["latch_mm"]]),
        "latch_deg": spread([v for r in runs for v in r["latch_deg"]]),
        "not_formed": [f"{r['kill']}@{r['seed']}" for r in runs if r["formed"] is None],
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Legs to snake in physics, whole: the dock's plan with free_distance against the 3 cm standoff"
    )
    parser.add_argument("--seeds", default="0,1,2,3", help="comma-separated seeds (default 0 to 3)")
    parser.add_argument(
        "--kills", default=",".join(KILLS), help=f"comma-separated interruptions, of {', '.join(KILLS)} (default all)"
    )
    parser.add_argument("--jobs", type=int, default=2, help="runs at once, one process each (default 2)")
    parser.add_argument("--quick", action="store_true", help="seed 0 without a kill (a smoke test)")
    parser.add_argument(
        "--variants",
        default=",".join(DEFAULT_VARIANTS),
        help=f"comma-separated, of {', '.join(VARIANTS)} (default {','.join(DEFAULT_VARIANTS)}); filtered is "
        "free_distance with the modules smoothing the tracker's reports (firmware.motion.floor_filter)",
    )
    parser.add_argument(
        "--filter-alpha", type=float, default=0.3, help="the filtered variant's alpha, in (0, 1] (default 0.3)"
    )
    parser.add_argument(
        "--tracker",
        default="0,0,0,0",
        help="the overhead tracker's position noise (mm), heading noise (deg), latency (cycles), dropout "
        "probability (default 0,0,0,0: exact)",
    )
    parser.add_argument(
        "--oracle", action="store_true", help="the motions read the faces' exact relative pose from the world"
    )
    parser.add_argument(
        "--camera",
        type=int,
        default=0,
        metavar="EVERY",
        help="the trip steers by a rendered overhead camera and the tracker's detector, a frame every EVERY "
        "cycles (replaces --tracker; 15 to 30 minutes a run)",
    )
    args = parser.parse_args(argv)
    variants = args.variants.split(",")
    if args.camera < 0:
        parser.error(f"--camera: a frame every EVERY cycles, 1 or more, got {args.camera}")
    if [v for v in variants if v not in VARIANTS]:
        parser.error(f"--variants: each one of {', '.join(VARIANTS)}, got {args.variants!r}")
    try:
        noise_mm, noise_deg, latency, dropout = args.tracker.split(",")
        tracker = (float(noise_mm), float(noise_deg), int(latency), float(dropout))
    except ValueError:
        parser.error(f"--tracker: four numbers NOISE_MM,NOISE_DEG,LATENCY,DROPOUT, got {args.tracker!r}")
    if min(tracker) < 0 or tracker[3] >= 1:
        parser.error(f"--tracker: noise and latency >= 0, dropout in [0, 1), got {args.tracker!r}")
    if not 0 < args.filter_alpha <= 1:
        parser.error(f"--filter-alpha: in (0, 1], got {args.filter_alpha}")
    chosen = {**VARIANTS, "filtered": (True, args.filter_alpha)}
    seeds = seeds_arg(parser, args.seeds)
    kills = args.kills.split(",")
    unknown = [k for k in kills if k not in KILLS]
    if unknown:
        parser.error(f"--kills: {', '.join(unknown)} not one of {', '.join(KILLS)}")
    jobs = jobs_arg(parser, args.jobs)
    if args.quick:
        seeds, kills = [0], ["none"]
    cases = [
        (name, one_run, (seed, kill, chosen[name], tracker, args.oracle, args.camera))
        for name in variants
        for seed in seeds
        for kill in kills
    ]
    print(f"{len(cases)} runs, {jobs} at a time (one run: 30 to 45 s on one core)", flush=True)

    def describe(name: str, r: dict[str, Any]) -> str:
        state = f"formed at cycle {r['formed']}" if r["formed"] is not None else "did not form"
        return f"{name:13} seed {r['seed']} kill {r['kill']:4}: {state}"

    results = run_variants(jobs, cases, describe)
    if results is None:
        print("interrupted", file=sys.stderr)
        return 130
    out: dict[str, Any] = {
        "bench": "legs_to_snake",
        "seeds": seeds,
        "kills": kills,
        "tracker": dict(zip(("noise_mm", "noise_deg", "latency", "dropout"), tracker, strict=True)),
        "oracle": args.oracle,
        "camera_every": args.camera or None,
    }
    if args.camera:
        out["camera"] = [dict(r["camera"], seed=r["seed"], kill=r["kill"]) for rs in results.values() for r in rs]
    for name in variants:
        s = summary(results[name])
        out[name] = s
        print(
            f"{name:13} formed {s['formed']}/{s['runs']}, cycle median {s['cycles']['median']} "
            f"(range {s['cycles']['range']}), docks given up {s['docks_gave_up']}, "
            f"latches {s['latch_mm']['median']} mm / {s['latch_deg']['median']} deg median, "
            f"not formed {s['not_formed'] or 'none'}"
        )
    if {"free_distance", "filtered"} <= set(variants):
        raw, smooth = out["free_distance"]["cycles"]["median"], out["filtered"]["cycles"]["median"]
        out["filtered_cycle_ratio"] = round(smooth / raw, 3) if smooth and raw else None
        print(f"median cycle the snake formed, filtered / raw tracker reports: {out['filtered_cycle_ratio']}")
    if set(DEFAULT_VARIANTS) <= set(variants):
        now, before = out["free_distance"]["cycles"]["median"], out["standoff"]["cycles"]["median"]
        out["median_cycle_ratio"] = round(now / before, 3) if now and before else None
        print(f"median cycle the snake formed, free_distance / standoff: {out['median_cycle_ratio']}")
    print(json.dumps(strict_json(out)))
    return 0 if any(out[name]["formed"] for name in variants) else 1


if __name__ == "__main__":
    raise SystemExit(main())
