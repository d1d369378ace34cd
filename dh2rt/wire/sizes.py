"""Sizes of the transfer family that every module needs without its messages: the wire
limits a rollout's frames keep to, and what a frame of n bytes costs a serial line or a CAN
bus (:mod:`dh2rt.flash.pacing` budgets a rollout with them at boot). :mod:`dh2rt.wire.transfer`
re-exports them.
"""

from __future__ import annotations

from dh2rt.wire.can_frames import CHECK_BYTES, CLASSIC_DATA

#: Longest path an OFFER or a REPORT carries: rollouts reach modules up to this deep.
MAX_PATH = 64
#: Longest verdict (ASCII) and reason (UTF-8, cut at a character boundary) a frame carries.
MAX_VERDICT = 16
MAX_REASON = 48
#: Highest connector number a transfer frame's sender field and path hops can name.
MAX_CONNECTOR = 15

#: Serial framing's overhead per frame: CRC-32 (4), COBS code byte (1), delimiter (1).
SERIAL_OVERHEAD = 6


def serial_cost(payload: int) -> int:
    """Bytes a frame of ``payload`` bytes takes on a serial link (COBS + CRC-32 + delimiter)."""
    return payload + SERIAL_OVERHEAD + (payload + 4) // 254


def can_frame_bits(data: int) -> int:
    """Worst-case bits of one extended-id CAN frame with ``data`` bytes, stuffing and the
    interframe space included: 67 + 8n + floor((53 + 8n) / 4)."""
    return 67 + 8 * data + (53 + 8 * data) // 4


def can_cost(payload: int) -> int:
    """Worst-case bus bits a frame of ``payload`` bytes takes on classic CAN: one frame, or a
    segment train carrying the payload and its check (:mod:`dh2rt.wire.can_frames`)."""
    if payload > CLASSIC_DATA:
        payload += CHECK_BYTES
    full, rest = divmod(payload, CLASSIC_DATA)
    return full * can_frame_bits(CLASSIC_DATA) + (can_frame_bits(rest) if rest else 0)
