"""Replies along path-1 reach exactly the module that sent the original."""

from __future__ import annotations

from dh2rt.compiler import compile_source
from dh2rt.hormone import Hormone
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec

PROGRAM = """
const ClockCycle = 10
var pongs = 0
hormone START
hormone PING
hormone PONG(hops: int)
receptor start when H == START { emit PING via all; keep_alive() }
receptor answer when T == T2 and H == PING as p { emit PONG(7) via p-1; keep_alive() }
receptor count when H == PONG(7) { V.pongs = V.pongs + 1; keep_alive() }
"""


def test_reply_retraces_the_path_in_a_branching_robot() -> None:
    cp = compile_source(PROGRAM, "replies.dh2")
    topo = parse_spec("dragon")
    origin = topo.module_index("left_leg0")
    robot = Robot(cp, topo, seed=2, record=True)
    robot.inject(origin, Hormone("START"))
    pong_receivers: list[tuple[int, int, tuple[int, ...] | None]] = []
    ping_hops = 0
    for _ in robot.iter_cycles(30):
        for rec in robot.records:
            for a in rec.received:
                if a.hormone.name == "PONG":
                    pong_receivers.append((rec.cycle, rec.module, a.hormone.route))
                if a.hormone.name == "PING" and rec.module == topo.module_index("tail4"):
                    ping_hops = len(a.hormone.path) + 1
        robot.records.clear()
    assert ping_hops >= 5  # left_leg0 -> spine0 -> spine1 -> tail0 .. tail4: 7 hops
    # the reply ends (empty route) at the origin and nowhere else
    ends = [m for _c, m, route in pong_receivers if route == ()]
    assert ends == [origin]
    # it visits exactly the modules on the way back, one hop per cycle, none off the path
    on_path = [topo.module_index(n) for n in ("tail3", "tail2", "tail1", "tail0", "spine1", "spine0", "left_leg0")]
    assert [m for _c, m, _r in pong_receivers] == on_path
    cycles = [c for c, _m, _r in pong_receivers]
    assert cycles == list(range(cycles[0], cycles[0] + len(cycles)))
    assert robot.engine(origin).var("pongs") == 1
    # the other feet and the other branch never saw it
    for name in ("right_leg0", "left_leg1", "right_leg1"):
        assert robot.engine(topo.module_index(name)).var("pongs") == 0


def test_reply_to_a_dead_end_is_dropped_quietly() -> None:
    cp = compile_source(PROGRAM, "replies.dh2")
    topo = parse_spec("snake:6")
    robot = Robot(cp, topo, seed=0)
    robot.inject(0, Hormone("START"))
    robot.run(6)
    robot.cut(2, 2)  # break the way back while PONG travels
    robot.run(10)
    assert robot.engine(0).var("pongs") == 0
    assert all(robot.engine(m).counters["faults"] == 0 for m in range(6))
