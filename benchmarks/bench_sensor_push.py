"""What pushing physics readings to the module processes costs the loop's world, per cycle.

In the loop with ``--stand-in pybullet`` the world, every world cycle, measures each module's
IMU, infrared pairs and ground contact in its PyBullet world (``sim.sensors``), rounds them to
the profile's ranges and sends each module one ``readings`` command, a JSON line on the
module's stdin (``hil.world.World.push_readings``). This measures that work on snakes of 8
and 20 modules, the physics stand-in as the loop builds it (servo emulators on ptys
included), writing each command's line to a pipe as ``ProcessModule.send`` does, and, in the
same run as the baseline, what the world's physics costs per cycle anyway
(``PhysicsStandIn.advance`` of one 20 ms cycle: ``STEPS_PER_CYCLE`` steps). Times are CPU
time of this process, so other work on the machine does not count.

Run: ``python -m benchmarks.bench_sensor_push [--cycles N] [--quick]``. The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import time

from dh2rt.profile import CONRO
from dh2rt.topology import parse_spec
from firmware.control import Readings, command_to_json
from hil.physics_stand_in import PhysicsStandIn
from sim.gaits import STEPS_PER_CYCLE

#: What a program that declares every sensor physics can give has the world measure.
SENSORS = CONRO.sensor_names


def measure(modules: int, cycles: int) -> dict[str, float]:
    stand_in = PhysicsStandIn(parse_spec(f"snake:{modules}"))
    read_fd, write_fd = os.pipe()
    os.set_blocking(read_fd, False)
    try:
        names = stand_in.measure(SENSORS)
        specs = {n: CONRO.sensor(n) for n in names}
        everyone = list(range(modules))
        physics = push = 0.0
        pipe = os.fdopen(write_fd, "w", closefd=False)
        for _ in range(cycles):
            t0 = time.process_time()
            with stand_in.lock:
                stand_in.world.step(STEPS_PER_CYCLE)
            t1 = time.process_time()
            for values in stand_in.readings(everyone).values():
                cmd = Readings({n: specs[n].reading(v) for n, v in values.items()})
                pipe.write(json.dumps(command_to_json(cmd)) + "\n")
                pipe.flush()
            t2 = time.process_time()
            while True:  # drain the pipe as the module processes would
                try:
                    if not os.read(read_fd, 1 << 16):
                        break
                except BlockingIOError:
                    break
            physics += t1 - t0
            push += t2 - t1
        return {
            "modules": modules,
            "sensors": len(names),
            "physics_ms_per_cycle": round(physics / cycles * 1000, 3),
            "push_ms_per_cycle": round(push / cycles * 1000, 3),
            "push_over_physics": round(push / physics, 3),
        }
    finally:
        os.close(read_fd)
        os.close(write_fd)
        stand_in.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=200, help="world cycles timed per robot (default: 200)")
    ap.add_argument("--quick", action="store_true", help="20 cycles, for smoke tests")
    ns = ap.parse_args()
    if ns.quick:
        ns.cycles = 20
    rows = [measure(n, ns.cycles) for n in (8, 20)]
    for r in rows:
        print(
            f"snake:{r['modules']}: {r['sensors']} sensors pushed, {r['push_ms_per_cycle']:.3f} ms per cycle "
            f"against {r['physics_ms_per_cycle']:.3f} ms of physics ({r['push_over_physics']:.2f}x)"
        )
    print(json.dumps({"bench": "sensor_push", "cycles": ns.cycles, "robots": rows}))


if __name__ == "__main__":
    main()
