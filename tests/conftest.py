"""Shared fixtures: the examples folder, compiled example programs, the strict watch on
receptor faults that every test runs under, and the machine's timer baseline.

No test is skipped because the machine is slow. A test that runs modules in real time is
marked ``realtime``; `make test` runs those after the rest (CPU-bound, on two xdist workers),
in a group of their own, two at a time: a loop run mostly waits for its cycles, so two share
the machine as a loop run shares it with one busy core, which every one must bear (issue 26).
`make test-long` runs its long ones one at a time. They are judged against this machine's own
timer, measured in the same session (on each worker): a bare sleep loop at the same period
(hil.pace).

* A loop run that the launcher calls too slow (its exit code EXIT_TOO_SLOW) fails the test
  when a bare loop kept that period: then dh2rt is what was slow.
* When the bare loop could not keep it either, hil.pace stretches the period by the factor
  the bare loop needs and makes the run again, which is judged like any other; past
  hil.pace.MAX_FACTOR it raises MachineTooSlow, which fails the test (never a skip).
* A test that judges timing itself allows dh2rt the bare loop's own lateness
  (``timer_baseline``, Baseline.allowance_s), never a fixed figure that a loaded machine
  breaks nor a skip.

Long sweeps (many seeds, whole reconfigurations in the loop) are marked ``long`` and run in
`make test-long`; `make test` keeps at least one case of each feature and topology.
"""

from __future__ import annotations

import signal
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import settings

from dh2rt.compiler import compile_file
from dh2rt.program import CompiledProgram
from dh2rt.testing import FaultWatch
from hil.pace import Baseline, baseline

# Started in the background by a shell without job control (`make test &`, a CI runner's
# nohup), this process ignores SIGINT, and so would every command a test starts: Python keeps an
# ignored SIGINT, so the tests' Ctrl-C would never reach them. Take it back: a handled signal is
# reset to the default in a child at exec.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"

# Hypothesis's 200 ms deadline per example is a timing test: on a machine whose processors are
# taken away for hundreds of milliseconds (seen here) any example can exceed it. The
# properties are what these tests check; benchmarks/ measures the speed.
settings.register_profile("dh2rt", deadline=None)
settings.load_profile("dh2rt")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tests marked ``slow`` (tens of seconds of CPU each: whole reconfigurations in physics)
    go first, the rest in their order: make test's workers (``--dist worksteal``) then end on
    short tests, instead of one worker running a 110 s test alone at the end (the CPU group
    took 9:05 with them last, measured on 2026-11-29)."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


@pytest.fixture(autouse=True)
def strict_faults(request: pytest.FixtureRequest) -> Iterator[FaultWatch]:
    """Fail any test during which a receptor faulted (in this process), unless it is marked
    ``@pytest.mark.expect_faults``; such a test fails if no fault happened."""
    expected = request.node.get_closest_marker("expect_faults") is not None
    with FaultWatch() as watch:
        yield watch
    if watch.faults and not expected:
        shown = "; ".join(watch.messages[:5])
        pytest.fail(f"{len(watch.faults)} receptor fault(s) (mark the test expect_faults if intended): {shown}")
    if expected and not watch.faults and not request.node.stash.get(SKIPPED, False):
        pytest.fail("the test is marked expect_faults but no receptor faulted")


@pytest.fixture(scope="session")
def examples() -> Path:
    return EXAMPLES


@pytest.fixture(scope="session")
def caterpillar() -> CompiledProgram:
    return compile_file(str(EXAMPLES / "caterpillar.dh2"))


@pytest.fixture(scope="session")
def locomotion() -> CompiledProgram:
    return compile_file(str(EXAMPLES / "locomotion.dh2"))


@pytest.fixture(scope="session")
def legs_to_snake() -> CompiledProgram:
    return compile_file(str(EXAMPLES / "legs_to_snake.dh2"))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Iterator[None]:
    try:
        return (yield)
    except pytest.skip.Exception:
        item.stash[SKIPPED] = True
        raise


#: set on a test that skipped (a missing tool, not a slow machine: its fault watch then expects nothing)
SKIPPED = pytest.StashKey[bool]()


@pytest.fixture(scope="session")
def timer_baseline() -> Baseline:
    """A bare sleep loop at the default cycle period, measured once in this session: what a
    test that judges timing allows dh2rt (Baseline.allowance_s)."""
    return baseline()
