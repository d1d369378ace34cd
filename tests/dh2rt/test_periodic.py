"""``periodic P via C every N`` sends at the first cycle and then every N cycles exactly,
whatever the period, the module's timer phase, and whether quiet cycles are skipped."""

from __future__ import annotations

import pytest

from dh2rt.compiler import compile_source
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec

PROGRAM = """program periodic
const ClockCycle = 20
hormone P
receptor start when T == T1 and LocalTimer == 5 {{
    periodic P via back every {period}
}}
"""


@pytest.mark.parametrize("period", [1, 2, 3, 10])
@pytest.mark.parametrize("phase", [0, 5, 13])
@pytest.mark.parametrize("skip_quiet", [True, False])
def test_periodic_sends_every_n_cycles_from_the_first(period: int, phase: int, skip_quiet: bool) -> None:
    program = compile_source(PROGRAM.format(period=period))
    robot = Robot(program, parse_spec("snake:2"), timer_phases=[phase, 0], skip_quiet=skip_quiet, record=True)
    sent: list[int] = []
    for cycle in robot.iter_cycles(80):
        sent += [cycle for rec in robot.records if rec.module == 0 for _ in rec.sent]
        robot.records.clear()
    first = (5 - phase) % 20
    assert sent[0] == first
    assert sent == list(range(first, 80, period))
