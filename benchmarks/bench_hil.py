"""Hardware-in-the-loop figures: hop latency, the fastest cycle 8 modules sustain, CAN bus load.

Run: ``python -m benchmarks.bench_hil [--quick]``.

* Baseline (same run): the in-process :class:`~dh2rt.robot.Robot`, 8 modules in lockstep,
  free-running; its hop takes exactly one cycle.
* For ``virtual`` (threads on python-can's virtual bus), ``udp`` (one process per module on
  python-can udp_multicast, inside a private network namespace: this script re-executes
  itself under ``unshare -rn``) and ``serial`` (one process per module, pty links through the
  link emulator): the caterpillar on snake:8 at shrinking cycle periods. A period is
  *sustained* when no hop is lost (every hormone a module sent through back reached its
  neighbour) and at most LATE_BUDGET of the cycles started late (more than half a period
  after their deadline). Hop latency: from the start of the cycle in which module k-1 sent
  a hormone to the start of the cycle in which module k got it (CLOCK_MONOTONIC across
  processes); cycles are not synchronised, so it averages about half a period plus the link.
* CAN bus load, computed: bits per frame on a classic CAN bus with 29-bit ids (worst-case
  bit stuffing), frames per cycle of a caterpillar snake (each link carries, each way,
  a hormone or a keep-alive every cycle), and how many modules fit at what cycle rate on
  1 Mbit/s.

Prints the figures, the ratios against the Robot, and one JSON object as the last line.
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
from dh2rt.hormone import Hormone
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from dh2rt.wire.frame import FrameCodec, KeepAlive
from hil.netns import in_namespace, namespace_problem

ROOT = Path(__file__).resolve().parents[1]
PROGRAM = ROOT / "examples" / "caterpillar.dh2"
MODULES = 8
#: Fraction of cycles allowed to start late at a sustained rate.
LATE_BUDGET = 0.02
CAN_BITRATE = 1_000_000


# ---------------------------------------------------------------- CAN arithmetic


def can_frame_bits(data_bytes: int) -> int:
    """Bits of one classic CAN frame with a 29-bit id, worst-case stuffing, with 3 bits of
    interframe space: SOF, 11-bit base id, SRR, IDE, 18-bit id extension, RTR, r1, r0, DLC,
    data, 15-bit CRC are stuffed (at worst one bit per 4 after the first); CRC delimiter,
    ACK slot and delimiter, 7-bit EOF and IFS are not."""
    stuffed = 1 + 11 + 1 + 1 + 18 + 1 + 2 + 4 + 8 * data_bytes + 15
    return stuffed + (stuffed - 1) // 4 + 1 + 2 + 7 + 3


def can_load(program: CompiledProgram) -> dict[str, Any]:
    codec = FrameCodec(program.vocabulary, program.profile.connector_count)
    hormone_bytes = len(codec.encode(2, Hormone("X", ("A",))))
    beacon_bytes = len(codec.encode(2, KeepAlive(1)))
    hormone_bits = can_frame_bits(hormone_bytes)
    beacon_bits = can_frame_bits(beacon_bytes)
    # per link and cycle: front->back carries a hormone or a beacon (worst case: a hormone),
    # back->front always a beacon (the caterpillar sends nothing towards the head)
    per_link = hormone_bits + beacon_bits
    fits: list[dict[str, Any]] = []
    for rate in (25, 50, 100, 200, 500):
        links = CAN_BITRATE // (per_link * rate)
        fits.append({"cycle_hz": rate, "max_modules": int(links) + 1})
    per_cycle_8 = (MODULES - 1) * per_link
    return {
        "hormone_frame_bytes": hormone_bytes,
        "hormone_frame_bits_worst": hormone_bits,
        "keepalive_frame_bytes": beacon_bytes,
        "keepalive_frame_bits_worst": beacon_bits,
        "frames_per_cycle_snake8": 2 * (MODULES - 1),
        "bits_per_cycle_snake8": per_cycle_8,
        "max_cycle_hz_snake8": CAN_BITRATE / per_cycle_8,
        "fits_on_1mbit": fits,
    }


# ---------------------------------------------------------------- measuring


def robot_baseline(program: CompiledProgram, cycles: int) -> dict[str, float]:
    robot = Robot(program, parse_spec(f"snake:{MODULES}", program.profile), seed=0, skip_quiet=False)
    t0 = time.perf_counter()
    robot.run(cycles)
    elapsed = time.perf_counter() - t0
    rate = cycles / elapsed
    return {"cycle_hz": rate, "hop_latency_s": 1.0 / rate}


def measure_world(program: CompiledProgram, transport: str, period: float, cycles: int) -> dict[str, Any]:
    """One run of the caterpillar on snake:8; hop statistics and late cycles."""
    from hil.world import World

    world = World(program, parse_spec(f"snake:{MODULES}", program.profile), transport, cycle_period=period,
                  cycles=cycles, trace=True, status_every=1000, stand_in="recording")  # fmt: skip
    try:
        world.start()
        deadline = time.monotonic() + cycles * period + 30
        while not world.done() and time.monotonic() < deadline:
            world.tick()
            time.sleep(0.01)
    finally:
        world.stop()
    records = world.sorted_records()
    rows = world.rows()
    late = sum(int(r["counters"].get("late_cycles", 0)) for r in rows)
    ran = sum(int(r["counters"].get("cycles", 0)) for r in rows)
    # steady window: before the first module finished (neighbours then see silence)
    last: dict[int, float] = {}
    for r in records:
        last[r["module"]] = max(last.get(r["module"], 0.0), r["t"])
    cutoff = min(last.values()) - 5 * period if last else 0.0
    sent: dict[int, list[float]] = {m: [] for m in range(MODULES)}
    got: dict[int, list[float]] = {m: [] for m in range(MODULES)}
    for r in records:
        if r["t"] > cutoff:
            continue
        for s in r["sent"]:
            if s["through"] == "back":
                sent[r["module"]].append(r["t"])
        for a in r["received"]:
            if a["at"] == "front":
                got[r["module"]].append(r["t"])
    lost = 0
    hops: list[float] = []
    for k in range(1, MODULES):
        times_sent, times_got = sent[k - 1], got[k]
        # every send but possibly the last one (in flight at the cutoff) must have arrived
        lost += max(0, len(times_sent) - len(times_got) - 1)
        hops.extend(g - s for s, g in zip(times_sent, times_got, strict=False))
    failed = [r["name"] for r in rows if r["state"] != "done"]
    return {
        "period_ms": period * 1000,
        "cycles": cycles,
        "late_fraction": late / ran if ran else 1.0,
        "lost_hops": lost,
        "hops": len(hops),
        "hop_latency_s": sum(hops) / len(hops) if hops else float("nan"),
        "hop_latency_max_s": max(hops) if hops else float("nan"),
        "failed_modules": failed,
    }


def sweep(program: CompiledProgram, transport: str, periods_ms: list[float], cycles: int) -> dict[str, Any]:
    runs: list[dict[str, Any]] = []
    best: dict[str, Any] | None = None
    for ms in periods_ms:
        run = measure_world(program, transport, ms / 1000, cycles)
        run["sustained"] = (
            run["lost_hops"] == 0
            and run["late_fraction"] <= LATE_BUDGET
            and not run["failed_modules"]
            and run["hops"] > 0
        )
        runs.append(run)
        if not run["sustained"]:
            break
        best = run
    return {
        "transport": transport,
        "runs": runs,
        "max_cycle_hz": 1000 / best["period_ms"] if best else 0.0,
        "hop_latency_s": best["hop_latency_s"] if best else float("nan"),
        "hop_latency_periods": best["hop_latency_s"] / (best["period_ms"] / 1000) if best else float("nan"),
    }


def udp_in_namespace(argv: list[str]) -> dict[str, Any]:
    """Run the udp sweep in a child under ``unshare -rn``; its result or the reason it could not."""
    if (problem := namespace_problem()) is not None:
        return {"transport": "udp", "skipped": problem}
    cmd = in_namespace([sys.executable, "-m", "benchmarks.bench_hil", "--udp-inner", *argv])
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600)
    if proc.returncode != 0:
        return {"transport": "udp", "skipped": f"private network namespace failed: {proc.stderr.strip()[-300:]}"}
    result: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="HIL hop latency, sustained cycle rate, CAN bus load")
    parser.add_argument("--quick", action="store_true", help="a few seconds, for smoke tests")
    parser.add_argument("--udp-inner", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    program = compile_file(str(PROGRAM))
    periods = [20.0] if args.quick else [40.0, 20.0, 10.0, 5.0, 3.0, 2.0]
    cycles = 60 if args.quick else 200
    if args.udp_inner:
        import socket

        if [n for _i, n in socket.if_nameindex()] != ["lo"]:
            print(json.dumps({"transport": "udp", "skipped": "not in a loopback-only namespace"}))
            return 2
        print(json.dumps(sweep(program, "udp", periods, cycles)))
        return 0
    baseline = robot_baseline(program, 2000 if args.quick else 20000)
    results = [sweep(program, "virtual", periods, cycles)]
    if args.quick:
        results.append({"transport": "udp", "skipped": "not run with --quick (namespace start-up)"})
    else:
        results.append(udp_in_namespace(["--quick"] if args.quick else []))
    results.append(sweep(program, "serial", periods, cycles))
    can = can_load(program)

    print(f"in-process Robot, snake:{MODULES}: {baseline['cycle_hz']:,.0f} cycles/s, "
          f"hop {baseline['hop_latency_s'] * 1e6:.1f} us (one cycle)")  # fmt: skip
    for r in results:
        if "skipped" in r:
            print(f"{r['transport']:>8}: skipped: {r['skipped']}")
            continue
        r["rate_vs_robot"] = r["max_cycle_hz"] / baseline["cycle_hz"]
        r["hop_latency_vs_robot"] = r["hop_latency_s"] / baseline["hop_latency_s"]
        print(
            f"{r['transport']:>8}: sustains {r['max_cycle_hz']:.0f} cycles/s ({r['rate_vs_robot']:.4f}x Robot); "
            f"hop {r['hop_latency_s'] * 1000:.2f} ms = {r['hop_latency_periods']:.2f} periods "
            f"({r['hop_latency_vs_robot']:.0f}x Robot's hop)"
        )
        for run in r["runs"]:
            print(
                f"          {run['period_ms']:>5.1f} ms: lost hops {run['lost_hops']}, "
                f"late {run['late_fraction']:.1%}, "
                f"hop mean {run['hop_latency_s'] * 1000:.2f} ms max {run['hop_latency_max_s'] * 1000:.2f} ms, "
                f"{'sustained' if run['sustained'] else 'NOT sustained'}"
            )
    print(
        f"CAN (1 Mbit/s classic, 29-bit ids, worst-case stuffing): caterpillar frame {can['hormone_frame_bytes']} B = "
        f"{can['hormone_frame_bits_worst']} bits, keep-alive {can['keepalive_frame_bytes']} B = "
        f"{can['keepalive_frame_bits_worst']} bits; snake:8 puts {can['frames_per_cycle_snake8']} frames, "
        f"{can['bits_per_cycle_snake8']} bits per cycle on the bus: at most {can['max_cycle_hz_snake8']:.0f} cycles/s"
    )
    print("  modules that fit: " + ", ".join(f"{f['max_modules']} at {f['cycle_hz']} Hz" for f in can["fits_on_1mbit"]))
    print(json.dumps({"bench": "hil", "quick": args.quick, "robot": baseline, "transports": results, "can": can}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
