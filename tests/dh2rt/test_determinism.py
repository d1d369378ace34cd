"""Runs depend on program, topology and seed only: not on module numbering or step order."""

from __future__ import annotations

import itertools
import json
import random
from pathlib import Path

from dh2rt.events import parse_event
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.testing import robot_snapshot
from dh2rt.topology import Link, Topology, parse_spec

Behaviour = list[list[tuple[object, ...]]]


def behaviour(robot: Robot, cycles: int, events: tuple[str, ...] | list[str] = ()) -> Behaviour:
    """Per module, per cycle: type, DOF1/DOF2, hormones received and sent (by connector)."""
    evs = [parse_event(e, robot.topology, robot.program.vocabulary) for e in events]
    out: Behaviour = [[] for _ in range(robot.size)]
    robot.record = True
    for _ in robot.iter_cycles(cycles, evs):
        for rec in sorted(robot.records, key=lambda r: r.module):
            e = robot.engine(rec.module)
            out[rec.module].append(
                (
                    e.topo_type.name,
                    tuple(e.dof),
                    tuple((a.at, a.remote, a.hormone) for a in rec.received),
                    tuple((x.through, x.hormone) for x in rec.sent),
                )
            )
        robot.records.clear()
    return out


def test_same_seed_same_run_different_seed_different_phases(locomotion: CompiledProgram) -> None:
    topo = parse_spec("hexapod")
    a = behaviour(Robot(locomotion, topo, seed=42), 150, ["60:cut:spine0.back"])
    b = behaviour(Robot(locomotion, topo, seed=42), 150, ["60:cut:spine0.back"])
    c = behaviour(Robot(locomotion, topo, seed=43), 150, ["60:cut:spine0.back"])
    assert a == b
    assert a != c


def test_step_order_does_not_matter(legs_to_snake: CompiledProgram) -> None:
    topo = parse_spec("dragon")
    runs = []
    for order in (None, "reversed", "shuffled"):
        robot = Robot(legs_to_snake, topo, seed=8)
        if order == "reversed":
            robot.step_order.reverse()
        elif order == "shuffled":
            random.Random(1).shuffle(robot.step_order)
        runs.append(behaviour(robot, 250, ["3:inject:tail1:LTS"]))
    assert runs[0] == runs[1] == runs[2]


def test_module_numbering_does_not_matter(caterpillar: CompiledProgram) -> None:
    topo = parse_spec("snake:9")
    perm = list(range(9))
    random.Random(5).shuffle(perm)  # old index -> new index
    renamed = Topology(
        topo.profile,
        tuple(topo.names[perm.index(i)] for i in range(9)),
        tuple(Link(perm[k.a], k.a_conn, perm[k.b], k.b_conn) for k in topo.links),
        "permuted",
    )
    phases = [random.Random(3).randrange(40) for _ in range(9)]
    a = behaviour(Robot(caterpillar, topo, timer_phases=phases), 200)
    b = behaviour(Robot(caterpillar, renamed, timer_phases=[phases[perm.index(i)] for i in range(9)]), 200)
    assert [b[perm[i]] for i in range(9)] == a


def test_skipping_quiet_cycles_changes_nothing(legs_to_snake: CompiledProgram, locomotion: CompiledProgram) -> None:
    scenarios = [
        (legs_to_snake, "dragon", ["3:inject:tail1:LTS", "90:kill:left_leg1", "200:restart:left_leg1"]),
        (locomotion, "octopod", ["50:cut:spine1.back", "120:dock:spine1.back-spine2.front", "130:kill:spine0"]),
        (locomotion, "snake:12", ["40:cut:m5.back", "77:restart:m3", "90:inject:m8:X(C)"]),
    ]
    for program, spec, events in scenarios:
        topo = parse_spec(spec)
        fast = Robot(program, topo, seed=6, skip_quiet=True)
        slow = Robot(program, topo, seed=6, skip_quiet=False)
        evs = [parse_event(e, topo, program.vocabulary) for e in events]
        fast_iter, slow_iter = fast.iter_cycles(300, evs), slow.iter_cycles(300, evs)
        for _ in range(300):
            next(fast_iter)
            next(slow_iter)
            if fast.cycle % 17 == 0:
                assert robot_snapshot(fast) == robot_snapshot(slow), (spec, fast.cycle)
        assert robot_snapshot(fast) == robot_snapshot(slow)
        assert fast.log == slow.log
        assert len(fast.asleep()) > 0 or spec == "dragon"


def test_the_listing_order_changes_only_the_timer_phases(tmp_path: Path, caterpillar: CompiledProgram) -> None:
    """What depends on the order modules are listed in (README, dh2rt.robot.PhaseDraw): only the
    LocalTimer phases the seed draws, in that order. The same snake written as a TOML topology
    with its modules listed in two orders, each module given the same phase by name, runs the
    same, module by module; left to the seed, the same module gets another phase."""
    from dh2rt.topology import parse_spec

    names = ["head", "neck", "spine", "hip", "tail"]
    links = [f'"{a}.back <-> {b}.front"' for a, b in itertools.pairwise(names)]
    phase = dict(zip(names, (3, 17, 0, 29, 11), strict=True))
    runs = []
    drawn = []
    for order in (names, [names[i] for i in (3, 0, 4, 2, 1)]):
        path = tmp_path / f"{order[0]}.toml"
        path.write_text(f"modules = {json.dumps(order)}\nlinks = [{', '.join(links)}]\n")
        topo = parse_spec(str(path))
        robot = Robot(caterpillar, topo, seed=7, timer_phases=[phase[n] for n in topo.names])
        by_name = []
        for _ in range(120):
            robot.step()
            snap = robot_snapshot(robot)
            by_name.append({topo.names[m]: snap[m] for m in range(topo.size)})
        runs.append(by_name)
        seeded = Robot(caterpillar, topo, seed=7)
        drawn.append({topo.names[m]: seeded.engine(m).timer for m in range(topo.size)})
    assert runs[0] == runs[1]
    assert drawn[0] != drawn[1]  # the seed's draw follows the listing order
