"""What the flashing tests in the loop share: the caterpillar with another ClockCycle, a
running snake, a programming cable on a module's front connector with the flasher on it, the
world run to a cycle or a condition, the switches and versions the modules report, and the
private network namespace udp_multicast needs."""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from dh2rt import cli
from dh2rt.compiler import compile_file, compile_source
from dh2rt.flash.pacing import link_pacing
from dh2rt.program import CompiledProgram
from dh2rt.signed_image import pack, read_private_key, write_key_pair
from dh2rt.topology import parse_spec
from dh2rt.transport.base import PortEnd
from dh2rt.transport.serial_link import SerialTransport
from firmware.flash.cable import FlashCable, FlashResult, hello_codec
from hil.pace import PACE
from hil.world import World

ROOT = Path(__file__).resolve().parents[2]
PROGRAM = ROOT / "examples" / "caterpillar.dh2"
PERIOD = 0.02
T = TypeVar("T")
FRONT = 1  # CONRO's front connector: the head's is free


def caterpillar(clock_cycle: int) -> CompiledProgram:
    text = PROGRAM.read_text(encoding="utf-8")
    return compile_source(text.replace("const ClockCycle = 40", f"const ClockCycle = {clock_cycle}"))


def robot_key_and_image(folder: Path, clock_cycle: int, version: int = 2) -> tuple[Path, Path]:
    """A robot's signing key (``--key``) in ``folder`` and the caterpillar with ``clock_cycle``
    signed with it at ``version`` (a flash event's IMAGE): their paths."""
    key_file = folder / "robot.key"
    write_key_pair(key_file)
    image = folder / "cat2.simg"
    image.write_bytes(pack(caterpillar(clock_cycle).image, version, read_private_key(key_file)))
    return key_file, image


def capture_a_flash(folder: Path, capture: Path) -> int:
    """A loop run of four modules on the virtual bus in which ``m0`` flashes the caterpillar
    with another ClockCycle to the others, captured to ``capture`` (keys and image in
    ``folder``): the launcher's exit code."""
    key_file, image = robot_key_and_image(folder, 20)
    return PACE.call(
        cli.main,
        ["--transport", "virtual", "--module-count", "4", "--cycles", "120", "--stand-in", "recording",
         "--key", str(key_file), "--event", f"40:flash:m0:{image}", "--capture", str(capture), "--force"]
    )  # fmt: skip


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


def _cycle_of_each(log: list[str], pattern: str) -> dict[int, int]:
    """Module -> the cycle (its own count) of its last log line matching ``pattern``, whose
    groups are the module's number and the cycle."""
    out: dict[int, int] = {}
    for line in log:
        m = re.search(pattern, line)
        if m:
            out[int(m.group(1))] = int(m.group(2))
    return out


def switches(log: list[str]) -> dict[int, int]:
    """Module -> the cycle (its own count) at which it switched, from its log lines (the
    world's, or the launcher summary's)."""
    return _cycle_of_each(log, r"\bm(\d+): cycle (\d+): switched to program")


def agreed_instants(log: list[str]) -> dict[int, tuple[int, float, float]]:
    """Module -> (its cycle, the switch instant on CLOCK_MONOTONIC to the microsecond, how many
    seconds ahead it was) from the log line that says its COMMIT agreed the instant."""
    out: dict[int, tuple[int, float, float]] = {}
    for line in log:
        m = re.match(r"m(\d+): cycle (\d+): rollout: switch agreed at t=([0-9.]+) \(([-+0-9.]+) ms from now\)$", line)
        if m:
            out[int(m.group(1))] = (int(m.group(2)), float(m.group(3)), float(m.group(4)) / 1000)
    return out


def staged_cycles(log: list[str]) -> dict[int, int]:
    """Module -> the cycle its image was in its flash, waiting for the switch."""
    return _cycle_of_each(log, r"^m(\d+): cycle (\d+): rollout: image staged in slot \w+: waits for the switch$")


@dataclass(frozen=True)
class SwitchTiming:
    """When each module's switch fell, against the instant its COMMIT agreed (its trace's
    ``t``: a cycle's start on CLOCK_MONOTONIC, as the instant).

    A module switches at its first cycle that starts at or after the instant, unless it was
    not ready then: its image not yet in its flash, or the commit not yet come (a module the
    loop's shared machine held up, which learns the instant after it passed); then at the
    cycle it becomes ready (the one after the commit came)."""

    agreed: dict[int, float]  # the instant
    ahead: dict[int, float]  # seconds ahead of the instant the module learned it
    switched: dict[int, int]  # the cycle that switched
    first_after: dict[int, int]  # the first cycle that started at or after the instant
    ready: dict[int, int]  # the cycle by which the module had both the image and the instant
    starts: dict[int, dict[int, float]]  # module -> cycle -> start

    def misplaced(self) -> dict[int, str]:
        """Modules that switched early, or later than the first cycle at or after the
        instant at which they were ready: what happened."""
        out = {}
        for m, s in self.switched.items():
            due = max(self.first_after[m], self.ready[m])
            if not self.first_after[m] <= s <= due:
                out[m] = (
                    f"switched at cycle {s}, due {due} (first at/after the instant {self.first_after[m]}, "
                    f"ready {self.ready[m]}); learned {self.ahead[m] * 1000:+.1f} ms ahead"
                )
        return out

    def in_time(self) -> list[int]:
        """Modules that learned the instant before it passed."""
        return sorted(m for m, a in self.ahead.items() if a > 0)

    def after(self) -> dict[int, float]:
        """Module -> how long after its instant its switch cycle began, in periods."""
        return {m: round((self.starts[m][s] - self.agreed[m]) / PERIOD, 3) for m, s in self.switched.items()}


def switch_timing(log: list[str], records: list[dict[str, Any]], n: int) -> SwitchTiming:
    """The switch timing of modules 0..n-1 from a run's log and trace records; asserts that
    every one switched, staged and logged its instant."""
    switched = switches(log)
    assert sorted(switched) == list(range(n)), log[-30:]
    said = agreed_instants(log)
    assert sorted(said) == list(range(n)), log[-30:]
    staged = staged_cycles(log)
    assert sorted(staged) == list(range(n)), log[-30:]
    starts: dict[int, dict[int, float]] = {m: {} for m in range(n)}
    for r in records:
        if int(r["module"]) in starts:
            starts[int(r["module"])][int(r["cycle"])] = float(r["t"])
    agreed = {m: at for m, (_, at, _) in said.items()}
    first_after = {m: min(c for c, t in starts[m].items() if t >= agreed[m] - 1e-6) for m in range(n)}
    # what a cycle's log says may have come at its start (then it switches in it) or later
    ready = {m: max(staged[m], said[m][0]) + 1 for m in range(n)}
    ahead = {m: a for m, (_, _, a) in said.items()}
    return SwitchTiming(agreed, ahead, switched, first_after, ready, starts)


def tick_until(world: World, done: Callable[[], object], seconds: float) -> bool:
    """Tick the world until ``done()`` is true (True) or ``seconds`` passed (False)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if done():
            return True
        world.tick()
        time.sleep(0.01)
    return False


def versions(world: World) -> list[Any]:
    """The program version each module's last status names."""
    return [v.status.get("program", {}).get("version") for v in world.views]


@contextmanager
def running_snake(transport: str, n: int, *, seed: int = 0, wait: float = 60.0, **options: Any) -> Iterator[World]:
    """A snake of ``n`` modules running the caterpillar (signed as version 1 with the world's
    key) over ``transport``, started and past its 30th cycle; always stopped."""
    world = World(compile_file(str(PROGRAM)), parse_spec(f"snake:{n}"), transport, seed=seed, cycle_period=PERIOD,
                  cycles=1_000_000, stand_in="recording", **options)  # fmt: skip
    try:
        world.start(ready_timeout=wait)
        tick_until(world, lambda: world.cycle >= 30, 30.0)
        yield world
    finally:
        world.stop()


def beside(world: World, work: Callable[[], T], seconds: float) -> T:
    """``work()`` in a thread (a command, as it would run in a shell) while this thread ticks
    the world; its result. Fails when it has not returned within ``seconds``."""
    out: list[T] = []
    thread = threading.Thread(target=lambda: out.append(work()), name="dh2rt-beside-the-world", daemon=True)
    thread.start()
    try:
        tick_until(world, lambda: not thread.is_alive(), seconds)
    finally:
        thread.join(10)
    assert out, f"{work} did not return within {seconds:g} s"
    return out[0]
