"""``dh2rt stats CAPTURE``: frames per second per link and kind, the load they put on a
classic CAN bus (or on each serial link), errors and losses.

Bus load is computed as can-utils' ``canbusload`` does, per frame from its length, with the
worst-case bit stuffing of an extended-id classic frame: ``67 + 8n + floor((53 + 8n) / 4)``
bits for ``n`` data bytes (the 54 + 8n stuffed bits from SOF to the CRC get at most one stuff
bit per 4), against ``--bitrate`` (default 1 Mbit/s). A serial link's load is its bytes (10
bits each on a UART: start, 8 data, stop) against ``--baud`` (default 115,200), per link and
direction. Counting uses numpy over blocks of frame sizes, so memory stays constant.
"""

from __future__ import annotations

import argparse
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from dh2rt.cmdline import EXIT_OK, EXIT_USAGE, err
from dh2rt.errors import CaptureError
from tools.capture_reader import CanRecord, Record, read_records
from tools.decode import decode
from tools.reading import PROGRAM_HELP, interruptible, options_and_capture

#: Frame sizes are summed in numpy blocks of this many frames.
BLOCK = 65536
UART_BITS_PER_BYTE = 10


def frame_bits(data_bytes: np.ndarray) -> np.ndarray:
    """Bits on the wire of extended-id classic frames with ``data_bytes`` bytes, worst-case stuffing."""
    n = data_bytes.astype(np.int64)
    return 67 + 8 * n + (53 + 8 * n) // 4


class _Tally:
    """Counts of a capture's records, in constant memory."""

    def __init__(self) -> None:
        self.first: float | None = None
        self.last: float | None = None
        self.can_frames = 0
        self.can_bits = 0
        self.serial_frames = 0
        self.serial_bytes: Counter[tuple[int, int]] = Counter()  # (link, side) -> bytes
        self.lost = 0
        self._sizes = np.zeros(BLOCK, dtype=np.int64)
        self._filled = 0

    def tap(self, records: Iterable[Record]) -> Iterator[Record]:
        for rec in records:
            t = rec.timestamp  # file order need not be time order: the span is min to max
            self.first = t if self.first is None else min(self.first, t)
            self.last = t if self.last is None else max(self.last, t)
            if isinstance(rec, CanRecord):
                self.can_frames += 1
                self._sizes[self._filled] = len(rec.data)
                self._filled += 1
                if self._filled == BLOCK:
                    self._sum()
            else:
                self.serial_frames += 1
                self.serial_bytes[(rec.link, rec.side)] += len(rec.wire)
                self.lost += rec.lost
            yield rec
        self._sum()

    def _sum(self) -> None:
        self.can_bits += int(frame_bits(self._sizes[: self._filled]).sum())
        self._filled = 0

    @property
    def span(self) -> float:
        if self.first is None or self.last is None:
            return 1e-9
        return (self.last - self.first) or 1e-9


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dh2rt stats",
        description="Frames per second per link and kind, bus load, errors and losses of a capture.",
    )
    p.add_argument("capture", type=Path, help="a pcapng or pcap, or a python-can log")
    p.add_argument("--program", type=Path, help=PROGRAM_HELP)
    p.add_argument(
        "--bitrate", type=positive_int, default=1_000_000, help="CAN bus bitrate in bit/s (default: 1000000)"
    )
    p.add_argument("--baud", type=positive_int, default=115_200, help="serial links' baud rate (default: 115200)")
    return p


def positive_int(text: str) -> int:
    """A rate the load is divided by: a whole number above 0 (argparse names the option)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{value}: must be 1 or more (a rate the load is divided by)")
    return value


@interruptible
def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    started = options_and_capture(parser, argv)
    if isinstance(started, int):
        return started
    ns, capture = started
    tally = _Tally()
    per: Counter[tuple[str, int | None, str]] = Counter()
    try:
        for hop in decode(tally.tap(read_records(capture.path)), capture.programs):
            per[(hop.medium, hop.link, hop.kind)] += 1
    except CaptureError as exc:
        err(str(exc))
        return EXIT_USAGE
    frames = tally.can_frames + tally.serial_frames
    if not frames:
        err(f"{ns.capture}: no frames in it")
        return EXIT_OK
    span = tally.span
    print(f"{ns.capture}: {frames} frames in {span:.3f} s ({frames / span:,.1f} frames/s)")
    if tally.can_frames:
        bits = tally.can_bits
        print(
            f"CAN bus load at {ns.bitrate:,} bit/s, worst-case stuffing: {bits / span / ns.bitrate:.1%} ({bits:,} bits)"
        )
    if tally.serial_bytes:
        busiest = max(tally.serial_bytes.items(), key=lambda kv: kv[1])
        (busy_link, busy_side), nbytes = busiest
        load = nbytes * UART_BITS_PER_BYTE / span / ns.baud
        print(f"serial links at {ns.baud:,} baud: busiest is link {busy_link} side {busy_side}, {load:.1%} of its line")
    print(f"{'medium':<7} {'link':>6} {'kind':<10} {'frames':>8} {'per s':>9}")
    for (medium, link, kind), count in sorted(
        per.items(), key=lambda kv: (kv[0][0], kv[0][1] is None, kv[0][1] or 0, kv[0][2])
    ):
        shown = "?" if link is None else str(link)
        print(f"{medium:<7} {shown:>6} {kind:<10} {count:>8} {count / span:>9.1f}")
    errors = sum(c for (_m, _l, k), c in per.items() if k == "error")
    print(f"errors: {errors} frame(s) that did not decode; lost: {tally.lost} serial frame(s) never delivered")
    return EXIT_OK
