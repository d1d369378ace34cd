"""A module's lives in the world: the end of a killed life, read after the module was started
again, is that life's, not the new one's (it once marked the new life dead, so the world
never sent it its Go and the restarted module waited for ever)."""

from __future__ import annotations

import time

import pytest

from dh2rt.compiler import compile_file
from dh2rt.topology import parse_spec
from firmware.control import Exited
from hil.world import World
from tests.hil.flashing import PERIOD, PROGRAM

#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


@pytest.mark.parametrize("transport", ["inproc", "serial"])
def test_a_previous_lifes_end_read_late_does_not_end_the_new_life(transport: str) -> None:
    world = World(compile_file(str(PROGRAM)), parse_spec("snake:3"), transport, cycle_period=PERIOD,
                  cycles=100_000, stand_in="recording")  # fmt: skip
    try:
        world.start()
        while world.cycle < 10:
            world.tick()
            time.sleep(0.01)
        world.restart(1)
        world.reports.put((1, Exited(life=0)))  # the killed life's end, read late
        deadline = time.monotonic() + 20
        start = int(world.views[1].status.get("cycle", 0))
        while time.monotonic() < deadline and int(world.views[1].status.get("cycle", 0)) <= start + 20:
            world.tick()
            time.sleep(0.01)
        v = world.views[1]
        assert v.alive and v.state == "running", v.state
        assert int(v.status.get("cycle", 0)) > start + 20, v.status.get("cycle")  # the new life cycles
        world.reports.put((1, Exited(life=1)))  # its own end is its end
        world.poll()
        assert not world.views[1].alive
    finally:
        world.stop()
