"""What the flashing tests in the loop share: the caterpillar with another ClockCycle, a
programming cable on a module's front connector with the flasher on it, the world run to a
cycle, and the switches the modules logged."""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable
from pathlib import Path

from dh2rt.compiler import compile_source
from dh2rt.program import CompiledProgram
from dh2rt.rollout import link_pacing
from dh2rt.transport.base import PortEnd
from dh2rt.transport.serial_link import SerialTransport
from drivers.flash_cable import FlashCable, FlashResult, hello_codec
from hil.world import World

ROOT = Path(__file__).resolve().parents[2]
PROGRAM = ROOT / "examples" / "caterpillar.dh2"
PERIOD = 0.02
FRONT = 1  # CONRO's front connector: the head's is free


def caterpillar(clock_cycle: int) -> CompiledProgram:
    text = PROGRAM.read_text(encoding="utf-8")
    return compile_source(text.replace("const ClockCycle = 40", f"const ClockCycle = {clock_cycle}"))


def flash_through_cable(
    world: World, module: int, image: bytes, *, timeout: float = 120.0, each_tick: Callable[[], None] | None = None
) -> FlashResult:
    """Plug a cable into ``module``'s front, run the flasher on it until it is done (the
    world ticking meanwhile, and ``each_tick`` called after each tick), pull the cable out;
    the flasher's result."""
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
            if each_tick is not None:
                each_tick()
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


def switches(log: list[str]) -> dict[int, int]:
    """Module -> the cycle (its own count) at which it switched, from its log."""
    out: dict[int, int] = {}
    for line in log:
        m = re.match(r"m(\d+): cycle (\d+): switched to program", line)
        if m:
            out[int(m.group(1))] = int(m.group(2))
    return out
