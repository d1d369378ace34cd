"""``dh2rt stats CAPTURE --program PROGRAM``: frames per second per link and kind, the load
they put on a classic CAN bus, errors and losses.

Bus load is computed as can-utils' ``canbusload`` does, per frame from its length, with the
worst-case bit stuffing of an extended-id classic frame: ``67 + 8n + floor((53 + 8n) / 4)``
bits for ``n`` data bytes (the 54 + 8n stuffed bits from SOF to the CRC get at most one stuff
bit per 4), against ``--bitrate`` (default 1 Mbit/s). Counting uses numpy over the frames'
times and sizes.
"""

from __future__ import annotations

import argparse
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from dh2rt.cmdline import EXIT_OK, EXIT_USAGE, err
from dh2rt.errors import CaptureError
from tools.can_decode import decode_can
from tools.capture_files import CanRecord, read_can
from tools.reading import options_and_program


def frame_bits(data_bytes: np.ndarray) -> np.ndarray:
    """Bits on the wire of extended-id classic frames with ``data_bytes`` bytes, worst-case stuffing."""
    n = data_bytes.astype(np.int64)
    return 67 + 8 * n + (53 + 8 * n) // 4


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dh2rt stats",
        description="Frames per second per link and kind, bus load, errors and losses of a CAN capture.",
    )
    p.add_argument("capture", type=Path, help="a pcap (link type 227) or a python-can log")
    p.add_argument("--program", type=Path, required=True, help="the .dh2 program the robot ran")
    p.add_argument("--bitrate", type=int, default=1_000_000, help="bus bitrate in bit/s (default: 1000000)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    started = options_and_program(parser, argv)
    if isinstance(started, int):
        return started
    ns, program = started
    times: list[float] = []
    sizes: list[int] = []
    per: Counter[tuple[int | None, str]] = Counter()

    def tapped(records: Iterable[CanRecord]) -> Iterator[CanRecord]:
        for rec in records:
            times.append(rec.timestamp)
            sizes.append(len(rec.data))
            yield rec

    try:
        for hop in decode_can(tapped(read_can(ns.capture)), program.vocabulary, program.profile):
            per[(hop.link, hop.kind)] += 1
    except CaptureError as exc:
        err(str(exc))
        return EXIT_USAGE
    if not times:
        err(f"{ns.capture}: no CAN frames in it")
        return EXIT_OK
    t = np.asarray(times)
    span = float(t.max() - t.min()) or 1e-9
    bits = int(frame_bits(np.asarray(sizes)).sum())
    print(f"{ns.capture}: {len(times)} frames in {span:.3f} s ({len(times) / span:,.1f} frames/s)")
    print(f"bus load at {ns.bitrate:,} bit/s, worst-case stuffing: {bits / span / ns.bitrate:.1%} ({bits:,} bits)")
    print(f"{'link':>6} {'kind':<10} {'frames':>8} {'per s':>9}")
    for (link, kind), count in sorted(per.items(), key=lambda kv: (kv[0][0] is None, kv[0][0] or 0, kv[0][1])):
        shown = "?" if link is None else str(link)
        print(f"{shown:>6} {kind:<10} {count:>8} {count / span:>9.1f}")
    errors = sum(c for (_l, k), c in per.items() if k == "error")
    print(f"errors: {errors} frame(s) that did not decode")
    return EXIT_OK
