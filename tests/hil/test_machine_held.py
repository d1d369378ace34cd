"""The launcher's verdict on links lost on clean links (hil.launcher.machine_held): the
machine's, when the link emulator's relay or a module's start was held as long as the liveness
bound after little work of the module's own; dh2rt's otherwise."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any, cast

import pytest

from hil.launcher import links_held_by_machine, machine_held
from hil.world import World


def world(relay_ms: float | None, late_ms: float = 1.0, work_ms: float = 2.0, lost: int = 1) -> World:
    status = {"counters": {"links_lost": lost}, "lateness_ms": {"max": late_ms}, "work_ms": {"max": work_ms}}
    views = [SimpleNamespace(name="m0", status=status), SimpleNamespace(name="m1", status={"counters": {}})]
    # a long hold before the modules started cycling (at 100 s) counts for nothing
    holds = [(99.0, 0.09)] + ([] if relay_ms is None else [(101.0, relay_ms / 1000)])
    emulator = SimpleNamespace(holds=lambda: holds)
    w: Any = SimpleNamespace(cycle_period=0.02, silence_cycles=3, views=views, emulator=emulator, go_at=100.0)
    return cast(World, w)


@pytest.mark.parametrize(
    ("relay_ms", "late_ms", "work_ms", "says"),
    [
        (75.0, 1.0, 2.0, "held the link emulator's relay 75 ms (the liveness bound is 60 ms)"),
        (40.0, 1.0, 2.0, "held the link emulator's relay 40 ms"),  # the bound less a period
        (None, 52.0, 2.0, "started m0 52 ms late"),
        (10.0, 10.0, 2.0, None),  # nothing held it: dh2rt's
        (75.0, 1.0, 35.0, None),  # the module's own work came near the bound: dh2rt's
    ],
)
def test_who_held_the_links(relay_ms: float | None, late_ms: float, work_ms: float, says: str | None) -> None:
    w = world(relay_ms, late_ms, work_ms)
    held = machine_held(w)
    assert (held is None) == (says is None) and (says is None or says in str(held)), held
    assert links_held_by_machine(w) == (says is not None)


def test_no_link_lost_is_not_the_machine_s() -> None:
    assert not links_held_by_machine(world(75.0, lost=0))
