"""Flashing a running robot in the loop: 8 module processes on serial links run the
caterpillar, a signed image with another ClockCycle comes in through a programming cable on
the head's free front connector mid-run, and every module switches at one agreed cycle.

What the test reads is what the modules say: their trace records (``t`` on CLOCK_MONOTONIC,
one clock for every process), their log lines, their status, and the flasher's report.
"""

from __future__ import annotations

import itertools
import re
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from dh2rt.compiler import compile_file, compile_source
from dh2rt.rollout import Outcome, link_pacing
from dh2rt.signed_image import pack
from dh2rt.topology import parse_spec
from dh2rt.transport.base import PortEnd
from dh2rt.transport.serial_link import SerialTransport
from drivers.flash_cable import FlashCable, FlashResult, hello_codec
from hil.world import World, module_pids

ROOT = Path(__file__).resolve().parents[2]
PROGRAM = ROOT / "examples" / "caterpillar.dh2"
TABLE_I = {"A": -45.0, "B": -45.0, "C": 45.0, "D": 45.0}
NEXT = {"A": "B", "B": "C", "C": "D", "D": "A"}
N = 8
PERIOD = 0.02
FRONT = 1  # CONRO's front connector: the head's is free
HOP = 3  # periods a hormone may take over one serial hop on a loaded machine


def caterpillar(clock_cycle: int) -> Any:
    text = PROGRAM.read_text(encoding="utf-8")
    return compile_source(text.replace("const ClockCycle = 40", f"const ClockCycle = {clock_cycle}"))


def flash_through_cable(world: World, module: int, image: bytes, *, timeout: float = 60.0) -> FlashResult:
    """Plug a cable into ``module``'s front, run the flasher on it until it is done (the
    world ticking meanwhile), pull the cable out; the flasher's result."""
    link_id, path = world.plug_cable(module, FRONT)
    transport = SerialTransport(hello_codec())
    transport.attach(1, PortEnd(path))
    pacing, segment, _ = link_pacing("serial", PERIOD, 115200, 0)
    cable = FlashCable(image, transport, period=PERIOD, pacing=pacing, segment_size=segment)
    out: list[FlashResult] = []
    thread = threading.Thread(target=lambda: out.append(cable.run(timeout=timeout)), daemon=True)
    try:
        thread.start()
        while thread.is_alive():
            world.tick()
            time.sleep(0.01)
    finally:
        thread.join(timeout + 5)
        transport.close()
        world.unplug_cable(module, FRONT, link_id)
    return out[0]


def run_world(world: World, until_cycle: int) -> None:
    while world.cycle < until_cycle and not world.done():
        world.tick()
        time.sleep(0.01)


def switches(world: World) -> dict[int, int]:
    """Module -> the cycle (its own count) at which it switched, from its log."""
    out: dict[int, int] = {}
    for line in world.log:
        m = re.match(r"m(\d+): cycle (\d+): switched to program", line)
        if m:
            out[int(m.group(1))] = int(m.group(2))
    return out


def world_cycle(world: World, module: int, cycle: int) -> int:
    """The world cycle in which ``module``'s ``cycle`` began, from its trace record's time."""
    (rec,) = [r for r in world.records if r["module"] == module and r["cycle"] == cycle and r.get("life", 0) == 0]
    assert world._go_at is not None
    return round((rec["t"] - world._go_at) / PERIOD)


def head_emissions(records: list[dict[str, Any]]) -> list[int]:
    return [r["cycle"] for r in sorted(records, key=lambda r: r["cycle"]) if r["module"] == 0 and r["sent"]]


@pytest.mark.xfail(
    strict=False,
    reason="never seen to run to the end: on the loaded machine (load 22 on 2 cores) the 8 module "
    "processes were not ready within the world's 30 s",
)
@pytest.mark.parametrize("seed", [0, 3])
def test_eight_modules_switch_at_one_cycle_and_the_wave_goes_on_at_the_new_period(seed: int) -> None:
    old, new = compile_file(str(PROGRAM)), caterpillar(20)
    total = 900
    world = World(old, parse_spec(f"snake:{N}"), "serial", seed=seed, cycle_period=PERIOD, cycles=total,
                  trace=True, stand_in="recording")  # fmt: skip
    try:
        world.start()
        run_world(world, 60)
        assert world.signer is not None
        image = pack(new.image, 2, world.signer)
        result = flash_through_cable(world, 0, image)
        run_world(world, total + 10)
        world.stop()
        pids = module_pids(world)
    finally:
        world.stop()
    report = {m.path: m for m in result.modules}
    assert result.succeeded, (result.failure, [m.describe() for m in result.modules], world.log[-40:])
    # every module named by its path from the cable: front>front ... one hop further each
    assert sorted(len(p) for p in report) == list(range(1, N + 1))
    assert all(m.outcome in (Outcome.COMMITTED, Outcome.CONFIRMED) and m.version == 2 for m in report.values())
    switched = switches(world)
    assert sorted(switched) == list(range(N)), world.log[-40:]
    at = {m: world_cycle(world, m, c) for m, c in switched.items()}
    assert len(set(at.values())) == 1, at  # one agreed cycle
    # the head's wave: every ClockCycle/4 cycles, 10 before the switch and 5 after
    emitted = head_emissions(world.records)
    before = [b - a for a, b in itertools.pairwise(emitted) if b <= switched[0]]
    after = [b - a for a, b in itertools.pairwise(emitted) if a >= switched[0]]
    assert before and set(before) == {10}, before
    assert len(after) > 20 and set(after) == {5}, after
    # Table I, hop by hop, on: each module after the switch receives the sequence in order
    # and sets the angle of the phase it receives (the next one's the one it passes on)
    for m in range(1, N):
        mine = sorted((r for r in world.records if r["module"] == m and r["cycle"] > switched[m]),
                      key=lambda r: r["cycle"])  # fmt: skip
        got = [(r, a["hormone"][2]) for r in mine for a in r["received"]]
        assert len(got) > 20, (m, len(got))
        phases = [p for _, p in got]
        assert all(NEXT[p] == q for p, q in itertools.pairwise(phases)), (m, phases)
        assert all(r["actuators"]["DOF1"] == TABLE_I[p] for r, p in got), m
        # one hop behind the module before it: what m got, m-1 got (or the head sent) the
        # phase before, less than HOP periods earlier
        if m == 1:
            sent = [(r["t"], e["hormone"][2]) for r in world.records if r["module"] == 0 for e in r["sent"]]
            before_me = [(t, NEXT[p]) for t, p in sent]
        else:
            before_me = [(r["t"], NEXT[a["hormone"][2]]) for r in world.records if r["module"] == m - 1
                         for a in r["received"]]  # fmt: skip
        for r, p in got:
            assert any(0 < r["t"] - t < HOP * PERIOD and q == NEXT[p] for t, q in before_me), (m, r["cycle"], p)
    for v in world.views:
        program = v.status.get("program", {})
        assert program.get("version") == 2 and not program.get("trial"), (v.name, program)
    assert not any(_alive(p) for p in pids)


def _alive(pid: int) -> bool:
    try:
        import os

        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True
