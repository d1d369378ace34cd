"""Reproducible measurements; each prints ratios against a baseline run in the same process."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any


def strict_json(value: Any) -> Any:
    """``value`` with every infinite or NaN float as null (a p99 beyond the last bucket, a
    ratio of two of them), so that a benchmark's last line is JSON that any reader takes."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [strict_json(v) for v in value]
    return value


def seeds_arg(parser: argparse.ArgumentParser, text: str) -> list[int]:
    """``--seeds`` given as comma-separated integers; a clear usage error (exit 2) otherwise."""
    try:
        return [int(s) for s in text.split(",")]
    except ValueError:
        parser.error(f"--seeds: expected comma-separated integers, got {text!r}")


def jobs_arg(parser: argparse.ArgumentParser, jobs: int) -> int:
    """``--jobs`` checked: at least 1, a clear usage error (exit 2) otherwise."""
    if jobs < 1:
        parser.error("--jobs must be at least 1")
    return jobs


def run_variants(
    jobs: int,
    cases: Sequence[tuple[str, Callable[..., dict[str, Any]], tuple[Any, ...]]],
    describe: Callable[[str, dict[str, Any]], str],
) -> dict[str, list[dict[str, Any]]] | None:
    """Run ``cases`` (variant name, function, arguments: one world each) ``jobs`` at a time in
    their own processes, printing ``describe(name, result)`` as each is taken, in order; the
    results by variant name, or None on Ctrl-C (the caller exits 130)."""
    results: dict[str, list[dict[str, Any]]] = {}
    try:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            futures = [(name, pool.submit(fn, *args)) for name, fn, args in cases]
            for i, (name, future) in enumerate(futures, 1):
                r = future.result()
                results.setdefault(name, []).append(r)
                print(f"[{i}/{len(cases)}] {describe(name, r)}", flush=True)
    except KeyboardInterrupt:
        return None
    return results
