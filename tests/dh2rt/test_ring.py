"""On a cycle, flooding must not melt down: unbound hormones die after max_hops links."""

from __future__ import annotations

import pytest

from dh2rt.compiler import compile_source
from dh2rt.hormone import DEFAULT_MAX_HOPS, Hormone
from dh2rt.robot import Robot
from dh2rt.topology import ring


@pytest.mark.parametrize("max_hops", [None, 10])
def test_unbound_hormone_dies_out_on_a_ring_of_6(max_hops: int | None) -> None:
    opt = f"option max_hops = {max_hops}\n" if max_hops else ""
    cp = compile_source(f"const ClockCycle = 4\n{opt}hormone Z\n", "ring.dh2")
    bound = max_hops or DEFAULT_MAX_HOPS
    robot = Robot(cp, ring(6), seed=1)
    assert all(robot.engine(m).topo_type.name == "body" for m in range(6))
    robot.inject(0, Hormone("Z"))
    in_flight = []
    for _ in robot.iter_cycles(bound + 5):
        in_flight.append(sum(len(box) for box in robot.inbox.values()))
    # two copies circle the ring (one each way) until their paths reach the bound
    assert in_flight[0] == 2
    assert all(n == 2 for n in in_flight[: bound - 1])
    assert all(n == 0 for n in in_flight[bound:])
    dropped = sum(robot.engine(m).counters["dropped_hops"] for m in range(6))
    assert dropped == 2


def test_bad_max_hops_option() -> None:
    from dh2rt.errors import ProgramCompileError

    with pytest.raises(ProgramCompileError, match="max_hops must be between 1 and 255"):
        compile_source("const ClockCycle = 4\noption max_hops = 300\n")
    with pytest.raises(ProgramCompileError, match="unknown option 'hops'"):
        compile_source("const ClockCycle = 4\noption hops = 3\n")
