"""The loop's latch emulator (--latch-emulator): each module's latch servo on its emulated bus,
its horn wired to physics, the world docking and undocking on it.

Real parts: the module's own latch (firmware.latch.open_latch from the [latch] the world
gives it: drivers.latch.ServoLatch, the real dynamixel-sdk) over the pty to the world's servo
emulator (hil.latch_emulator.LatchJoint), on real PyBullet; the dock decided as a module's
reach decides it (firmware.main_loop._ModuleLatch)."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

import pytest

from dh2rt.compiler import compile_file
from dh2rt.topology import parse_spec
from drivers.latch import Latch, LatchState
from firmware.latch import open_latch
from firmware.main_loop import ModuleHost, _ModuleLatch
from hil import launcher
from hil.latch_emulator import LATCH_CONNECTOR, LATCH_ID
from hil.pace import PACE
from hil.world import World
from sim.runner import DOCK_TOLERANCE_DEG, DOCK_TOLERANCE_M
from tests.marks import LONG

ROOT = Path(__file__).resolve().parents[2]
FRONT, BACK = 1, 2
#: World cycles for snake_to_t with the motion in the modules (as tests/hil/test_hil_reach_physics.py)
OWN_T_CYCLES = 1000

#: module processes run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


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
    cycle) until the latch docks it or refuses a try: whether it docked, and the module's log."""
    log: list[str] = []
    verified = SimpleNamespace(verified=lambda c: world.link_map.peer_of((1, c)) is not None, log=log)
    host = cast(ModuleHost, SimpleNamespace(runtime=verified))
    own = _ModuleLatch(host, latch, FRONT)
    for _ in range(60):  # 3 s of 50 ms cycles
        if own.aligned(1, FRONT, 0, BACK):
            return own.latch(1, FRONT, 0, BACK), log
        if log:  # refused: opened again, the motion would go on and ask again
            return False, log
        time.sleep(0.05)
        world.watch_latches()
    raise AssertionError(f"neither docked nor refused in 3 s: {log}")


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


@LONG  # a whole reconfiguration in the loop
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_snake_to_t_forms_on_the_latch_servos(seed: int, capsys: pytest.CaptureFixture[str]) -> None:
    """--motions-in-modules --latch-emulator: m0's own reach closes m0's own latch servo; its horn
    passes the pins (m0.front aligned with m5.left in physics) and the world links them on that;
    no LatchAnswer is sent. The T forms as with the world's latch."""
    code = PACE.call(
        launcher.main,
        ["--transport", "serial", "--program", str(ROOT / "examples" / "snake_to_t.dh2"), "--topology", "snake:8",
         "--cycles", str(OWN_T_CYCLES), "--cycle-ms", "50", "--silence-cycles", "6", "--event", "50:inject:m4:STT",
         "--seed", str(seed), "--json", "--stand-in", "pybullet", "--motions-in-modules", "--latch-emulator"]
    )  # fmt: skip
    out = capsys.readouterr().out
    assert code == 0, out
    summary: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
    log = summary["log"]
    docking = [line for line in log if "dock" in line or "latch" in line or "release" in line]
    assert any("m0: latch: the module's own (servo) on connector 1" in line for line in log), docking
    types = {m["name"]: m["type"] for m in summary["modules"]}
    assert types["m3"] == "head" and types["m2"] == "tail" and types["m7"] == "tail", (types, docking)
    docked = [line for line in log if "m0.front docked to m5.left" in line]
    assert len(docked) == 1 and "by its latch's horn" in docked[0], docking
    assert any("m0: latch on connector 1: docked (closed and linked)" in line for line in log), docking
    reaches = summary["reaches"]
    assert reaches["latch_answers"] == 0
    (contact,) = reaches["contacts"]
    assert contact["distance_mm"] <= DOCK_TOLERANCE_M * 1000 and contact["attitude_deg"] <= DOCK_TOLERANCE_DEG
    order = [i for i, line in enumerate(log) if "docked to m5.left" in line or "m2.back released" in line]
    assert len(order) == 2 and "docked" in log[order[0]], docking
