"""The overhead tracker's accuracy at 1 m, on frames PyBullet renders (tools.tracker.accuracy).

Scenes: free markers at random poses over the whole field (as rendered; then blurred and
noised as a lens and a sensor would), and robots as sim.world.World lays them out (a marker on
each module, each frame the robot turned and shifted by its seed). For each: markers placed and
missed, position error (mm) and heading error (degrees), max and median, and the seconds a
frame took to render and to detect. The camera: 1280 x 960 pixels, 40 degrees of vertical
field, 1 m over the floor (about 0.74 mm a pixel; a 20 mm marker spans 27 pixels).

    python -m benchmarks.bench_tracker [--quick]

The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from typing import Any

from benchmarks import strict_json
from tools.tracker.accuracy import Accuracy, measure_free, measure_robot


def report(name: str, found: Accuracy) -> dict[str, Any]:
    summary = found.summary()
    position, heading = summary["position_error_mm"], summary["heading_error_deg"]
    print(
        f"{name:<34} {found.placed - found.missed:>4}/{found.placed:<4} "
        f"{position['max']:>7.2f} {position['median']:>7.2f} {heading['max']:>7.2f} {heading['median']:>7.2f} "
        f"{summary['render_s_per_frame']:>7.3f} {summary['detect_s_per_frame']:>7.4f}"
    )
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_tracker", description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="one frame of each scene (a smoke test)")
    args = parser.parse_args(argv)
    frames = 1 if args.quick else 10
    robot_frames = 1 if args.quick else 4
    columns = ("pos max", "pos med", "hd max", "hd med", "render", "detect")
    print(f"{'scene':<34} {'found':>9} " + " ".join(f"{c:>7}" for c in columns))
    print(f"{'':<34} {'':>9} " + " ".join(f"{u:>7}" for u in ("mm", "mm", "deg", "deg", "s", "s")))
    out: dict[str, Any] = {"camera": {"width_px": 1280, "height_px": 960, "fov_deg": 40.0, "height_m": 1.0}}
    out["free"] = report("free markers, as rendered", measure_free(frames, 10, seed=0))
    out["free_blur_0.8_noise_4"] = report(
        "free, blur 0.8 px, noise 4 levels", measure_free(frames, 10, seed=0, blur_px=0.8, noise=4.0)
    )
    out["free_blur_1.2_noise_8"] = report(
        "free, blur 1.2 px, noise 8 levels", measure_free(frames, 10, seed=0, blur_px=1.2, noise=8.0)
    )
    for topology in ("snake:8", "dragon", "quadruped"):
        out[topology] = report(f"{topology} (World, settled)", measure_robot(topology, robot_frames, seed=1))
    print(json.dumps(strict_json(out)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
