"""The public testing helpers: the fault watch, the fake clock, runtime chains."""

from __future__ import annotations

import pytest

from dh2rt.compiler import compile_source
from dh2rt.engine import Engine
from dh2rt.errors import ServoCommError
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.testing import FakeClock, FaultWatch, runtime_chain, step_all
from dh2rt.topology import parse_spec

RAISING = """
program raising
const ClockCycle = 4
native boom()
receptor r1 when LocalTimer == 0 {
    boom(); keep_alive()
}
"""


def _boom(engine: Engine) -> None:
    raise ServoCommError("the native failed")  # a failing servo: a fault by design


def _robot() -> Robot:
    return Robot(compile_source(RAISING), parse_spec("snake:2"), natives={"boom": _boom})


@pytest.mark.expect_faults  # the suite's own watch sees them too
def test_fault_watch_sees_a_native_that_raises() -> None:
    with FaultWatch() as watch:
        _robot().run(8)
    assert len(watch.faults) == 4  # 2 modules, 2 periods each
    assert all("receptor r1: the native failed" in m for m in watch.messages)
    with FaultWatch() as outer:
        with FaultWatch() as ended:
            pass
        _robot().run(8)
    # restored: a watch that ended sees no more faults, and the one around it sees them all
    assert ended.faults == [] and len(outer.faults) == 4


@pytest.mark.expect_faults
def test_the_strict_fixture_lets_a_marked_test_fault() -> None:
    """conftest's strict_faults fails an unmarked test that faults, and a marked one that
    does not: this one passes only if the fixture saw the faults."""
    _robot().run(4)


def test_a_native_with_a_bug_surfaces() -> None:
    """Only what actions raise by design is a fault; anything else is a bug and stops the run."""

    def buggy(engine: Engine) -> None:
        raise KeyError("oops")

    robot = Robot(compile_source(RAISING), parse_spec("snake:2"), natives={"boom": buggy})
    with pytest.raises(KeyError, match="oops"):
        robot.run(4)


def test_fake_clock() -> None:
    clock = FakeClock(step=0.5)
    assert [clock(), clock()] == [0.5, 1.0]
    still = FakeClock()
    still.sleep(2.0)
    assert still() == still() == 2.0


def test_runtime_chain_links_and_types(caterpillar: CompiledProgram) -> None:
    mods = runtime_chain(caterpillar, 3)
    try:
        step_all(mods, 3)
        assert [m.engine.topo_type.name for m in mods] == ["head", "body", "tail"]
        assert all(m.counters["refused"] == 0 for m in mods)
    finally:
        for m in mods:
            m.close()
    with pytest.raises(ValueError, match="phases"):
        runtime_chain(caterpillar, 2, phases=[0])
