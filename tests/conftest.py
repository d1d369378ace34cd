"""Shared fixtures: the examples folder, compiled example programs, and the strict watch on
receptor faults that every test runs under."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import settings

from dh2rt.compiler import compile_file
from dh2rt.errors import MachineTooSlow
from dh2rt.program import CompiledProgram
from dh2rt.testing import FaultWatch
from hil.pace import realtime_problem

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"

# Hypothesis's 200 ms deadline per example is a timing test: on a machine whose processors are
# taken away for hundreds of milliseconds (seen here) any example can exceed it. The
# properties are what these tests check; benchmarks/ measures the speed.
settings.register_profile("dh2rt", deadline=None)
settings.load_profile("dh2rt")


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
def pytest_runtest_setup(item: pytest.Item) -> Iterator[None]:
    return (yield from _skip_if_too_slow(item))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Iterator[None]:
    return (yield from _skip_if_too_slow(item))


@pytest.fixture(autouse=True)
def _realtime(request: pytest.FixtureRequest) -> None:
    """A test marked ``realtime`` is skipped, saying why, on a machine that keeps no real time."""
    if request.node.get_closest_marker("realtime") is not None and (why := realtime_problem()):
        pytest.skip(why)


#: set on a test skipped because the machine keeps no real time (its fault watch then expects nothing)
SKIPPED = pytest.StashKey[bool]()


def _skip_if_too_slow(item: pytest.Item) -> Iterator[None]:
    """A loop run that the machine could not keep at any period hil.pace tries is no verdict
    on dh2rt: the test is skipped, saying what the launcher said (visible with -ra)."""
    try:
        return (yield)
    except MachineTooSlow as exc:
        item.stash[SKIPPED] = True
        pytest.skip(f"this machine cannot keep real time: {exc}")
