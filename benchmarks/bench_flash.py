"""Time to flash a running robot (issue 11), against each link's own limit.

Run: ``python -m benchmarks.bench_flash [--quick]`` (about a minute; ``--quick`` about 6 s).

What is flashed: the caterpillar with ClockCycle 20, signed as version 2 with the run's key,
into a robot running the caterpillar with ClockCycle 40 at 20 ms cycles.

* **Serial links, module processes** (the main figure): a ``snake:N`` World (N = 8 and 20,
  PROCESS_SEEDS runs each, medians; ``--quick``: N = 4, one run) of ``dh2rt`` module
  processes whose infrared links are pty pairs relayed by the link emulator at 115,200 baud
  (10 bits a byte). After WARMUP cycles a programming cable is plugged into the head's free
  front connector, and PLUGGED cycles later (the head has opened its end, as a cable is in
  before ``dh2rt flash`` runs) :class:`~firmware.flash.cable.FlashCable` starts offering the
  image through it (paced as a module's rollout is). Times run from the flasher's start, as
  the simulation's from the entry point's first cycle. *Staged*: until the last module's log
  says "image staged", timed by the trace record of the cycle it logged it in (``t``,
  CLOCK_MONOTONIC, one clock for every process): the start of that cycle, at most one period
  after the staging itself (a module stages between cycles, as the last segment arrives;
  the start of the cycle before is shown as the lower bound). The log lines themselves reach
  the world only every ``status_every`` cycles, too late to time anything. *Switched*: until
  the last module's first cycle on the new program (its "switched to program" line; the
  switch happens at that cycle's start, so this one is exact). Also shown: when the flasher
  had its first ACK, heard the whole robot staged and committed (its progress, each tick).
* **The limits, measured in the same run**: one paced link of a
  ``LinkEmulator(baudrate=115200)`` carries the image as the rollout frames it (80-byte
  SEGMENT transfer frames in serial framing, 92 bytes on the wire each) from one pyserial
  port to the other: *hop* is the time the whole image takes, *segment* the time one
  80-byte segment frame takes (median of several). Store and forward: ``depth x hop``;
  pipelined (segments forwarded while later ones still arrive): ``hop + depth x segment``.
  The ratio staged / pipelined is judged; beside it the ratio against the nominal limits of
  docs/flashing.md (image bytes / 11,520 bytes/s, no framing).
* **Hormones during the rollout**: from the trace records between the plug and the last
  switch, for each module m >= 1 and each hormone it received, the lag since module m-1
  received the previous phase (or the head sent it), in periods (the hop-by-hop check of
  tests/hil/test_flash_loop.py); p50, p99, max and the share within 1 and 2 periods, the
  same for the WARMUP cycles before the plug (same run, no rollout), hormones sent with no
  arrival, and the modules' ``late_cycles`` and ``links_lost`` counters over the rollout
  (``links_lost`` must stay 0), and the cycles that began more than 1.5 periods after the
  module's previous one (the machine held the process up), at the switch or elsewhere.
* **Simulated robot** (tests/dh2rt/rollout_sim.py, sans-IO, prompt hosts): CAN at 1 Mbit/s
  (bits counted as classic CAN frames with worst-case stuffing: ``dh2rt.wire.transfer.
  can_cost``) and, beside the real figure, serial at 115,200 baud; snake:8 and snake:20,
  median over seeds 0..4 (``--quick``: snake:8, seed 0). Limit on CAN: every copy crosses
  the one bus, ``depth x image / throughput``.

Target: staged within 2x of the limit (pipelined on serial links, the bus on CAN), hormones
on time meanwhile (every hormone arrives, at most HOP periods after its upstream, and no
link lost). Figures in cycles of 20 ms; the last line is one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import bisect
import itertools
import json
import math
import os
import re
import statistics
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any

from benchmarks import strict_json
from dh2rt.compiler import compile_file
from dh2rt.errors import DH2Error
from dh2rt.flash.flasher import Progress
from dh2rt.flash.pacing import link_pacing
from dh2rt.signed_image import pack
from dh2rt.topology import parse_spec
from dh2rt.transport.base import PortEnd
from dh2rt.transport.serial_link import SerialTransport
from dh2rt.wire import transfer as tw
from dh2rt.wire.serial_framing import encode_serial
from firmware.flash.cable import FlashCable, FlashResult, hello_codec
from hil.link_emulator import LinkEmulator
from hil.world import World
from tests.dh2rt.rollout_sim import CAN, SERIAL, Medium, flash_time, make_images
from tests.hil.flashing import FRONT, PERIOD, PROGRAM, caterpillar, run_world, switches

BAUD = 115_200
#: Cycles the robot runs before the cable is plugged in (the hormones' baseline window).
WARMUP = 60
#: Cycles between plugging the cable in and starting the flasher on it (the head opens its end).
PLUGGED = 5
#: Cycles the robot runs after the last switch, so that its last trace records and log arrive.
AFTER = 25
#: Runs (seeds) of each robot of module processes; the table shows their medians.
PROCESS_SEEDS = 5
#: The target: staged within this factor of the limit.
TARGET = 2.0
#: Periods a hormone may take over one serial hop (tests/hil/test_flash_loop.py's HOP).
HOP = 3
#: How far apart (periods) a hormone and its upstream may be to be matched at all.
MATCH = 10
#: Seconds a flash may take before it is given up.
FLASH_TIMEOUT = 120.0
#: Single-segment transfers timed for the segment time.
SEGMENT_PROBES = 9
NEXT = {"A": "B", "B": "C", "C": "D", "D": "A"}


# ---------------------------------------------------------------- the link's own limit


def measure_link(image: bytes, repeats: int) -> dict[str, Any]:
    """One paced link of the link emulator, pyserial at both ends: the image as SEGMENT frames
    (the rollout's serial segment size and framing) from side 0 to side 1, all written at
    once, until the last byte is read (``hop``, median of ``repeats``); one segment frame on
    an idle line (``segment``, median of SEGMENT_PROBES)."""
    import serial

    _, segment_size, _ = link_pacing("serial", PERIOD, BAUD, 0)
    tag = tw.tag_of(image)
    chunks = [image[i : i + segment_size] for i in range(0, len(image), segment_size)]
    frames = [encode_serial(tw.encode(1, tw.Segment(tag, i, c))) for i, c in enumerate(chunks)]
    wire = b"".join(frames)
    emulator = LinkEmulator(baudrate=BAUD)
    try:
        link = emulator.add_link(0)
        tx = serial.Serial(link.paths[0], baudrate=BAUD, timeout=0, write_timeout=1.0)
        rx = serial.Serial(link.paths[1], baudrate=BAUD, timeout=0.2)
        try:

            def carry(data: bytes) -> float:
                rx.reset_input_buffer()
                got = 0
                start = time.monotonic()
                tx.write(data)
                tx.flush()
                deadline = start + 5.0 + len(data) * 20 / BAUD
                while got < len(data) and time.monotonic() < deadline:
                    got += len(rx.read(len(data) - got))
                elapsed = time.monotonic() - start
                if got != len(data):
                    raise RuntimeError(f"link emulator delivered {got} of {len(data)} bytes")
                time.sleep(0.05)  # the line idle again
                return elapsed

            hops = [carry(wire) for _ in range(repeats)]
            segments = [carry(frames[0]) for _ in range(SEGMENT_PROBES)]
        finally:
            tx.close()
            rx.close()
    finally:
        emulator.close()
    return {
        "image_bytes": len(image),
        "segment_size": segment_size,
        "segments": len(frames),
        "wire_bytes": len(wire),
        "segment_wire_bytes": len(frames[0]),
        "hop_s": statistics.median(hops),
        "hop_runs_s": hops,
        "hop_line_s": len(wire) * 10 / BAUD,
        "segment_s": statistics.median(segments),
        "segment_line_s": len(frames[0]) * 10 / BAUD,
        "nominal_hop_s": len(image) / SERIAL.throughput,
        "nominal_segment_s": segment_size / SERIAL.throughput,
    }


def limits(hop: float, segment: float, depth: int) -> dict[str, float]:
    return {"store_forward_s": depth * hop, "pipelined_s": hop + depth * segment, "bus_s": depth * hop}


# ---------------------------------------------------------------- serial robot, module processes


def percentile(values: list[float], q: float) -> float:
    """Nearest rank; NaN for no values."""
    if not values:
        return math.nan
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, math.ceil(q * len(ordered)) - 1))]


def lag_stats(lags: list[float]) -> dict[str, Any]:
    n = len(lags)
    return {
        "hormones": n,
        "p50": percentile(lags, 0.50),
        "p99": percentile(lags, 0.99),
        "max": max(lags) if lags else math.nan,
        "within_1_period": sum(lag <= 1.0 for lag in lags) / n if n else math.nan,
        "within_2_periods": sum(lag <= 2.0 for lag in lags) / n if n else math.nan,
    }


def hormone_lags(records: list[dict[str, Any]], n: int, start: float, end: float, origin: float) -> dict[str, Any]:
    """For each module m >= 1 and each hormone it received in [start, end]: the lag (periods)
    since module m-1 received the phase before it (m-1 passed on its next) or, for m = 1, the
    head sent it; the nearest earlier one within MATCH periods. ``unmatched``: arrivals with
    no such upstream; ``missing``: upstream hormones in the window (but its last HOP periods)
    that reached no module within MATCH periods; ``over_hop``: [module, cycles since
    ``origin``, lag] of the arrivals HOP periods or more behind; ``unmatched_at``: [module,
    cycles since ``origin``, phase, the upstream's times of that phase nearby (periods, from
    the arrival)] of the arrivals with no upstream."""
    by_module: dict[int, list[dict[str, Any]]] = defaultdict(list)
    for r in records:
        if r.get("life", 0) == 0:
            by_module[int(r["module"])].append(r)
    # upstream[m]: (t, phase) that module m passes on through back
    upstream: dict[int, list[tuple[float, str]]] = {}
    upstream[0] = sorted((float(r["t"]), str(e["hormone"][2])) for r in by_module[0] for e in r["sent"])
    got: dict[int, list[tuple[float, str]]] = {}
    for m in range(1, n):
        got[m] = sorted((float(r["t"]), str(a["hormone"][2])) for r in by_module[m] for a in r["received"])
        upstream[m] = [(t, NEXT[p]) for t, p in got[m]]
    lags: list[float] = []
    over: list[list[float]] = []
    strays: list[list[Any]] = []
    unmatched = missing = 0
    for m in range(1, n):
        ups: dict[str, list[float]] = defaultdict(list)
        for t, p in upstream[m - 1]:
            ups[p].append(t)
        downs: dict[str, list[float]] = defaultdict(list)
        for t, p in got[m]:
            downs[p].append(t)
        for t, p in got[m]:
            if not start <= t <= end:
                continue
            times = ups[p]
            i = bisect.bisect_left(times, t) - 1  # the latest strictly before
            while i >= 0 and times[i] >= t:
                i -= 1
            if i >= 0 and t - times[i] < MATCH * PERIOD:
                lags.append((t - times[i]) / PERIOD)
                if lags[-1] >= HOP:
                    over.append([m, round((t - origin) / PERIOD, 1), round(lags[-1], 2)])
            else:
                unmatched += 1
                before = [round((u - t) / PERIOD, 2) for u in times if abs(u - t) < MATCH * PERIOD]
                strays.append([m, round((t - origin) / PERIOD, 1), p, before])
        for t, p in upstream[m - 1]:
            if not start <= t <= end - HOP * PERIOD:
                continue
            later = downs[p]
            j = bisect.bisect_right(later, t)
            if j >= len(later) or later[j] - t >= MATCH * PERIOD:
                missing += 1
    return {**lag_stats(lags), "unmatched": unmatched, "missing": missing, "over_hop": over, "unmatched_at": strays}


def stalls(records: list[dict[str, Any]], switched_at: dict[int, float], start: float, end: float) -> dict[str, Any]:
    """Cycles in [start, end] that began more than 1.5 periods after the module's previous
    one (the machine held the process up), by where they fell: within 3 periods after the
    module's switch, or elsewhere; and the longest gap (periods)."""
    by_module: dict[int, list[float]] = defaultdict(list)
    for r in records:
        if r.get("life", 0) == 0:
            by_module[int(r["module"])].append(float(r["t"]))
    at_switch = elsewhere = 0
    longest = 0.0
    for m, times in by_module.items():
        times.sort()
        for a, b in itertools.pairwise(times):
            gap = (b - a) / PERIOD
            if not start <= b <= end or gap <= 1.5:
                continue
            longest = max(longest, gap)
            if m in switched_at and 0 <= b - switched_at[m] <= 3 * PERIOD:
                at_switch += 1
            else:
                elsewhere += 1
    return {"at_switch": at_switch, "elsewhere": elsewhere, "longest_gap_periods": longest}


def silences_after_switch(world: World) -> int:
    """Links the modules' logs say fell silent in or after their switch cycle."""
    switched = switches(world.log)
    index = {name: i for i, name in enumerate(world.topology.names)}
    count = 0
    for line in world.log:
        m = re.match(r"(\S+): cycle (\d+): connector \S+ silent for", line)
        if m and m.group(1) in index and int(m.group(2)) >= switched.get(index[m.group(1)], 1 << 62):
            count += 1
    return count


def counters(world: World) -> list[dict[str, int]]:
    return [{k: int(v) for k, v in dict(view.status.get("counters", {})).items()} for view in world.views]


def delta(after: list[dict[str, int]], before: list[dict[str, int]], key: str) -> list[int]:
    return [a.get(key, 0) - b.get(key, 0) for a, b in zip(after, before, strict=True)]


def at_cycle_start(world: World, pattern: str, before: int = 0) -> dict[int, float]:
    """Module -> the ``t`` (trace record) of the cycle in which its log first says ``pattern``
    (or of the cycle ``before`` cycles earlier)."""
    index = {name: i for i, name in enumerate(world.topology.names)}
    cycle_of: dict[int, int] = {}
    for line in world.log:
        m = re.match(r"(\S+): cycle (\d+): " + pattern, line)
        if m and m.group(1) in index and index[m.group(1)] not in cycle_of:
            cycle_of[index[m.group(1)]] = int(m.group(2))
    starts = {(int(r["module"]), int(r["cycle"])): float(r["t"]) for r in world.records if r.get("life", 0) == 0}
    return {k: starts[(k, c - before)] for k, c in cycle_of.items() if (k, c - before) in starts}


def flash_running_robot(n: int, seed: int, link: dict[str, Any]) -> dict[str, Any]:
    """A snake:n of module processes over serial links at BAUD, flashed through a cable on the
    head's front after WARMUP cycles (see the module docs). Times in seconds from the
    flasher's start; the cable was plugged PLUGGED cycles before."""
    spec = f"snake:{n}"
    out: dict[str, Any] = {"robot": spec, "modules": n, "seed": seed, "medium": f"serial {BAUD:,} baud"}
    progress: list[tuple[float, Progress]] = []
    result: list[FlashResult] = []
    try:
        old, new = compile_file(str(PROGRAM)), caterpillar(20)
        world = World(old, parse_spec(spec), "serial", seed=seed, cycle_period=PERIOD, cycles=100_000, trace=True,
                      stand_in="recording", line_baud=BAUD)  # fmt: skip
    except (DH2Error, OSError) as exc:
        out["error"] = f"{type(exc).__name__}: {exc}"
        return out
    try:
        started = time.monotonic()
        world.start(ready_timeout=120.0)
        out["start_s"] = time.monotonic() - started
        run_world(world, WARMUP)
        assert world.signer is not None
        image = pack(new.image, 2, world.signer)
        before = counters(world)
        warm_from = world._go_at or started
        plug = time.monotonic()
        link_id, path = world.plug_cable(0, FRONT)
        transport = SerialTransport(hello_codec())
        try:
            transport.attach(1, PortEnd(path, baudrate=BAUD))
            pacing, segment, _ = link_pacing("serial", PERIOD, BAUD, 0)
            cable = FlashCable(image, transport, period=PERIOD, pacing=pacing, segment_size=segment)

            def seen(p: Progress) -> None:
                progress.append((time.monotonic(), p))

            def flash() -> None:
                result.append(cable.run(timeout=FLASH_TIMEOUT, progress=seen, progress_every=0.0))

            run_world(world, world.cycle + PLUGGED)  # the head has opened its end of the cable
            thread = threading.Thread(target=flash, daemon=True)
            start = time.monotonic()
            thread.start()
            while thread.is_alive():
                world.tick()
                time.sleep(0.01)
            thread.join(FLASH_TIMEOUT + 5)
        finally:
            transport.close()
            world.unplug_cable(0, FRONT, link_id)
        # until every module switched, and AFTER cycles more for its last records and log lines
        deadline = time.monotonic() + 60.0
        until: int | None = None
        while time.monotonic() < deadline and not world.done():
            world.tick()
            if until is None and len(switches(world.log)) == n:
                until = world.cycle + AFTER
            if until is not None and world.cycle >= until:
                break
            time.sleep(0.01)
        after = counters(world)
    except (DH2Error, OSError) as exc:
        out["error"] = f"{type(exc).__name__}: {exc}"
        out["module_errors"] = [f"{v.name}: {e}" for v in world.views for e in v.errors]
        return out
    finally:
        world.stop()
    flashed = result[0] if result else None
    out["image_bytes"] = len(image)
    out["plugged_before_s"] = start - plug
    out["module_errors"] = [f"{v.name}: {e}" for v in world.views for e in v.errors]
    out["flash_report"] = [m.describe() for m in flashed.modules] if flashed else []
    out["flash_succeeded"] = bool(flashed and flashed.succeeded)
    out["flash_failure"] = flashed.failure if flashed else "no result"
    out["depth"] = max((len(m.path) for m in flashed.modules), default=0) if flashed else 0
    staged_at = at_cycle_start(world, "rollout: image staged")
    staged_after = at_cycle_start(world, "rollout: image staged", before=1)
    switched_at = at_cycle_start(world, "switched to program")
    out["staged_modules"] = len(staged_at)
    out["switched_modules"] = len(switched_at)
    out["staged_by_module_s"] = [staged_at[m] - start if m in staged_at else None for m in range(n)]
    out["switched_by_module_s"] = [switched_at[m] - start if m in switched_at else None for m in range(n)]
    complete = len(staged_at) == n and len(switched_at) == n
    out["staged_s"] = max(staged_at.values()) - start if complete else math.nan
    out["staged_lower_s"] = max(staged_after.values()) - start if complete and len(staged_after) == n else math.nan
    out["switched_s"] = max(switched_at.values()) - start if complete else math.nan
    out["switch_spread_periods"] = (
        (max(switched_at.values()) - min(switched_at.values())) / PERIOD if complete else math.nan
    )

    def first(ok: Callable[[Progress], bool]) -> float:
        return next((t - start for t, p in progress if ok(p)), math.nan)

    out["flasher_first_ack_s"] = first(lambda p: p.bytes_acked > 0)
    out["flasher_heard_staged_s"] = first(lambda p: p.staged >= n)
    out["flasher_heard_committed_s"] = first(lambda p: p.committed >= n)
    depth = out["depth"] or n
    lim = limits(link["hop_s"], link["segment_s"], depth)
    nominal = limits(link["nominal_hop_s"], link["nominal_segment_s"], depth)
    out["limits_s"] = lim
    out["nominal_limits_s"] = nominal
    out["ratio"] = out["staged_s"] / lim["pipelined_s"]
    out["ratio_lower"] = out["staged_lower_s"] / lim["pipelined_s"]
    out["ratio_nominal"] = out["staged_s"] / nominal["pipelined_s"]
    out["ratio_store_forward"] = out["staged_s"] / lim["store_forward_s"]
    end = max(switched_at.values()) if switched_at else time.monotonic()
    records = world.records
    out["hormones_during"] = hormone_lags(records, n, plug, end, start)
    out["hormones_before"] = hormone_lags(records, n, warm_from + 5 * PERIOD, plug, start)
    out["late_cycles_during"] = sum(delta(after, before, "late_cycles"))
    out["stalls_during"] = stalls(records, switched_at, plug, end + AFTER * PERIOD)
    out["late_cycles_before"] = sum(c.get("late_cycles", 0) for c in before)
    out["cycles_during"] = sum(delta(after, before, "cycles"))
    out["links_lost_during"] = sum(delta(after, before, "links_lost"))
    out["links_lost_by_module"] = delta(after, before, "links_lost")
    out["silences"] = [line for line in world.log if "silent for" in line]
    out["links_lost_at_switch"] = silences_after_switch(world)
    h = out["hormones_during"]
    out["hormones_on_time"] = (
        h["hormones"] > 0 and h["missing"] == 0 and h["unmatched"] == 0 and h["max"] < HOP
        and out["links_lost_during"] == 0
    )  # fmt: skip
    return out


def summarise(n: int, runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The runs of one robot: medians of the times, the worst of the hormones' figures."""
    done = [r for r in runs if "error" not in r and r["flash_succeeded"] and math.isfinite(r["staged_s"])]
    out: dict[str, Any] = {"robot": f"snake:{n}", "modules": n, "medium": f"serial {BAUD:,} baud",
                           "how": "processes", "runs": runs, "succeeded": len(done), "tried": len(runs)}  # fmt: skip
    if not done:
        out["error"] = "; ".join(str(r.get("error") or r.get("flash_failure")) for r in runs)
        out["met"] = False
        return out

    def median(key: str) -> float:
        return statistics.median(float(r[key]) for r in done)

    lim = done[0]["limits_s"]
    out["depth"] = done[0]["depth"]
    out["limits_s"] = lim
    out["nominal_limits_s"] = done[0]["nominal_limits_s"]
    for key in ("staged_s", "staged_lower_s", "switched_s", "flasher_first_ack_s", "flasher_heard_staged_s",
                "flasher_heard_committed_s", "switch_spread_periods"):  # fmt: skip
        out[key] = median(key)
    out["ratio"] = out["staged_s"] / lim["pipelined_s"]
    out["ratio_lower"] = out["staged_lower_s"] / lim["pipelined_s"]
    out["ratio_runs"] = [r["ratio"] for r in done]
    out["ratio_nominal"] = out["staged_s"] / out["nominal_limits_s"]["pipelined_s"]
    out["ratio_store_forward"] = out["staged_s"] / lim["store_forward_s"]
    out["staged_by_module_s"] = [
        statistics.median(r["staged_by_module_s"][m] for r in done) for m in range(n)
    ]  # fmt: skip
    during = [r["hormones_during"] for r in done]
    count = max(1, sum(h["hormones"] for h in during))
    out["hormones_during"] = {
        "hormones": sum(h["hormones"] for h in during),
        "p50": statistics.median(h["p50"] for h in during),
        "p99": max(h["p99"] for h in during),
        "max": max(h["max"] for h in during),
        "within_1_period": sum(h["within_1_period"] * h["hormones"] for h in during if h["hormones"]) / count,
        "within_2_periods": sum(h["within_2_periods"] * h["hormones"] for h in during if h["hormones"]) / count,
        "missing": sum(h["missing"] for h in during),
        "unmatched": sum(h["unmatched"] for h in during),
        "over_hop": [[r["seed"], *o] for r in done for o in r["hormones_during"]["over_hop"]],
        "unmatched_at": [[r["seed"], *o] for r in done for o in r["hormones_during"]["unmatched_at"]],
    }
    out["late_cycles_during"] = sum(r["late_cycles_during"] for r in done)
    out["stalls_during"] = {
        "at_switch": sum(r["stalls_during"]["at_switch"] for r in done),
        "elsewhere": sum(r["stalls_during"]["elsewhere"] for r in done),
        "longest_gap_periods": max(r["stalls_during"]["longest_gap_periods"] for r in done),
    }
    out["cycles_during"] = sum(r["cycles_during"] for r in done)
    out["links_lost_during"] = sum(r["links_lost_during"] for r in done)
    out["links_lost_at_switch"] = sum(r["links_lost_at_switch"] for r in done)
    out["hormones_on_time"] = all(r["hormones_on_time"] for r in done)
    out["met"] = len(done) == len(runs) and out["ratio"] <= TARGET and out["hormones_on_time"]
    return out


# ---------------------------------------------------------------- the simulated robot


def simulated(medium: Medium, spec: str, seeds: range, source: str) -> dict[str, Any]:
    images = make_images(source)
    runs = [flash_time(spec, medium, images, seed, True) for seed in seeds]
    staged = statistics.median(r[0] for r in runs)
    switched = statistics.median(r[1] for r in runs)
    depth = runs[0][2]
    size = len(images.v2)
    lim = limits(size / medium.throughput, medium.segment_size / medium.throughput, depth)
    limit = lim["bus_s"] if medium.shared else lim["pipelined_s"]
    return {
        "medium": medium.name,
        "robot": spec,
        "how": "simulated",
        "seeds": list(seeds),
        "depth": depth,
        "image_bytes": size,
        "staged_s": staged,
        "switched_s": switched,
        "staged_runs_s": [r[0] for r in runs],
        "limits_s": lim,
        "limit": "bus" if medium.shared else "pipelined",
        "ratio": staged / limit,
        "met": staged / limit <= TARGET,
    }


# ---------------------------------------------------------------- output


def cycles(seconds: float) -> str:
    return f"{seconds / PERIOD:7.1f}" if math.isfinite(seconds) else f"{'-':>7}"


def table(
    real: list[dict[str, Any]], sims: list[dict[str, Any]], link: dict[str, Any], runs: int, seeds: int
) -> list[str]:
    lines = [
        f"time to flash a {link['image_bytes']}-byte signed image, in cycles of {PERIOD * 1000:.0f} ms from the "
        f"flasher's start (processes: median of {runs} runs) or the entry point's first cycle (simulated: median "
        f"of {seeds} seeds)",
        f"{'medium':20} {'robot':9} {'how':10} {'depth':>5} {'staged':>7} {'switched':>8} {'s&f':>6} {'pipe':>6} "
        f"{'bus':>6} {'ratio':>6} {'nominal':>7}",
    ]
    for r in real:
        if "error" in r:
            lines.append(f"{r['medium']:20} {r['robot']:9} {'processes':10} not run: {r['error']}")
            continue
        lim = r["limits_s"]
        lines.append(
            f"{r['medium']:20} {r['robot']:9} {'processes':10} {r['depth']:5d} {cycles(r['staged_s'])} "
            f"{cycles(r['switched_s']):>8} {lim['store_forward_s'] / PERIOD:6.1f} {lim['pipelined_s'] / PERIOD:6.1f} "
            f"{'-':>6} {r['ratio']:6.2f} {r['ratio_nominal']:7.2f}"
        )
    for s in sims:
        lim = s["limits_s"]
        bus = f"{lim['bus_s'] / PERIOD:6.1f}" if s["limit"] == "bus" else f"{'-':>6}"
        lines.append(
            f"{s['medium']:20} {s['robot']:9} {'simulated':10} {s['depth']:5d} {cycles(s['staged_s'])} "
            f"{cycles(s['switched_s']):>8} {lim['store_forward_s'] / PERIOD:6.1f} {lim['pipelined_s'] / PERIOD:6.1f} "
            f"{bus} {s['ratio']:6.2f} {'':>7}"
        )
    lines.append(
        f"(ratio: staged / limit, the limit pipelined on serial links, the bus on CAN; target <= {TARGET:g}x. "
        "processes: limits from the link measured in this run; nominal: from image / 11,520 bytes/s as in "
        "docs/flashing.md)"
    )
    return lines


def fmt_lags(h: dict[str, Any]) -> str:
    if not h["hormones"]:
        return "no hormones"
    return (
        f"{h['hormones']} hormones, lag p50 {h['p50']:.2f} p99 {h['p99']:.2f} max {h['max']:.2f} periods, "
        f"{h['within_1_period']:.1%} within 1, {h['within_2_periods']:.1%} within 2; "
        f"missing {h['missing']}, unmatched {h['unmatched']}"
        + (
            f"; {HOP}+ periods behind ([seed,] module, cycle from the flasher's start, lag): {h['over_hop']}"
            if h["over_hop"]
            else ""
        )
    )


def show_run(r: dict[str, Any]) -> None:
    where = f"{r['robot']} over serial, seed {r['seed']}"
    if "error" in r:
        print(f"{where}: not run: {r['error']} {r.get('module_errors') or ''}", flush=True)
        return
    staged = ", ".join("-" if s is None else f"{s / PERIOD:.1f}" for s in r["staged_by_module_s"])
    switched = ", ".join("-" if s is None else f"{s / PERIOD:.1f}" for s in r["switched_by_module_s"])
    print(
        f"{where} (modules started in {r['start_s']:.1f} s): flash "
        f"{'succeeded' if r['flash_succeeded'] else 'FAILED: ' + str(r['flash_failure'])}; in cycles from the "
        f"flasher's start: its first ACK {cycles(r['flasher_first_ack_s']).strip()}; staged by module [{staged}]; "
        f"the flasher heard all staged {cycles(r['flasher_heard_staged_s']).strip()}; switched [{switched}] "
        f"(spread {r['switch_spread_periods']:.2f} periods); the flasher heard all committed "
        f"{cycles(r['flasher_heard_committed_s']).strip()}",
        flush=True,
    )
    print(
        f"  staged {cycles(r['staged_s']).strip()} (at least {cycles(r['staged_lower_s']).strip()}): "
        f"{r['ratio']:.2f}x pipelined (at least {r['ratio_lower']:.2f}x), {r['ratio_store_forward']:.2f}x "
        f"store and forward"
    )
    if not r["flash_succeeded"] or r["module_errors"]:
        print(f"  flasher's report: {r['flash_report']}; module errors: {r['module_errors']}")
    print(f"  hormones during the rollout: {fmt_lags(r['hormones_during'])}")
    print(f"  hormones before it (same run): {fmt_lags(r['hormones_before'])}")
    print(
        f"  late cycles during the rollout {r['late_cycles_during']} of {r['cycles_during']} (before it "
        f"{r['late_cycles_before']}; cycles held up > 1.5 periods: {r['stalls_during']['at_switch']} at the switch, "
        f"{r['stalls_during']['elsewhere']} elsewhere, longest {r['stalls_during']['longest_gap_periods']:.1f} "
        f"periods), links lost during it {r['links_lost_during']}"
        f"{' ' + str(r['silences']) if r['silences'] else ''}; hormones on time: "
        f"{'yes' if r['hormones_on_time'] else 'NO'}",
        flush=True,
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Time to flash 8 and 20 modules over serial links and CAN")
    parser.add_argument("--quick", action="store_true", help="snake:4 on serial, one simulated seed (smoke test)")
    args = parser.parse_args(argv)
    from hil.pace import realtime_problem

    began = time.monotonic()
    load_before = os.getloadavg()
    realtime = realtime_problem()
    source = PROGRAM.read_text(encoding="utf-8")
    sizes = (4,) if args.quick else (8, 20)
    specs = ("snake:8",) if args.quick else ("snake:8", "snake:20")
    seeds = range(1) if args.quick else range(5)
    process_seeds = range(1) if args.quick else range(PROCESS_SEEDS)
    probe_image = pack(caterpillar(20).image, 2, make_images(source).key)
    link = measure_link(probe_image, 3 if args.quick else 5)
    print(
        f"one hop at {BAUD:,} baud, measured (link emulator, pyserial): {link['segments']} segment frames, "
        f"{link['wire_bytes']} bytes on the wire, {link['hop_s'] * 1000:.1f} ms (line: "
        f"{link['hop_line_s'] * 1000:.1f} ms; image / 11,520 B/s: {link['nominal_hop_s'] * 1000:.1f} ms); "
        f"one segment {link['segment_s'] * 1000:.1f} ms (line: {link['segment_line_s'] * 1000:.1f} ms)",
        flush=True,
    )
    real: list[dict[str, Any]] = []
    for n in sizes:
        runs = []
        for seed in process_seeds:
            r = flash_running_robot(n, seed, link)
            runs.append(r)
            show_run(r)
        real.append(summarise(n, runs))
    sims: list[dict[str, Any]] = []
    for medium in (SERIAL, CAN):
        for spec in specs:
            sims.append(simulated(medium, spec, seeds, source))
    lines = table(real, sims, link, len(process_seeds), len(seeds))
    print("\n".join(lines))
    done = [r for r in real if "error" not in r]
    for r in done:
        st = r["stalls_during"]
        print(
            f"{r['robot']} over serial, {r['succeeded']} of {r['tried']} runs flashed: hormones during the rollout: "
            f"{fmt_lags(r['hormones_during'])}; late cycles {r['late_cycles_during']} of {r['cycles_during']} "
            f"(held up > 1.5 periods: {st['at_switch']} at the switch, {st['elsewhere']} elsewhere, longest "
            f"{st['longest_gap_periods']:.1f}), links lost {r['links_lost_during']} ({r['links_lost_at_switch']} "
            f"at or after the switch): "
            f"{'on time' if r['hormones_on_time'] else 'NOT on time'}"
        )
    met = {
        "serial_processes": bool(done) and all(r["met"] for r in done),
        "serial_processes_ratio": bool(done) and all(r["ratio"] <= TARGET for r in done),
        "serial_processes_flashed": bool(done) and all(r["succeeded"] == r["tried"] for r in done),
        "serial_processes_hormones_on_time": bool(done) and all(r["hormones_on_time"] for r in done),
        "can_simulated": all(s["met"] for s in sims if s["limit"] == "bus"),
        "serial_simulated": all(s["met"] for s in sims if s["limit"] == "pipelined"),
    }
    print(
        f"target: staged within {TARGET:g}x of the pipelined limit (serial) or the bus limit (CAN), hormones on "
        f"time meanwhile: " + ", ".join(f"{k} {'met' if v else 'NOT met'}" for k, v in met.items())
    )
    load_after = os.getloadavg()
    print(
        f"machine: {os.cpu_count()} CPUs, load average (1, 5, 15 min) {', '.join(f'{x:.2f}' for x in load_before)} "
        f"before, {', '.join(f'{x:.2f}' for x in load_after)} after; keeps real time: "
        f"{'no: ' + realtime if realtime else 'yes (hil.pace probe)'}"
    )
    result = {
        "bench": "flash",
        "quick": args.quick,
        "period_ms": PERIOD * 1000,
        "baud": BAUD,
        "target_ratio": TARGET,
        "hop_bound_periods": HOP,
        "machine_realtime_problem": realtime,
        "cpus": os.cpu_count(),
        "load_average_before": list(load_before),
        "load_average_after": list(load_after),
        "link": link,
        "serial_processes": real,
        "simulated": sims,
        "met": met,
        "elapsed_s": time.monotonic() - began,
    }
    print(json.dumps(strict_json(result)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
