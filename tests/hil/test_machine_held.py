"""The launcher's verdict on links lost on clean links (hil.launcher.machine_held): the
machine's, when the link emulator's relay or a module's start was held as long as the liveness
bound after little work of the module's own; dh2rt's otherwise."""

from __future__ import annotations

import hashlib
import json
import threading
from types import SimpleNamespace
from typing import Any, cast

import pytest

from dh2rt import cli
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


@pytest.mark.realtime
def test_a_module_run_as_a_thread_counts_its_own_work_not_the_process_s(capsys: pytest.CaptureFixture[str]) -> None:
    """Modules on the in-process bus are threads of the launcher's process, beside its physics
    (here a thread hashing, which lets go of the GIL, as PyBullet's stepping does): each
    module's ``work_ms`` is its thread's CPU time, not the process's. Counted as the process's
    (before the fifteenth session of issue 28), every module worked a whole period a cycle, so
    machine_held blamed the modules for any link the machine lost: a CI run's docs example on
    python-can's virtual bus failed with exit 1 where the machine had held it."""
    stop = threading.Event()

    def busy() -> None:
        block = bytes(1 << 20)
        while not stop.is_set():
            hashlib.sha256(block).digest()

    burner = threading.Thread(target=busy, name="test-busy", daemon=True)
    burner.start()
    try:
        cli.main(["--transport", "inproc", "--module-count", "4", "--cycles", "80", "--stand-in", "none", "--json"])
    finally:
        stop.set()
        burner.join()
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    period_ms = float(summary["cycle_period"]) * 1000
    work = {row["name"]: row["work_ms"]["p50"] for row in summary["modules"]}
    assert all(ms < period_ms / 4 for ms in work.values()), (work, period_ms)
