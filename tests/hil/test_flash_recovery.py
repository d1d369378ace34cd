"""A module killed during a rollout, in the loop (4 module processes on serial links):

- killed in the middle of staging (its flash holds a partial image), it boots its old
  program, and on restart finishes the update from its neighbours;
- killed during its trial (it switched, and had not confirmed), it reverts to the old
  program at its next boot, and counts the revert.

The victim is the third module of the snake (``m2``): it has neighbours on both sides, and it
is not the entry point, so what it gets it gets from its neighbours.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from dh2rt.compiler import compile_file
from dh2rt.signed_image import pack
from dh2rt.topology import parse_spec
from firmware.flash.slots import PARTIAL_IMAGE
from hil.world import World
from tests.hil.flashing import (
    PERIOD,
    PROGRAM,
    caterpillar,
    flash_through_cable,
    run_world,
    switches,
    tick_until,
    versions,
)
from tests.marks import sweep

N = 4
VICTIM = 2
WAIT = 120.0


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


def watch(world: World, until: Callable[[], object], seconds: float = WAIT) -> bool:
    return tick_until(world, until, seconds)


def new_world(seed: int, trial_cycles: int = 100) -> World:
    return World(compile_file(str(PROGRAM)), parse_spec(f"snake:{N}"), "serial", seed=seed, cycle_period=PERIOD,
                 cycles=100_000, stand_in="recording", trial_cycles=trial_cycles)  # fmt: skip


@pytest.mark.parametrize("seed", sweep([0, 1]))
def test_killed_while_staging_boots_the_old_program_and_finishes_from_its_neighbours(seed: int) -> None:
    world = new_world(seed)
    flash = world.workdir / f"m{VICTIM}" / "flash"
    try:
        world.start()
        run_world(world, 40)
        assert world.signer is not None
        image = pack(caterpillar(20).image, 2, world.signer)
        killed: list[int] = []
        restarted: list[int] = []

        def kill_when_partial() -> None:
            if not killed and (flash / PARTIAL_IMAGE).exists():
                killed.append(world.cycle)
                world.kill(VICTIM)
            elif killed and not restarted and world.cycle >= killed[0] + 40:
                restarted.append(world.cycle)
                world.restart(VICTIM)

        result = flash_through_cable(world, 0, image, each_tick=kill_when_partial)
        assert killed, "the victim never held a partial image: the test did not test anything"
        # the victim's old program ran after the kill (its restart boots it) ...
        if not restarted:
            world.restart(VICTIM)
        assert watch(world, lambda: versions(world) == [2] * N), (versions(world), world.log[-30:])
        # ... and the new one came from its neighbours, not from the cable
        life1 = [line for line in world.log if line.startswith(f"m{VICTIM}: ")]
        assert any("switched to program" in line for line in life1), life1[-20:]
        statuses = [dict(v.status) for v in world.views]
        assert all(not s["program"]["trial"] or s["program"]["version"] == 2 for s in statuses)
        # the flasher heard of the modules it could reach; those it heard of committed
        assert result.modules, result
    finally:
        world.stop()


@pytest.mark.parametrize("seed", sweep([0, 1]))
def test_killed_during_its_trial_reverts(seed: int) -> None:
    # a long trial, so that the victim is surely killed before it confirms
    world = new_world(seed, trial_cycles=100_000)
    try:
        world.start()
        run_world(world, 40)
        assert world.signer is not None
        image = pack(caterpillar(20).image, 2, world.signer)
        switched_at: list[int] = []

        def kill_on_switch() -> None:
            if not switched_at and VICTIM in switches(world.log):
                switched_at.append(world.cycle)
                world.kill(VICTIM)

        flash_through_cable(world, 0, image, timeout=30.0, each_tick=kill_on_switch)
        assert watch(world, lambda: VICTIM in switches(world.log)), world.log[-30:]
        if not switched_at:
            world.kill(VICTIM)
        world.restart(VICTIM)

        def reverted() -> bool:
            program = world.views[VICTIM].status.get("program", {})
            return bool(program.get("reverts", 0) >= 1 and program.get("version") == 1 and not program.get("trial"))

        v = world.views[VICTIM]
        mine = [line for line in world.log if line.startswith(f"m{VICTIM}")]
        assert watch(world, reverted, 60.0), (v.state, v.errors, v.status.get("program"), mine[-30:])
        assert world.views[VICTIM].alive
    finally:
        world.stop()


def test_flash_folder_is_the_modules_across_its_lives(tmp_path: Path) -> None:
    """The world keeps each module's flash across restarts: one folder per module."""
    world = new_world(0)
    try:
        world.start()
        run_world(world, 10)
        world.restart(VICTIM)
        run_world(world, world.cycle + 10)
        folder = world.workdir / f"m{VICTIM}"
        assert sorted(p.name for p in folder.iterdir() if p.name.startswith("life")) == ["life0", "life1"]
        assert (folder / "flash").is_dir()
    finally:
        world.stop()
