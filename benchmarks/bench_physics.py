"""Physics stand-in speed: real-time factor of caterpillar snakes, and frame capture time.

For snakes of 8 and 20 modules at the stated physics rate (headless, DIRECT) this runs the
paper's caterpillar schedule (Table I, ``sim.gaits``) through :class:`sim.world.World` and,
in the same run, through a plain PyBullet loop over the very same bodies and constraints
(``setJointMotorControl2`` when a target changes, ``stepSimulation`` in a loop). The ratio
World / plain is the cost of the World layer. The gait matters for speed: contacts dominate
PyBullet's step time, and a crawling snake has far fewer of them than one lying flat, so both
loops run the same gait from the same start.

The sensors-on variant runs the World loop again reading every sensor of every module once a
cycle, as a physics run does for a program that declares them all (:mod:`sim.sensors`: IMU,
infrared with its ray casts, ground contact, joint positions and loads; each value rounded and
clamped to the profile's range), so sensors / plain is what sensing costs on top.

Run: ``python -m benchmarks.bench_physics [--quick]``. The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import tempfile
import time
from pathlib import Path

import pybullet as p

from dh2rt.profile import CONRO
from dh2rt.topology import parse_spec
from firmware.motion.gaits import caterpillar_schedule
from sim.gaits import CLOCK_CYCLE, STEPS_PER_CYCLE, run_caterpillar
from sim.record import Recorder
from sim.sensors import PhysicsSensors, physics_sensor_names
from sim.world import World

#: Real-time factor goals from the brief.
TARGET_RTF = {8: 20.0, 20: 8.0}
SETTLE_CYCLES = CLOCK_CYCLE  # one gait period before timing, so the gait is under way


def _time_world(n: int, hz: float, cycles: int) -> float:
    """Steps per second of World + run_caterpillar."""
    with World(parse_spec(f"snake:{n}"), physics_hz=hz) as w:
        run_caterpillar(w, SETTLE_CYCLES)
        t0 = time.perf_counter()
        run_caterpillar(w, cycles, first_cycle=SETTLE_CYCLES)
        elapsed = time.perf_counter() - t0
    return cycles * STEPS_PER_CYCLE / elapsed


def _time_sensors(n: int, hz: float, cycles: int) -> float:
    """Steps per second of World + run_caterpillar reading every module's every sensor each cycle."""
    with World(parse_spec(f"snake:{n}"), physics_hz=hz) as w:
        sensors = PhysicsSensors(w, physics_sensor_names(w.model))
        specs = [CONRO.sensor(name) for name in sensors.names]
        modules = list(range(n))
        values = [[0] * len(specs) for _ in modules]  # what the engines' S would hold

        def sense(_cycle: int) -> None:
            for m, readings in sensors.read(modules).items():
                row = values[m]
                for i, spec in enumerate(specs):
                    row[i] = spec.reading(readings[spec.name])

        run_caterpillar(w, SETTLE_CYCLES, on_step=sense)
        t0 = time.perf_counter()
        run_caterpillar(w, cycles, first_cycle=SETTLE_CYCLES, on_step=sense)
        elapsed = time.perf_counter() - t0
    return cycles * STEPS_PER_CYCLE / elapsed


def _time_plain(n: int, hz: float, cycles: int) -> float:
    """Steps per second of a bare PyBullet loop over the same bodies and constraints."""
    with World(parse_spec(f"snake:{n}"), physics_hz=hz) as w:
        run_caterpillar(w, SETTLE_CYCLES)
        cid = w.client
        bodies = [w.body(m) for m in range(n)]
        lim = w.model.dof1
        force, speed = lim.max_torque_nm, math.radians(lim.max_speed_dps)
        table = [caterpillar_schedule(n, c, CLOCK_CYCLE) for c in range(SETTLE_CYCLES, SETTLE_CYCLES + cycles)]
        last = table[0][:]
        step, motor, pos = p.stepSimulation, p.setJointMotorControl2, p.POSITION_CONTROL
        t0 = time.perf_counter()
        for row in table:
            for m, target in enumerate(row):
                if target != last[m]:
                    last[m] = target
                    motor(
                        bodies[m],
                        0,
                        pos,
                        targetPosition=math.radians(target),
                        force=force,
                        maxVelocity=speed,
                        physicsClientId=cid,
                    )
            for _ in range(STEPS_PER_CYCLE):
                step(physicsClientId=cid)
        elapsed = time.perf_counter() - t0
    return cycles * STEPS_PER_CYCLE / elapsed


def _time_frames(n: int, frames: int, tmp_gif: str) -> float:
    """Median milliseconds of one captured 320x240 frame (ER_TINY_RENDERER, fixed camera) of an
    n-module snake: each capture timed alone (render, painted floor, overlay, GIF encoding), the
    median so that a moment of load on the machine does not count."""
    with World(parse_spec(f"snake:{n}")) as w:
        rec = Recorder(w, path=Path(tmp_gif), size=(320, 240))
        rec.capture()  # warm-up: the palette and the floor image
        times = []
        for _ in range(frames):
            w.step(rec.steps_per_frame)
            t0 = time.perf_counter()
            rec.capture()
            times.append(time.perf_counter() - t0)
        rec.save()
    return statistics.median(times) * 1000.0


def _travel_per_period(n: int, periods: int, seed: int) -> float:
    """Metres the centroid moves forward per gait period (after one period to settle)."""
    with World(parse_spec(f"snake:{n}"), seed=seed) as w:
        run_caterpillar(w, SETTLE_CYCLES)
        start = w.centroid()
        run_caterpillar(w, periods * CLOCK_CYCLE, first_cycle=SETTLE_CYCLES)
        return w.travel(start) / periods


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_physics", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="a few seconds: short runs, one repeat")
    parser.add_argument("--hz", type=float, default=240.0, help="physics rate (default 240)")
    parser.add_argument("--periods", type=int, default=4, help="gait periods timed per run (default 4)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per figure, best kept (default 3)")
    args = parser.parse_args(argv)
    if args.periods < 1 or args.repeats < 1 or not 30.0 <= args.hz <= 10_000.0:
        parser.error("--periods and --repeats must be >= 1 and --hz within 30..10000")
    periods, repeats = (1, 1) if args.quick else (args.periods, args.repeats)
    cycles = periods * CLOCK_CYCLE
    hz = args.hz
    print(
        f"physics {hz:g} Hz, control cycle {STEPS_PER_CYCLE} steps, ClockCycle {CLOCK_CYCLE}, "
        f"{periods} gait period(s) timed, best of {repeats}"
    )
    result: dict[str, object] = {"bench": "physics", "physics_hz": hz, "quick": args.quick}
    for n in (8, 20):
        world_best = plain_best = sensors_best = 0.0
        for _ in range(repeats):  # interleaved, so drift in machine load hits all alike
            world_best = max(world_best, _time_world(n, hz, cycles))
            plain_best = max(plain_best, _time_plain(n, hz, cycles))
            sensors_best = max(sensors_best, _time_sensors(n, hz, cycles))
        rtf, plain_rtf, sensors_rtf = world_best / hz, plain_best / hz, sensors_best / hz
        ok = rtf >= TARGET_RTF[n]
        sensors_ok = sensors_rtf >= TARGET_RTF[n]
        print(
            f"snake:{n:<2}  World {world_best:8.0f} steps/s = {rtf:5.1f}x real time "
            f"(target >= {TARGET_RTF[n]:g}x: {'met' if ok else 'MISSED'}); "
            f"plain PyBullet {plain_best:8.0f} steps/s = {plain_rtf:5.1f}x; "
            f"World/plain {rtf / plain_rtf:.2f}"
        )
        print(
            f"snake:{n:<2}  World with every sensor {sensors_best:8.0f} steps/s = {sensors_rtf:5.1f}x real time "
            f"(target >= {TARGET_RTF[n]:g}x: {'met' if sensors_ok else 'MISSED'}); "
            f"sensors/plain {sensors_rtf / plain_rtf:.2f}"
        )
        result[f"snake{n}"] = {
            "steps_per_s": round(world_best),
            "rtf": round(rtf, 2),
            "plain_rtf": round(plain_rtf, 2),
            "ratio_vs_plain": round(rtf / plain_rtf, 3),
            "target_rtf": TARGET_RTF[n],
            "met": ok,
            "sensors_rtf": round(sensors_rtf, 2),
            "sensors_ratio_vs_plain": round(sensors_rtf / plain_rtf, 3),
            "sensors_met": sensors_ok,
        }
    seeds = (0,) if args.quick else (0, 1, 2)
    travel: dict[str, list[float]] = {}
    for n in (5, 8, 20):
        travel[str(n)] = [round(_travel_per_period(n, periods, s), 4) for s in seeds]
        figures = ", ".join(f"{v * 100:.1f}" for v in travel[str(n)])
        print(f"snake:{n:<2}  forward travel per gait period (seeds {seeds}): {figures} cm")
    result["travel_m_per_period"] = travel
    with tempfile.TemporaryDirectory() as tmp:
        frame_ms = _time_frames(8, 3 if args.quick else 20, f"{tmp}/b.gif")
    print(f"frame capture 320x240 ER_TINY_RENDERER, snake:8: {frame_ms:.1f} ms per frame")
    result["frame_ms_320x240"] = round(frame_ms, 2)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
