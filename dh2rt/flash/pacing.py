"""How much of a module's links a rollout may take each cycle (:func:`link_pacing`).

A file of its own so that a module can check, when it boots, that its lines can carry a
rollout at all (and say why not) without loading the rollout's state machines
(:mod:`dh2rt.flash.rollout`), which it loads only once an image concerns it
(:mod:`firmware.flash.door`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from dh2rt.wire.can_frames import CLASSIC_DATA
from dh2rt.wire.sizes import MAX_PATH, MAX_REASON, MAX_VERDICT, can_cost, can_frame_bits, serial_cost

#: Share of a serial line's bytes per cycle the rollout may take (hormones keep the rest).
SERIAL_SHARE = 0.8
#: Segment size on serial links (92 bytes on the wire each) and on a CAN bus (8 frames).
SERIAL_SEGMENT = 80
CAN_SEGMENT = 56
#: The share of a serial line's nominal rate a rollout times its frames at (``Pacing.rate``):
#: a line runs a little slower than nominal (the link emulator carried the image's 35.0 ms of
#: bytes in 36.1 ms in benchmarks/bench_flash.py), and a frame timed to be out just before the
#: next tick must not still be on the line when the hormones go.
SERIAL_TIMING = 0.95
#: Bits per cycle a module may spend on a shared CAN bus, as a share of the bus.
CAN_SHARE = 0.3
#: A COMMIT's payload, for its transit time.
_COMMIT_BYTES = 15
#: The largest control frame: a REPORT with the longest path, verdict and reason.
LARGEST_CONTROL = 12 + 1 + MAX_PATH + 1 + MAX_VERDICT + 1 + MAX_REASON


def _bytes(n: int) -> int:
    return n


@dataclass(frozen=True, slots=True)
class Pacing:
    """How much a module may send per cycle: ``budget`` link units per connector (or per
    module when ``shared``: every connector on one bus), a frame of n bytes costing
    ``cost(n)`` units (:func:`dh2rt.wire.transfer.serial_cost`: bytes on a serial line;
    :func:`~dh2rt.wire.transfer.can_cost`: worst-case bits on a CAN bus).

    ``rate``: the line's own units per second (:data:`SERIAL_TIMING` of its nominal rate),
    when the module's frames have the line to themselves (a serial connector): a frame sent
    between ticks is timed out at it, so that one that is out before the next tick goes
    now. 0 (a shared bus, whose frames wait for the others' arbitration; or unknown): timed
    at the budget's rate, ``budget`` units per period, slower than the line."""

    budget: int
    cost: Callable[[int], int] = _bytes
    shared: bool = False
    rate: float = 0.0


def link_pacing(transport: str, period: float, baudrate: int, bitrate: int) -> tuple[Pacing, int, float]:
    """The rollout's pacing, segment size and COMMIT transit time on this module's links:
    a share of each serial line's bytes per cycle, or of a CAN bus's bits per cycle.
    Raises ValueError, naming the line and the period, when that share of a cycle cannot
    carry the largest transfer frame (a slow line at a short period)."""
    if transport == "serial":
        per_cycle = int(baudrate / 10 * period * SERIAL_SHARE)
        _check_share(per_cycle, serial_cost, SERIAL_SEGMENT, "bytes", f"a {baudrate}-baud serial line", period)
        pacing = Pacing(per_cycle, serial_cost, rate=baudrate / 10 * SERIAL_TIMING)
        return pacing, SERIAL_SEGMENT, serial_cost(_COMMIT_BYTES) * 10 / baudrate
    per_cycle = int(bitrate * period * CAN_SHARE)
    _check_share(per_cycle, can_cost, CAN_SEGMENT, "bits", f"a {bitrate} bit/s CAN bus", period)
    # a train is timed by its first frame (dh2rt.wire.can_frames.Reassembler.started)
    first = can_frame_bits(min(_COMMIT_BYTES, CLASSIC_DATA))
    return Pacing(per_cycle, can_cost, shared=True), CAN_SEGMENT, first / bitrate


def _check_share(per_cycle: int, cost: Callable[[int], int], segment: int, unit: str, line: str, period: float) -> None:
    largest = cost(max(segment + 6, LARGEST_CONTROL))
    if per_cycle < largest:
        raise ValueError(
            f"{line} gives a rollout {per_cycle} {unit} per {period * 1000:g} ms cycle; its largest transfer "
            f"frame takes {largest}: use a faster line or a longer cycle"
        )
