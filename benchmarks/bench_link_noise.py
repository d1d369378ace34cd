"""Residual error rate of the serial link layer under random noise (Monte-Carlo).

Run: ``python -m benchmarks.bench_link_noise [--quick]``. Random payloads (2..24 bytes) are
framed, put on an idle line (``00 frame 00``) and sent through a binary symmetric channel
(every bit flipped with probability ``--ber``); the line is decoded and every payload that
comes out different from the one sent is a *false accept*. The baseline, on lines damaged
by the same channel, is serial framing version 1 (CRC-16/CCITT-FALSE, no final XOR). Its false
accepts split into *structural* ones, the sent payload with bytes added or cut at its end
(the delimiter turned into ``01``: plus one byte; that and the idle zero after it: plus the
CRC; the COBS byte of a zero CRC low byte turned into ``00``: minus one byte), which a CRC
without a final XOR lets through whatever the data, and the rest (chance, at most about 2^-16
per damaged frame). Prints the figures and one JSON object as its last line.
"""

from __future__ import annotations

import argparse
import binascii
import json
import math
import random

from dh2rt.errors import FrameCorrupted
from dh2rt.wire.serial_framing import CRC_BYTES, SerialDecoder, cobs_decode, cobs_encode, encode_serial


def encode_v1(payload: bytes) -> bytes:
    """Serial framing version 1, the baseline: COBS(payload ‖ CRC-16/CCITT-FALSE big-endian) ‖ 00."""
    return cobs_encode(payload + binascii.crc_hqx(payload, 0xFFFF).to_bytes(2, "big")) + b"\x00"


def decode_v1(line: bytes) -> list[bytes]:
    """Version 1's decoder on a whole line: every delimited frame whose COBS and CRC hold."""
    out = []
    for raw in line.split(b"\x00")[:-1]:  # what follows the last delimiter is no frame yet
        if not raw:
            continue
        try:
            body = cobs_decode(raw)
        except FrameCorrupted:
            continue
        if len(body) > 2 and binascii.crc_hqx(body[:-2], 0xFFFF) == int.from_bytes(body[-2:], "big"):
            out.append(body[:-2])
    return out


def damage(line: bytes, ber: float, rng: random.Random) -> bytes:
    """``line`` through a binary symmetric channel: gaps between flipped bits are geometric."""
    bad = bytearray(line)
    bits = 8 * len(bad)
    log_keep = math.log1p(-ber)
    pos = int(math.log(1.0 - rng.random()) / log_keep)
    while pos < bits:
        bad[pos >> 3] ^= 1 << (pos & 7)
        pos += 1 + int(math.log(1.0 - rng.random()) / log_keep)
    return bytes(bad)


def upper_95(events: int, trials: int) -> float:
    """One-sided 95 % upper bound on a rate seen ``events`` times in ``trials`` (rule of three at 0)."""
    if trials == 0:
        return 1.0
    return (3.0 if events == 0 else events + 2.0 * math.sqrt(events) + 2.0) / trials


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_link_noise", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="20,000 frames (a smoke test)")
    parser.add_argument("--frames", type=int, default=1_000_000, help="frames to send (default 1,000,000)")
    parser.add_argument("--ber", type=float, default=0.01, help="bit error rate of the channel (default 0.01)")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    trials = 20_000 if args.quick else args.frames
    rng = random.Random(args.seed)

    damaged = {"v1": 0, "v2": 0}
    false_accepts = {"v1": 0, "v2": 0}
    v1_structural = 0
    for _ in range(trials):
        payload = rng.randbytes(rng.randint(2, 24))
        for version, encode in (("v2", encode_serial), ("v1", encode_v1)):
            line = b"\x00" + encode(payload) + b"\x00"
            bad = damage(line, args.ber, rng)
            if bad == line:
                continue
            damaged[version] += 1
            bad += b"\x00"  # the idle line goes on: whatever the noise left open ends here
            got = SerialDecoder().feed(bad) if version == "v2" else decode_v1(bad)
            wrong = [p for p in got if p != payload]
            if wrong:
                false_accepts[version] += 1
                if version == "v1" and all(p.startswith(payload) or payload.startswith(p) for p in wrong):
                    v1_structural += 1

    v1_chance = false_accepts["v1"] - v1_structural
    results = {
        "ber": args.ber,
        "frames": trials,
        "fcs_bits": 8 * CRC_BYTES,
        "v2_damaged_frames": damaged["v2"],
        "v2_false_accepts": false_accepts["v2"],
        "v2_false_accept_rate_upper95": upper_95(false_accepts["v2"], damaged["v2"]),
        "v2_model_rate": 2.0 ** -(8 * CRC_BYTES),
        "v1_damaged_frames": damaged["v1"],
        "v1_false_accepts": false_accepts["v1"],
        "v1_structural_accepts": v1_structural,
        "v1_chance_accepts": v1_chance,
        "v1_chance_rate": v1_chance / max(damaged["v1"], 1),
        "v1_model_rate": 2.0**-16,
    }
    r = results
    print("dh2rt serial link under random noise" + (" (quick)" if args.quick else ""))
    print(f"  {trials:,} random payloads of 2..24 bytes on an idle line, bit error rate {args.ber}")
    print(
        f"  version 2 (CRC-32 FCS): {r['v2_damaged_frames']:,} damaged, {r['v2_false_accepts']} passed "
        f"(95 % bound {r['v2_false_accept_rate_upper95']:.1e} per damaged frame; "
        f"model 2^-32 = {r['v2_model_rate']:.1e})"
    )
    print(
        f"  version 1 (CRC-16, no final XOR, baseline): {r['v1_damaged_frames']:,} damaged, "
        f"{r['v1_false_accepts']:,} passed: {v1_structural:,} as the payload with bytes added or cut at "
        f"its end, {v1_chance} by chance ({r['v1_chance_rate']:.1e} per damaged frame; "
        f"model 2^-16 = {r['v1_model_rate']:.1e})"
    )
    print(json.dumps(results, sort_keys=True))
    return 0 if false_accepts["v2"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
