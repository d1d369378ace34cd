"""How long a ``sense`` event takes from the HIL world to S in a module process.

A snake of 3 module processes over emulated serial links (the recording stand-in: no
physics, so that only the path of the command is timed) runs a program that reads
``S.roll``; the world sends ``sense`` events, one every few cycles, each to a module in
turn, and the modules' trace records show the first cycle whose S has the value. For each
event: the wall time from the world's write of the command returning to the start of that
cycle, and how many cycles of that module started in between without it (0: the next cycle
had it). The baseline, from the same records: the wall time from the write returning to the
start of that module's next cycle, whatever its S (no command can count sooner); the ratio of
the two medians is 1 when every value lands in the very next cycle. On a busy machine a
process can stand still for a while; such stalls show in the wall times (p90, max), not in
the cycle counts.

Run: ``python -m benchmarks.bench_sense_latency [--events N] [--quick]``. The last line is one
JSON object.
"""

from __future__ import annotations

import argparse
import json
import time

from benchmarks import strict_json
from dh2rt.compiler import compile_source
from dh2rt.events import parse_event
from dh2rt.topology import parse_spec
from hil.world import World

PROGRAM = """
program alarm
const ClockCycle = 4
sensor roll
receptor tipped when S.roll > 45 { DOF1(30); keep_alive() }
receptor level when S.roll <= 45 { DOF1(0); keep_alive() }
"""
PERIOD = 0.02
EVERY = 7  # world cycles between two events (co-prime with the period's phase of anything)


def measure(events: int, seed: int) -> dict[str, object]:
    program = compile_source(PROGRAM, "alarm.dh2")
    topology = parse_spec("snake:3")
    texts = [f"{10 + EVERY * k}:sense:m{k % 3}:roll={(k % 170) + 10}" for k in range(events)]
    evs = [parse_event(t, topology, program.vocabulary) for t in texts]
    cycles = 10 + EVERY * events + 20
    world = World(program, topology, "serial", seed=seed, cycles=cycles, trace=True, stand_in="recording")
    applied: set[int] = set()
    try:
        world.start()
        deadline = time.monotonic() + cycles * PERIOD + 60
        while not world.done() and time.monotonic() < deadline:
            world.run_events(evs, applied)
            world.tick()
            time.sleep(0.005)
        world.tick()
    finally:
        world.stop()
    records = world.sorted_records()
    walls: list[float] = []
    nexts: list[float] = []
    missed: list[int] = []
    lost = 0
    for module, _name, value, _before, after in world.sense_times:
        mine = [r for r in records if r["module"] == module]
        first = next((i for i, r in enumerate(mine) if r["sensors"]["roll"] == value), None)
        if first is None:
            lost += 1
            continue
        walls.append(mine[first]["t"] - after)
        nexts.append(next(r["t"] for r in mine if r["t"] >= after) - after)
        missed.append(sum(1 for r in mine[:first] if r["t"] >= after and r["sensors"]["roll"] != value))
    walls.sort()
    nexts.sort()
    n = len(walls)

    def q(p: float, values: list[float] = walls) -> float:
        return round(values[min(n - 1, int(p * n))] * 1000, 1) if n else float("nan")

    return {
        "events": len(world.sense_times),
        "not_seen": lost,
        "wall_ms": {"p50": q(0.5), "p90": q(0.9), "max": q(1.0)},
        "next_cycle_ms": {"p50": q(0.5, nexts), "p90": q(0.9, nexts), "max": q(1.0, nexts)},
        "wall_over_next_cycle_p50": round(q(0.5) / q(0.5, nexts), 3) if n and q(0.5, nexts) > 0 else float("nan"),
        "cycles_missed": {str(k): missed.count(k) for k in sorted(set(missed))},
        "period_ms": PERIOD * 1000,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--events", type=int, default=30, help="sense events (default: 30)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="6 events, for smoke tests")
    ns = ap.parse_args()
    result = measure(6 if ns.quick else ns.events, ns.seed)
    wall = result["wall_ms"]
    assert isinstance(wall, dict)
    print(
        f"{result['events']} sense events over serial links, 20 ms cycles: S had the value "
        f"{wall['p50']} ms (p50), {wall['p90']} ms (p90), {wall['max']} ms (max) after the world sent it; "
        f"cycles that started in between without it: {result['cycles_missed']}; not seen: {result['not_seen']}"
    )
    nxt = result["next_cycle_ms"]
    assert isinstance(nxt, dict)
    print(
        f"baseline (same records): the module's next cycle started {nxt['p50']} ms (p50), {nxt['p90']} ms (p90), "
        f"{nxt['max']} ms (max) after the send: ratio of the medians {result['wall_over_next_cycle_p50']}"
    )
    print(json.dumps(strict_json({"bench": "sense_latency", **result})))


if __name__ == "__main__":
    main()
