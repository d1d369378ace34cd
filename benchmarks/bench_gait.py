"""Caterpillar travel in physics: the DH2 engine running examples/caterpillar.dh2 against the
scripted Table I schedule (firmware.motion.gaits.caterpillar_schedule, written independently from the
paper) on the same world, same ClockCycle and control period.

A ratio near 1.0 says the engine and its hormones reproduce the paper's gait; the absolute
figures are the robot's forward travel per gait cycle (ClockCycle control cycles).

    python -m benchmarks.bench_gait [--quick]
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dh2rt.compiler import compile_file
from dh2rt.robot import Robot
from dh2rt.topology import snake
from sim.gaits import run_caterpillar
from sim.runner import STEPS_PER_CYCLE, PhysicsRun
from sim.world import World

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def engine_travel(n: int, seed: int, settle: int, periods: int) -> float:
    program = compile_file(str(EXAMPLES / "caterpillar.dh2"))
    run = PhysicsRun(Robot(program, snake(n), seed=seed))
    try:
        run.run(settle * program.clock_cycle)
        run.start = run.world.centroid()
        run.run(periods * program.clock_cycle)
        return run.displacement() * 100 / periods
    finally:
        run.close()


def scripted_travel(n: int, seed: int, settle: int, periods: int, clock: int) -> float:
    with World(snake(n), seed=seed) as world:
        run_caterpillar(world, settle * clock, steps_per_cycle=STEPS_PER_CYCLE, clock_cycle=clock)
        start = world.centroid()
        run_caterpillar(
            world, periods * clock, steps_per_cycle=STEPS_PER_CYCLE, clock_cycle=clock, first_cycle=settle * clock
        )
        return world.travel(start) * 100 / periods


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Caterpillar travel: engine vs scripted Table I")
    parser.add_argument("--quick", action="store_true", help="a few seconds, for smoke tests")
    args = parser.parse_args(argv)
    clock = compile_file(str(EXAMPLES / "caterpillar.dh2")).clock_cycle
    sizes, seeds, periods = ((5,), (0,), 1) if args.quick else ((5, 8, 20), (0, 1, 2), 4)
    rows: list[dict[str, Any]] = []
    print(f"Forward travel per gait cycle ({clock} cycles x {STEPS_PER_CYCLE} steps at 240 Hz), cm")
    for n in sizes:
        eng = [engine_travel(n, s, 1, periods) for s in seeds]
        ref = [scripted_travel(n, s, 1, periods, clock) for s in seeds]
        ratio = statistics.mean(eng) / statistics.mean(ref)
        rows.append({"modules": n, "engine_cm": eng, "scripted_cm": ref, "ratio": ratio})
        print(
            f"  snake:{n:<3} engine {', '.join(f'{x:5.2f}' for x in eng)}   "
            f"scripted Table I {', '.join(f'{x:5.2f}' for x in ref)}   engine/scripted {ratio:.2f}"
        )
    print(json.dumps({"benchmark": "gait", "quick": args.quick, "seeds": list(seeds), "rows": rows}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
