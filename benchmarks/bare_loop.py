"""The footprint benchmark's baseline (benchmarks/bench_footprint.py): a bare cycle loop with
pyserial or python-can alone, sending what a caterpillar module sends, on the same links.

Run as a script, never imported by dh2rt: ``python benchmarks/bare_loop.py SPEC``, where SPEC
is a JSON object: kind ("serial" or "udp"), period (s), status (file), status_every,
edges_ms (the lateness histogram's bucket edges), group (udp), ports (each: serial "path";
udp "filter" [can_id, mask]; and "hello", "keepalive", "hormone" (or null): hex of the serial
bytes, or lists of [arbitration_id, hex data] CAN frames). It imports nothing but the
standard library and its link library, so that what it costs is the floor dh2rt is measured
against.
"""

from __future__ import annotations

import bisect
import json
import math
import os
import signal
import sys
import time
from collections import deque
from collections.abc import Callable
from typing import Any


class SerialLinks:
    """One pyserial port per connector."""

    def __init__(self, ports: list[dict[str, Any]]) -> None:
        import serial

        self.links = [serial.Serial(p["path"], baudrate=115200, timeout=0, write_timeout=0.5) for p in ports]
        self.refused: tuple[type[BaseException], ...] = (serial.SerialException, OSError)

    def frames(self, value: str | None) -> Any:
        return None if value is None else bytes.fromhex(value)

    def send(self, i: int, frame: Any) -> None:
        self.links[i].write(frame)

    def receive(self) -> int:
        return sum(s.read(4096).count(0) for s in self.links)

    def close(self) -> None:
        for s in self.links:
            s.close()


class UdpBus:
    """One python-can udp_multicast bus for all the connectors."""

    def __init__(self, ports: list[dict[str, Any]], group: str) -> None:
        import can

        self.can = can
        self.bus = can.Bus(interface="udp_multicast", channel=group, fd=False)
        # no set_filters: with them, recv(timeout=0) returns None at the first frame they drop
        self.wanted = [tuple(p["filter"]) for p in ports]
        self.refused: tuple[type[BaseException], ...] = (can.CanError, OSError)

    def frames(self, value: list[list[Any]] | None) -> Any:
        if value is None:
            return None
        return [self.can.Message(arbitration_id=a, data=bytes.fromhex(d), is_extended_id=True) for a, d in value]

    def send(self, _i: int, frame: Any) -> None:
        for msg in frame:
            self.bus.send(msg, timeout=0.2)

    def receive(self) -> int:
        got = 0
        while (msg := self.bus.recv(timeout=0.0)) is not None:
            got += any(msg.arbitration_id & mask == can_id for can_id, mask in self.wanted)
        return got

    def close(self) -> None:
        self.bus.shutdown()


class Loop:
    """The cycle loop and its status file (the fields a dh2rt module's status has)."""

    def __init__(self, spec: dict[str, Any], links: SerialLinks | UdpBus) -> None:
        self.spec = spec
        self.links = links
        self.plan = [
            (links.frames(p["hello"]), links.frames(p["keepalive"]), links.frames(p["hormone"])) for p in spec["ports"]
        ]
        self.lateness: deque[float] = deque(maxlen=4096)
        self.edges_ms: list[float] = spec["edges_ms"]
        self.edges = [e / 1000 for e in self.edges_ms]
        self.counts = [0] * (len(self.edges) + 1)
        self.cycle = self.received = self.send_failed = 0
        self.first: float | None = None

    def status(self, final: bool = False) -> None:
        ordered = sorted(self.lateness)
        n = len(ordered)

        def rank(q: float) -> float:
            return round(ordered[min(n - 1, max(0, math.ceil(q * n) - 1))] * 1000, 3)

        late = {"p50": rank(0.5), "p99": rank(0.99), "max": round(ordered[-1] * 1000, 3)} if n else None
        body = {
            "cycle": self.cycle, "first_cycle_at": self.first, "final": final, "received": self.received,
            "send_failed": self.send_failed, "lateness_ms": late,
            "lateness_hist": {"edges_ms": self.edges_ms, "counts": self.counts},
        }  # fmt: skip
        tmp = self.spec["status"] + ".tmp"
        with open(tmp, "w") as f:
            f.write(json.dumps(body))
        os.replace(tmp, self.spec["status"])

    def run(self, stopped: Callable[[], bool]) -> None:
        period: float = self.spec["period"]
        deadline = time.monotonic()
        while not stopped():
            now = time.monotonic()
            self.lateness.append(now - deadline)
            self.counts[bisect.bisect_left(self.edges, now - deadline)] += 1
            if self.first is None:
                self.first = now
            if now - deadline > period / 2:
                deadline = now
            self.received += self.links.receive()
            for i, (hello, keepalive, hormone) in enumerate(self.plan):
                try:  # a refused write is counted, as dh2rt counts it (a relay starved of CPU fills up)
                    if self.cycle == 0:
                        self.links.send(i, hello)
                    elif hormone is not None and self.cycle % 10 == 0:
                        self.links.send(i, hormone)
                    else:
                        self.links.send(i, keepalive)
                except self.links.refused:
                    self.send_failed += 1
            self.cycle += 1
            if self.cycle % self.spec["status_every"] == 0:
                self.status()
            deadline += period
            left = deadline - time.monotonic()
            if left > 0:
                time.sleep(left)
        self.status(final=True)


def main(argv: list[str]) -> int:
    spec: dict[str, Any] = json.loads(argv[1])
    stop: list[int] = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    ports = spec["ports"]
    links: SerialLinks | UdpBus = SerialLinks(ports) if spec["kind"] == "serial" else UdpBus(ports, spec["group"])
    Loop(spec, links).run(lambda: bool(stop))
    links.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
