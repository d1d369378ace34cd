"""Servo bus round trips through the Protocol 2.0 emulator on a pty, against a raw pty echo.

Measured with the real dynamixel-sdk: (1) one GroupSyncWrite of two goal positions plus one
GroupSyncRead of two present positions, (2) one PING, (3) the same cycle through
DynamixelDriver (set_targets + read_positions). The baseline, measured in the same run, is a
thread echoing the same byte counts through a pty pair (write the request bytes, get the reply
bytes back): the floor that the pty and the thread handoff set. Run:

    python -m benchmarks.bench_servo [--quick] [--iterations N]

The last line of output is one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import statistics
import sys
import threading
import time
import tty
from collections.abc import Callable
from typing import Any

SYNC_WRITE_BYTES = 7 + 1 + 4 + 2 * (1 + 4) + 2  # header/id/len, inst, addr+len, 2x(id+data), crc
SYNC_READ_BYTES = 7 + 1 + 4 + 2 + 2  # ... addr+len, two ids, crc
SYNC_READ_REPLY_BYTES = 2 * (7 + 1 + 1 + 4 + 2)  # two status packets with 4 data bytes each
PING_BYTES, PING_REPLY_BYTES = 10, 14


def _timed(fn: Callable[[], object], iterations: int, warmup: int) -> dict[str, float]:
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(iterations):
        start = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - start)
    samples.sort()
    return {
        "median_us": statistics.median(samples) * 1e6,
        "mean_us": statistics.fmean(samples) * 1e6,
        "p99_us": samples[min(len(samples) - 1, int(len(samples) * 0.99))] * 1e6,
    }


class _PtyEcho:
    """Reads ``request`` bytes from a pty master and answers ``reply`` bytes, in a thread."""

    def __init__(self, request: int, reply: int) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.request, self.reply = request, bytes(reply)
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        got = 0
        while True:
            ready, _, _ = select.select([self.master, self._wake_r], [], [])
            if self._wake_r in ready:
                return
            got += len(os.read(self.master, 4096))
            if got >= self.request:
                got -= self.request
                os.write(self.master, self.reply)

    def close(self) -> None:
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=5)
        for fd in (self.master, self.slave, self._wake_r, self._wake_w):
            os.close(fd)


def _echo_round_trip(
    requests: tuple[int, ...], reply: int, iterations: int, warmup: int, *, busy: bool = False
) -> dict[str, float]:
    """The pty echo. ``busy`` polls with zero-timeout reads as dynamixel-sdk does, instead of
    blocking in select: it shows how much of the emulator's figure is the SDK's busy wait
    competing with the emulator thread for the GIL."""
    import serial

    echo = _PtyEcho(sum(requests), reply)
    port = serial.Serial(echo.path, baudrate=1_000_000, timeout=0 if busy else 1.0)
    chunks = [bytes(n) for n in requests]

    def cycle() -> None:
        port.reset_input_buffer()
        for chunk in chunks:
            port.write(chunk)
        got = port.read(reply)
        deadline = time.monotonic() + 1.0
        while len(got) < reply and time.monotonic() < deadline:
            got += port.read(reply - len(got))
        if len(got) != reply:
            raise RuntimeError("pty echo lost bytes")

    try:
        return _timed(cycle, iterations, warmup)
    finally:
        port.close()
        echo.close()


def _emulator_round_trips(iterations: int, warmup: int) -> dict[str, dict[str, float]]:
    from dynamixel_sdk import GroupSyncRead, GroupSyncWrite, PacketHandler, PortHandler

    from drivers.dynamixel import DynamixelDriver
    from hil.servo_emulator import ServoEmulator

    results: dict[str, dict[str, float]] = {}
    with ServoEmulator((1, 2)) as emu:
        port = PortHandler(emu.port_path)
        if not port.setBaudRate(1_000_000):
            raise RuntimeError(f"cannot open {emu.port_path}")
        ph = PacketHandler(2.0)
        writer = GroupSyncWrite(port, ph, 116, 4)
        reader = GroupSyncRead(port, ph, 132, 4)
        for dxl_id in (1, 2):
            writer.addParam(dxl_id, list((2048).to_bytes(4, "little")))
            reader.addParam(dxl_id)

        # A reply can miss the SDK's timeout when the emulator thread waits for the GIL (both
        # live in this process): such round trips are counted, not fatal, and reported.
        failures = {"sync": 0, "ping": 0}

        def sync_cycle() -> None:
            if writer.txPacket() != 0 or reader.txRxPacket() != 0:
                failures["sync"] += 1

        def ping() -> None:
            if ph.ping(port, 1)[1] != 0:
                failures["ping"] += 1

        try:
            results["sync"] = _timed(sync_cycle, iterations, warmup)
            results["ping"] = _timed(ping, iterations, warmup)
            for name, count in failures.items():
                results[name]["failed"] = float(count)
        finally:
            port.closePort()
        with DynamixelDriver(emu.port_path) as driver:

            def driver_cycle() -> None:
                driver.set_targets(10.0, -10.0)
                driver.read_positions()

            results["driver"] = _timed(driver_cycle, iterations, warmup)
        if emu.error is not None:
            raise RuntimeError(f"emulator failed: {emu.error!r}")
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_servo", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="a few hundred cycles (seconds)")
    parser.add_argument("--iterations", type=int, default=None, help="cycles per figure")
    args = parser.parse_args(argv)
    iterations = args.iterations or (200 if args.quick else 3000)
    if iterations <= 0:
        parser.error(f"--iterations must be positive, got {iterations}")
    warmup = max(10, iterations // 20)

    emulated = _emulator_round_trips(iterations, warmup)
    sync_requests = (SYNC_WRITE_BYTES, SYNC_READ_BYTES)
    baseline_sync = _echo_round_trip(sync_requests, SYNC_READ_REPLY_BYTES, iterations, warmup)
    baseline_ping = _echo_round_trip((PING_BYTES,), PING_REPLY_BYTES, iterations, warmup)
    busy_sync = _echo_round_trip(sync_requests, SYNC_READ_REPLY_BYTES, iterations, warmup, busy=True)

    def row(name: str, fig: dict[str, float], base: dict[str, float]) -> dict[str, Any]:
        ratio = fig["median_us"] / base["median_us"]
        print(
            f"{name:<34} median {fig['median_us']:8.1f} us  mean {fig['mean_us']:8.1f} us  "
            f"p99 {fig['p99_us']:8.1f} us   {ratio:5.2f}x the pty echo "
            f"({base['median_us']:.1f} us)"
        )
        return {**{k: round(v, 1) for k, v in fig.items()}, "ratio_vs_echo": round(ratio, 2)}

    print(f"servo bus round trips, {iterations} cycles each, Python {sys.version.split()[0]}")
    report: dict[str, Any] = {
        "benchmark": "servo",
        "iterations": iterations,
        "sync_write_plus_sync_read": row("sync write + sync read (2 servos)", emulated["sync"], baseline_sync),
        "ping": row("ping", emulated["ping"], baseline_ping),
        "driver_set_targets_plus_read_positions": row("DynamixelDriver set+read", emulated["driver"], baseline_sync),
        "baseline_echo_sync_bytes": {k: round(v, 1) for k, v in baseline_sync.items()},
        "baseline_echo_ping_bytes": {k: round(v, 1) for k, v in baseline_ping.items()},
        "echo_sync_bytes_busy_polling": row("pty echo, busy-polling client", busy_sync, baseline_sync),
        "bytes": {
            "sync_request": SYNC_WRITE_BYTES + SYNC_READ_BYTES,
            "sync_reply": SYNC_READ_REPLY_BYTES,
            "ping_request": PING_BYTES,
            "ping_reply": PING_REPLY_BYTES,
        },
    }
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
