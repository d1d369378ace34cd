"""Reproducible measurements; each prints ratios against a baseline run in the same process."""

from __future__ import annotations

import argparse
import math
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
