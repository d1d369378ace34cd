"""Wire-format figures: frames and bytes per caterpillar hop, what a multi-frame hormone costs
on CAN (its segment train's check included; baseline: the same payload cut without one, as
before wire version 3), codec throughput vs json/pickle.

Run: ``python -m benchmarks.bench_wire [--quick]``. Prints absolute figures, ratios against
baselines measured in the same run (json and pickle of the same hormone), and one JSON
object as its last line.
"""

from __future__ import annotations

import argparse
import json
import pickle
import time
from collections.abc import Callable
from typing import Any

from dh2rt.hormone import Hormone, HormoneSpec, ParamSpec, Vocabulary
from dh2rt.testing import CONTRACT_VOCABULARY, collect, contract_codec
from dh2rt.wire.can_frames import CLASSIC_DATA, Reassembler, segment
from dh2rt.wire.frame import FrameCodec
from dh2rt.wire.serial_framing import SerialDecoder, encode_serial
from dh2rt.wire.sizes import can_frame_bits

CATERPILLAR = Vocabulary([HormoneSpec(0, "X", (ParamSpec("a", ("A", "B")),))])
CAT = Hormone("X", ("A",))
#: A reply that crossed 8 links and travels back along a route: a "typical" larger hormone.
ROUTED = Hormone("P", (-1234, 99, "down"), tuple((2, 1) for _ in range(8)), tuple(1 for _ in range(8)))
#: Multi-frame hormones: issue 27's N(100, 200, 300) (P here: two integers and an atom, one
#: hop), the routed reply, and the largest hormone frame (255-hop path and route).
MULTI = {
    "p_one_hop": Hormone("P", (100, 200, "up"), ((1, 2),)),
    "routed8": ROUTED,
    "largest": Hormone("P", (-(2**31), -(2**31), "down"), ((1, 2),) * 255, (1,) * 255),
}


def _multi_frame_costs(codec: FrameCodec) -> dict[str, Any]:
    """Per multi-frame hormone: payload bytes, classic CAN frames, data bytes and worst-case
    bus bits, now (a segment train with its check) and cut without a check (the baseline)."""
    out: dict[str, Any] = {}
    for label, hormone in MULTI.items():
        payload = codec.encode(2, hormone)
        frames = segment(payload, 1, 0)
        unchecked = [len(payload[i : i + CLASSIC_DATA]) for i in range(0, len(payload), CLASSIC_DATA)]
        bits = sum(can_frame_bits(len(f.data)) for f in frames)
        base_bits = sum(can_frame_bits(n) for n in unchecked)
        out[label] = {
            "payload_bytes": len(payload),
            "can_frames": len(frames),
            "can_data_bytes": sum(len(f.data) for f in frames),
            "can_bus_bits": bits,
            "unchecked_can_frames": len(unchecked),
            "unchecked_can_data_bytes": len(payload),
            "unchecked_can_bus_bits": base_bits,
            "bits_vs_unchecked": round(bits / base_bits, 3),
        }
    return out


def _rate(fn: Callable[[], object], n: int) -> float:
    """Calls per second of ``fn`` over ``n`` calls (best of three runs)."""
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        best = min(best, time.perf_counter() - t0)
    return n / best


def _as_dict(h: Hormone) -> dict[str, Any]:
    return {
        "sender": 2,
        "name": h.name,
        "args": list(h.args),
        "path": [list(p) for p in h.path],
        "route": None if h.route is None else list(h.route),
    }


def _transport_rate(name: str, n: int) -> float:
    """Frames per second, one link, send then poll, through a real transport."""
    from dh2rt.transport.base import BusEnd
    from dh2rt.transport.registry import open_transport

    codec = contract_codec()
    opts: dict[str, Any] = {"channel": f"bench-{name}-{time.monotonic_ns()}"}
    with open_transport(name, codec, **opts) as a, open_transport(name, codec, **opts) as b:
        a.attach(2, BusEnd(1, 0))
        b.attach(1, BusEnd(1, 1))
        t0 = time.perf_counter()
        got = 0
        for i in range(n):
            a.send(2, CAT)
            if i % 100 == 99:
                got += len(b.poll())
        got += len(collect(b, n - got, 5.0))
        dt = time.perf_counter() - t0
    if got != n:
        raise RuntimeError(f"{name}: {got} of {n} frames arrived")
    return n / dt


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_wire", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="few iterations (a few seconds)")
    args = parser.parse_args(argv)
    n = 3_000 if args.quick else 50_000
    nt = 500 if args.quick else 5_000

    cat_codec = FrameCodec(CATERPILLAR, 4)
    cat_payload = cat_codec.encode(2, CAT)
    can_frames = segment(cat_payload, link_id=1, side=0)
    serial_bytes = encode_serial(cat_payload)
    codec = FrameCodec(CONTRACT_VOCABULARY, 4)
    routed_payload = codec.encode(2, ROUTED)

    results: dict[str, Any] = {
        "caterpillar_frame_bytes": len(cat_payload),
        "can_frames_per_caterpillar_hop": len(can_frames),
        "can_data_bytes_per_caterpillar_hop": sum(len(f.data) for f in can_frames),
        "serial_bytes_per_caterpillar_hop": len(serial_bytes),
        "routed8_frame_bytes": len(routed_payload),
        "routed8_json_bytes": len(json.dumps(_as_dict(ROUTED), separators=(",", ":"))),
        "routed8_pickle_bytes": len(pickle.dumps(_as_dict(ROUTED))),
        "routed8_can_frames": len(segment(routed_payload, 1, 0)),
        "routed8_serial_bytes": len(encode_serial(routed_payload)),
        "multi_frame": _multi_frame_costs(codec),
    }

    for label, h, c in (("caterpillar", CAT, cat_codec), ("routed8", ROUTED, codec)):
        payload = c.encode(2, h)
        d = _as_dict(h)
        js = json.dumps(d)
        pk = pickle.dumps(d)
        ours = _rate(lambda: c.decode(c.encode(2, h)), n)  # noqa: B023 (runs in this iteration)
        jsr = _rate(lambda: json.loads(json.dumps(d)), n)  # noqa: B023
        pkr = _rate(lambda: pickle.loads(pickle.dumps(d)), n)  # noqa: B023
        results[f"{label}_codec_roundtrips_per_s"] = round(ours)
        results[f"{label}_json_roundtrips_per_s"] = round(jsr)
        results[f"{label}_pickle_roundtrips_per_s"] = round(pkr)
        results[f"{label}_vs_json"] = round(ours / jsr, 3)
        results[f"{label}_vs_pickle"] = round(ours / pkr, 3)
        del payload, js, pk

    dec = SerialDecoder()
    results["serial_frame_roundtrips_per_s"] = round(_rate(lambda: dec.feed(encode_serial(cat_payload)), n))
    reasm = Reassembler()

    def can_round() -> None:
        for f in segment(routed_payload, 1, 0):
            reasm.feed(f.arbitration_id, f.data)

    results["can_routed8_segment_reassemble_per_s"] = round(_rate(can_round, n))
    results["inproc_frames_per_s"] = round(_transport_rate("inproc", nt))
    results["virtual_can_frames_per_s"] = round(_transport_rate("virtual", nt))
    # A classic extended-id frame costs 67 bits of overhead (incl. interframe space) plus its
    # data, before bit stuffing: the most caterpillar frames a 1 Mbit/s bus can carry.
    bus_rate = 1e6 / (67 + 8 * len(cat_payload))
    results["can_1mbit_caterpillar_frames_per_s"] = round(bus_rate)
    results["codec_headroom_vs_1mbit_can"] = round(results["caterpillar_codec_roundtrips_per_s"] / bus_rate, 1)
    results["targets_met"] = (
        results["can_frames_per_caterpillar_hop"] == 1 and results["serial_bytes_per_caterpillar_hop"] <= 12
    )

    r = results
    print("dh2rt wire benchmark" + (" (quick)" if args.quick else ""))
    print(
        f"  caterpillar X(A): {r['caterpillar_frame_bytes']} B frame, "
        f"{r['can_frames_per_caterpillar_hop']} classic CAN frame "
        f"({r['can_data_bytes_per_caterpillar_hop']} data bytes), "
        f"{r['serial_bytes_per_caterpillar_hop']} B on serial (target <= 12)"
    )
    print(
        f"  routed reply, 8 hops: {r['routed8_frame_bytes']} B frame vs "
        f"{r['routed8_json_bytes']} B json, {r['routed8_pickle_bytes']} B pickle; "
        f"{r['routed8_can_frames']} CAN frames, {r['routed8_serial_bytes']} B serial"
    )
    for label, m in r["multi_frame"].items():
        print(
            f"  multi-frame {label} ({m['payload_bytes']} B): {m['can_frames']} CAN frames, "
            f"{m['can_data_bytes']} data bytes, {m['can_bus_bits']} bus bits worst case; without a check "
            f"{m['unchecked_can_frames']} frames, {m['unchecked_can_data_bytes']} bytes, "
            f"{m['unchecked_can_bus_bits']} bits (ratio {m['bits_vs_unchecked']})"
        )
    for label in ("caterpillar", "routed8"):
        print(
            f"  {label} encode+decode: {r[label + '_codec_roundtrips_per_s']:,}/s; "
            f"json {r[label + '_json_roundtrips_per_s']:,}/s (ratio {r[label + '_vs_json']}), "
            f"pickle {r[label + '_pickle_roundtrips_per_s']:,}/s "
            f"(ratio {r[label + '_vs_pickle']})"
        )
    print(
        f"  a 1 Mbit/s CAN bus carries at most {r['can_1mbit_caterpillar_frames_per_s']:,} "
        f"caterpillar frames/s: codec headroom {r['codec_headroom_vs_1mbit_can']}x"
    )
    print(f"  serial COBS+CRC frame encode+decode: {r['serial_frame_roundtrips_per_s']:,}/s")
    print(f"  CAN segment+reassemble (routed 8 hops): {r['can_routed8_segment_reassemble_per_s']:,}/s")
    print(
        f"  transport send+poll: inproc {r['inproc_frames_per_s']:,} frames/s, "
        f"python-can virtual {r['virtual_can_frames_per_s']:,} frames/s"
    )
    print(json.dumps(results, sort_keys=True))
    return 0 if results["targets_met"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
