"""snake_to_t's docking motion in the loop against the same motion in one process.

Run: ``python -m benchmarks.bench_hil_reach [--seeds 0 1 2] [--quick]`` (about 40 s a seed;
``--quick``: seed 0 only). Exits 1 if a run did not end as the T.

For each seed: ``dh2rt --transport serial --stand-in pybullet`` (module processes driving
their servos through dynamixel-sdk over ptys; hil.reach_loop steps the motion once per
50 ms world cycle) runs examples/snake_to_t.dh2 on snake:8 with STT injected at cycle 50
(at m4, m0, m7 in turn, as tests/sim/test_snake_to_t_physics.py); then ``PhysicsRun``
(``dh2rt run --sim pybullet``) runs the same. Printed per seed and run: the cycle the motion
was asked at, the cycle it latched (or gave up) at, its steps, the faces' distance and
attitude error at the latch and the infrared reading then, and whether the run ended as the
T. One JSON object as the last line.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from dh2rt.compiler import compile_file
from dh2rt.events import parse_event
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec

ROOT = Path(__file__).resolve().parents[1]
PROGRAM = ROOT / "examples" / "snake_to_t.dh2"
AT = ("m4", "m0", "m7")
CYCLES = 600


def in_the_loop(seed: int, at: str) -> dict[str, Any]:
    cmd = [
        sys.executable, "-m", "dh2rt", "--transport", "serial", "--program", str(PROGRAM), "--topology", "snake:8",
        "--cycles", str(CYCLES), "--cycle-ms", "50", "--silence-cycles", "6", "--event", f"50:inject:{at}:STT",
        "--seed", str(seed), "--json", "--stand-in", "pybullet",
    ]  # fmt: skip
    started = time.monotonic()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT)
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    types = {m["name"]: m["type"] for m in summary["modules"]}
    reaches = summary["reaches"]
    out: dict[str, Any] = {
        "exit": proc.returncode,
        "problems": summary["problems"],
        "seconds": round(time.monotonic() - started, 1),
        "t": types["m3"] == "head" and types["m2"] == "tail" and types["m7"] == "tail",
    }
    for outcome, contact in zip(reaches["outcomes"], reaches["contacts"] + reaches["failed"], strict=False):
        out.update(outcome)
        out.update({k: contact[k] for k in ("distance_mm", "attitude_deg", "ir_mm", "ir_align_deg")})
    return out


def in_one_process(seed: int, at: str) -> dict[str, Any]:
    from sim.runner import PhysicsRun

    prog = compile_file(str(PROGRAM))
    topo = parse_spec("snake:8")
    robot = Robot(prog, topo, seed=seed)
    run = PhysicsRun(robot)
    try:
        run.run(50, [])
        run.run(1, [parse_event(f"50:inject:{at}:STT", topo, prog.vocabulary)])
        asked = None
        while not (run.contacts or run.failed) and robot.cycle < CYCLES:
            run.run(1, [])
            if asked is None and run.docking.motions:
                asked = run.docking.motions[0].reach.start_cycle
        run.run(20, [])
        types = [e.topo_type.name for e in robot.engines if e is not None]
        out: dict[str, Any] = {"t": types[3] == "head" and types[2] == "tail" and types[7] == "tail"}
        for c, latched in [(c, True) for c in run.contacts] + [(c, False) for c in run.failed]:
            out.update({"asked": asked, "ended": c.cycle, "latched": latched})
            out.update({k: v for k, v in c.as_dict().items() if k in ("distance_mm", "attitude_deg", "ir_mm")})
            out["ir_align_deg"] = c.as_dict()["ir_align_deg"]
        return out
    finally:
        run.close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--quick", action="store_true", help="seed 0 only, for smoke tests")
    ns = p.parse_args(argv)
    rows = []
    for seed in [0] if ns.quick else ns.seeds:
        at = AT[seed % len(AT)]
        for where, fn in (("loop", in_the_loop), ("process", in_one_process)):
            row = {"seed": seed, "at": at, "run": where, **fn(seed, at)}
            rows.append(row)
            loop = (
                f"; plan ready at {row['planned']} ({row['plan_s']} s), {row['missed']} cycles missed; "
                f"{row['seconds']} s, exit {row['exit']}"
                if where == "loop"
                else ""
            )
            print(
                f"seed {seed} STT at {at} {where:>7}: asked {row.get('asked')}, "
                f"{'latched' if row.get('latched') else 'NOT latched'} at {row.get('ended')} "
                f"({row.get('steps', '-')} steps), {row.get('distance_mm')} mm, {row.get('attitude_deg')} deg, "
                f"infrared {row.get('ir_mm')} mm {row.get('ir_align_deg')} deg; T: {row['t']}" + loop,
                flush=True,
            )
    print(json.dumps({"rows": rows}))
    return 0 if all(row["t"] for row in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
