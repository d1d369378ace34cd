"""``python -m benchmarks [--quick] [NAME ...]``: run the benchmarks one after another.

Each benchmark prints its figures and, as its last line, one JSON object; this runner runs
each in its own process (so one's memory and threads do not colour the next) and ends with
a JSON list of those objects.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def available() -> list[str]:
    return sorted(p.stem.removeprefix("bench_") for p in HERE.glob("bench_*.py"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description="Run dh2rt's benchmarks.")
    parser.add_argument("names", nargs="*", help=f"which to run (default: all of {', '.join(available())})")
    parser.add_argument("--quick", action="store_true", help="a few seconds each (smoke test)")
    args = parser.parse_args(argv)
    names = args.names or available()
    unknown = sorted(set(names) - set(available()))
    if unknown:
        parser.error(f"unknown benchmark(s): {', '.join(unknown)}")
    results = []
    failed = 0
    for name in names:
        print(f"== {name}", flush=True)
        started = time.perf_counter()
        cmd = [sys.executable, "-m", f"benchmarks.bench_{name}", *(["--quick"] if args.quick else [])]
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=HERE.parent)
        out = proc.stdout.strip().splitlines()
        for line in out[:-1]:
            print(line)
        try:
            results.append(json.loads(out[-1]) if out else {"benchmark": name, "error": "no output"})
        except json.JSONDecodeError:
            results.append({"benchmark": name, "error": "last line is not JSON"})
        if proc.returncode != 0:
            failed += 1
            print(proc.stderr.strip()[-2000:], file=sys.stderr)
        print(f"   ({time.perf_counter() - started:.1f} s, exit {proc.returncode})", flush=True)
    print(json.dumps(results))
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
