"""Fig. 5 on the in-process robot: LTS, RCT, TAR, ALT; one foot per round; resumes."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

from dh2rt.hormone import Hormone
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec

FEET = ("left_foot", "right_foot")


def run_logged(
    robot: Robot, cycles: int, on_cycle: Callable[[int], None] | None = None
) -> list[tuple[int, int, str, str, str]]:
    """(cycle, module, type, 'recv'|'sent', hormone name) for the reconfiguration hormones."""
    log: list[tuple[int, int, str, str, str]] = []
    robot.record = True
    for c in robot.iter_cycles(cycles):
        for rec in robot.records:
            e = robot.engines[rec.module]
            t = e.topo_type.name if e else "dead"
            log.extend(
                (rec.cycle, rec.module, t, "recv", a.hormone.name) for a in rec.received if a.hormone.name != "X"
            )
            log.extend((rec.cycle, rec.module, t, "sent", x.hormone.name) for x in rec.sent if x.hormone.name != "X")
        robot.records.clear()
        if on_cycle:
            on_cycle(c)
    return log


def is_snake(robot: Robot) -> bool:
    names = sorted(e.topo_type.name for e in robot.engines if e)
    n = len(names)
    chain = all(robot.profile.connector_name(c) in ("front", "back") for (_m, c) in robot.peer)
    return Counter(names) == Counter({"head": 1, "tail": 1, "body": n - 2}) and chain and len(robot.peer) == 2 * (n - 1)


def test_dragon_becomes_an_11_module_snake(legs_to_snake: CompiledProgram) -> None:
    topo = parse_spec("dragon")
    robot = Robot(legs_to_snake, topo, seed=4)
    robot.inject(topo.module_index("tail2"), Hormone("LTS"))  # through any module
    log = run_logged(robot, 400)
    assert is_snake(robot)
    assert robot.engine(topo.module_index("spine0")).topo_type.name == "head"
    # LTS reaches everyone; only feet react to it, each starting RCT
    lts_binders = {m for c, m, t, d, h in log if d == "sent" and h == "RCT" and t in FEET}
    assert lts_binders == {topo.module_index(n) for n in topo.names if "leg" in n}
    # RCT is bound only by tails: every TAR comes from a module that was the tail then
    tar_senders = [(c, m) for c, m, t, d, h in log if d == "sent" and h == "TAR" and t == "tail"]
    assert len(tar_senders) == 4
    assert len([1 for c, m, t, d, h in log if d == "sent" and h == "TAR"]) > 4  # relayed on the way
    # exactly one foot wins each round: one ALT originates at a foot per TAR
    alt_origins = [(c, m) for c, m, t, d, h in log if d == "sent" and h == "ALT" and t in FEET]
    assert len(alt_origins) == 4 and len({m for _c, m in alt_origins}) == 4
    for (tc, _tail), (ac, _foot) in zip(tar_senders, alt_origins, strict=True):
        assert tc < ac
    # the ALT of each round reaches the tail of that round, which docks to the winning foot
    docks = [line for line in robot.log if "docked to" in line]
    assert len(docks) == 4
    # the tail that accepted a round is never a tail again
    assert len({m for _c, m in tar_senders}) == 4


def test_interrupted_round_resumes(legs_to_snake: CompiledProgram) -> None:
    topo = parse_spec("dragon")
    robot = Robot(legs_to_snake, topo, seed=9)
    robot.inject(topo.module_index("spine0"), Hormone("LTS"))
    killed: list[int] = []

    def kill_first_winner(_cycle: int) -> None:
        # the first foot to send ALT dies before the tail can dock to it
        if killed:
            return
        for m, e in enumerate(robot.engines):
            if e and e.topo_type.name in FEET and "RCT" not in e.periodics and e.counters["sent"] and m not in killed:
                killed.append(m)
                robot.kill(m)
                return

    log = run_logged(robot, 300, kill_first_winner)
    assert len(killed) == 1
    # the tail gave up on the dead foot, re-created its receptor, and the other 3 legs joined
    assert sum("docked to" in line for line in robot.log) == 3
    tails = [(c, m) for c, m, t, d, h in log if d == "sent" and h == "TAR" and t == "tail"]
    assert len(tails) == 4  # one round lost to the interruption, then three good ones
    assert tails[1][1] == tails[0][1]  # the same tail accepted again after RearmDelay
    assert tails[1][0] - tails[0][0] >= 80
    # the interruption is over: the foot restarts, hears LTS again, and is assimilated too
    robot.restart(killed[0])
    robot.inject(killed[0], Hormone("LTS"))
    run_logged(robot, 200)
    assert is_snake(robot)


def test_the_head_holds_still_until_no_feet_are_left_then_crawls(legs_to_snake: CompiledProgram) -> None:
    """The spine's front module is a head once its own legs are gone, while the rear feet
    still come to the tail; it holds still until the last tail, having heard no RCT for
    Quiet cycles, sends SNK; then the wave starts. Several seeds: the rounds' order differs."""
    topo = parse_spec("dragon")
    spine0 = topo.module_index("spine0")
    quiet = 60  # the program's Quiet: 3 * RctPeriod
    for seed in range(6):
        robot = Robot(legs_to_snake, topo, seed=seed)
        robot.inject(spine0, Hormone("LTS"))
        formed = moved = None
        for c in robot.iter_cycles(700):
            head = robot.engine(spine0)
            if formed is None and is_snake(robot):
                formed = c
            if head.dof[0] != 0 and moved is None:
                moved = c
        assert formed is not None, seed
        assert moved is not None and formed <= moved <= formed + quiet + 11 + 40, (seed, formed, moved)
