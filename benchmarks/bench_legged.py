"""Legged walking in physics: examples/locomotion.dh2 against the program before the legged
gait of issue 13 (benchmarks/locomotion_before.dh2) and against itself unsteered (its side
legs' ``SteerNum`` 0: they stroke ``Swing`` whatever their IMU's ``S.yaw`` says), on the same
worlds in the same run, and the snake (caterpillar receptors of the same program) beside them.

For each robot and seed: centimetres per gait cycle (the centroid's travel along the
direction module 0's front faced at the start, one gait cycle to settle, then the measured
ones), and the heading drift: the largest angle between module 0's front connector's
horizontal direction at the end of a gait cycle and at the start (sim.walk.measure_walk).

    python -m benchmarks.bench_legged [--quick] [--gait-cycles N] [--seeds 0,1,2] [--no-before]
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from benchmarks import seeds_arg, strict_json
from dh2rt.compiler import compile_file, compile_source
from dh2rt.program import CompiledProgram
from sim.walk import measure_walk

HERE = Path(__file__).resolve().parent
EXAMPLES = HERE.parent / "examples"
LEGGED = ("tripod", "quadruped", "hexapod", "octopod")
#: The line of locomotion.dh2 that sets its legs' steering gain, and the same line unsteered.
STEER, UNSTEERED = "const SteerNum = 3 ", "const SteerNum = 0 "


def unsteered(path: Path) -> CompiledProgram:
    """The program at ``path`` with its legs' steering gain set to 0."""
    text = path.read_text(encoding="utf-8")
    if text.count(STEER) != 1:
        raise SystemExit(f"{path}: expected one line starting {STEER.strip()!r} (the legs' steering gain)")
    return compile_source(text.replace(STEER, UNSTEERED), str(path))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Legged walking: the locomotion program against its earlier gait")
    parser.add_argument("--quick", action="store_true", help="quadruped, seed 0, 2 gait cycles (a smoke test)")
    parser.add_argument("--gait-cycles", type=int, default=20, help="gait cycles measured after one to settle")
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default 0,1,2)")
    parser.add_argument("--no-before", action="store_true", help="skip the earlier gait and the unsteered one")
    args = parser.parse_args(argv)
    seeds = seeds_arg(parser, args.seeds)
    if args.gait_cycles < 1:
        parser.error("--gait-cycles must be at least 1")
    now = compile_file(str(EXAMPLES / "locomotion.dh2"))
    straight = unsteered(EXAMPLES / "locomotion.dh2")
    before = compile_file(str(HERE / "locomotion_before.dh2"))
    robots: tuple[str, ...] = (*LEGGED, "snake:8")
    gait_cycles = args.gait_cycles
    if args.quick:
        robots, seeds, gait_cycles = ("quadruped",), [0], 2
    rows: list[dict[str, Any]] = []
    print(f"cm per gait cycle ({now.clock_cycle} control cycles), heading drift over {gait_cycles} gait cycles")
    for robot in robots:
        walks = [measure_walk(now, robot, s, gait_cycles=gait_cycles) for s in seeds]
        row: dict[str, Any] = {
            "robot": robot,
            "seeds": seeds,
            "cm_per_gait_cycle": [round(w.cm_per_gait_cycle, 2) for w in walks],
            "drift_deg": [round(w.drift_deg, 1) for w in walks],
        }
        line = (
            f"  {robot:<10} {', '.join(f'{w.cm_per_gait_cycle:5.2f}' for w in walks)} cm   "
            f"drift {', '.join(f'{w.drift_deg:4.1f}' for w in walks)} deg"
        )
        if robot in LEGGED and not args.no_before:
            old = [measure_walk(before, robot, s, gait_cycles=gait_cycles) for s in seeds]
            ratio = statistics.mean(w.cm_per_gait_cycle for w in walks) / statistics.mean(
                w.cm_per_gait_cycle for w in old
            )
            row["before_cm_per_gait_cycle"] = [round(w.cm_per_gait_cycle, 2) for w in old]
            row["before_drift_deg"] = [round(w.drift_deg, 1) for w in old]
            row["ratio"] = round(ratio, 2)
            loose = [measure_walk(straight, robot, s, gait_cycles=gait_cycles) for s in seeds]
            row["unsteered_cm_per_gait_cycle"] = [round(w.cm_per_gait_cycle, 2) for w in loose]
            row["unsteered_drift_deg"] = [round(w.drift_deg, 1) for w in loose]
            line += (
                f"   before {', '.join(f'{w.cm_per_gait_cycle:5.2f}' for w in old)} cm, "
                f"drift {', '.join(f'{w.drift_deg:4.1f}' for w in old)} deg   now/before {ratio:.2f}"
                f"   unsteered {', '.join(f'{w.cm_per_gait_cycle:5.2f}' for w in loose)} cm, "
                f"drift {', '.join(f'{w.drift_deg:4.1f}' for w in loose)} deg"
            )
        rows.append(row)
        print(line, flush=True)
    result = {"benchmark": "legged", "quick": args.quick, "gait_cycles": gait_cycles, "rows": rows}
    print(json.dumps(strict_json(result)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
