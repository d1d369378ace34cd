"""The loop's latch emulator (--latch-emulator): each module's latch servo on its emulated bus,
its horn wired to physics, the world docking and undocking on it.

Real parts: the module's own latch (firmware.latch.open_latch from the [latch] the world
gives it: drivers.latch.ServoLatch, the real dynamixel-sdk) over the pty to the world's servo
emulator (hil.latch_emulator.LatchJoint), on real PyBullet; the dock decided as a module's
reach decides it (firmware.main_loop._ModuleLatch)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from dh2rt.compiler import compile_file
from dh2rt.topology import parse_spec
from drivers.latch import Latch, LatchState
from firmware.latch import open_latch
from firmware.main_loop import _ModuleLatch
from hil import launcher
from hil.physics_stand_in import LATCH_CONNECTOR, LATCH_ID
from hil.world import World

ROOT = Path(__file__).resolve().parents[2]
FRONT, BACK = 1, 2


@pytest.fixture
def world() -> Iterator[World]:
    """snake:2 (m0.back docked to m1.front) on the stand-in with latch servos; no module runs."""
    program = compile_file(str(ROOT / "examples" / "snake_to_t.dh2"))
    with World(program, parse_spec("snake:2"), "serial", stand_in="pybullet", latch_emulator=True) as w:
        yield w


def _settle(world: World, latch: Latch, want: LatchState, most_s: float = 3.0) -> LatchState:
    """Poll the latch (as a module does each cycle) and let the world watch the horns."""
    state = latch.state().state
    end = time.monotonic() + most_s
    while state is not want and state is not LatchState.FAULT and time.monotonic() < end:
        time.sleep(0.02)
        world.watch_latches()
        state = latch.state().state
    world.watch_latches()
    return state


def _dock(world: World, latch: Latch) -> tuple[bool, list[str]]:
    """A module's reach asking its own latch to close at its front (as firmware.main_loop does each
    cycle): the dock's verdict, and the module's log."""
    log: list[str] = []
    verified = SimpleNamespace(verified=lambda c: world.link_map.peer_of((1, c)) is not None, log=log)
    own = _ModuleLatch(SimpleNamespace(runtime=verified), latch, FRONT)
    while not own.aligned(1, FRONT, 0, BACK):
        time.sleep(0.05)
        world.watch_latches()
    return own.latch(1, FRONT, 0, BACK), log


def test_the_horn_links_only_when_aligned(world: World) -> None:
    config = world.config(1, None, 0)
    assert config.latch is not None and config.latch.connector == LATCH_CONNECTOR
    assert config.latch.settings["id"] == LATCH_ID and config.latch.settings["port"] is None
    physics = world.physics
    assert physics is not None and physics.horn_closed(1)  # docked at the start: closed
    latch, fault = open_latch(config)
    assert latch is not None, fault
    with latch:
        assert latch.state().state is LatchState.CLOSED
        # the module opens its latch: the world undocks on the horn opening
        latch.open()
        assert _settle(world, latch, LatchState.OPEN) is LatchState.OPEN
        assert world.link_map.peer_of((1, FRONT)) is None and not physics.world.links()
        # the faces are where they were, aligned: the horn passes the pins, the world links them
        docked, log = _dock(world, latch)
        assert docked and "docked (closed and linked)" in log[-1], log
        assert world.link_map.peer_of((1, FRONT)) == (0, BACK) and physics.world.links()
        assert physics.mated[1] == (0, BACK) and world.horn_links[1] == (0, BACK)
        assert any("m1.front docked to m0.back by its latch's horn" in line for line in world.log), world.log
        # opened again, then m1 moved out of line: the pins jam, no link, the dock refused
        latch.open()
        assert _settle(world, latch, LatchState.OPEN) is LatchState.OPEN
        assert world.link_map.peer_of((1, FRONT)) is None
        with physics.lock:
            x, y, _ = physics.world.module_position(1)
            physics.world.set_module_pose(1, (x + 0.05, y + 0.05, 0.05), 40.0)
        refused = physics.latches[1].refused
        docked, log = _dock(world, latch)
        assert not docked and "refused (latch fault" in log[-1], log
        assert physics.latches[1].refused == refused + 1 and not physics.horn_closed(1)
        assert world.link_map.peer_of((1, FRONT)) is None and not physics.world.links()
        assert world.latch_answers == 0


def test_the_option_needs_the_pybullet_stand_in(capsys: pytest.CaptureFixture[str]) -> None:
    program = ROOT / "examples" / "snake_to_t.dh2"
    code = launcher.main(
        ["--transport", "serial", "--program", str(program), "--topology", "snake:2", "--cycles", "5",
         "--stand-in", "recording", "--latch-emulator"]
    )  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "--latch-emulator" in err and "--stand-in pybullet" in err and "Traceback" not in err
