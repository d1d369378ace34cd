"""Live surgery in physics at the timings that froze a piece before (mail in flight across
the cut link), and a few around them: every piece re-types itself and its joints keep moving."""

from __future__ import annotations

import pytest

from dh2rt.events import parse_event
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec
from sim.runner import PhysicsRun

# (event, seed): 199..229 with seed 3 froze the rear piece; the others are neighbours in time
SAMPLES = [
    ("199:cut:m3.back", 3),
    ("209:cut:m3.back", 3),
    ("229:cut:m3.back", 3),
    ("200:cut:m3.back", 0),
    ("214:kill:m3", 1),
]


@pytest.mark.parametrize(("event", "seed"), SAMPLES)
def test_cut_snake_keeps_both_pieces_moving_in_physics(caterpillar: CompiledProgram, event: str, seed: int) -> None:
    topo = parse_spec("snake:8")
    run = PhysicsRun(Robot(caterpillar, topo, seed=seed))
    try:
        ev = parse_event(event, topo, caterpillar.vocabulary)
        run.run(ev.cycle)
        run.run(2, [ev])
        types = [e.topo_type.name if e else None for e in run.robot.engines]
        if ev.kind == "kill":
            assert types == ["head", "body", "tail", None, "head", "body", "body", "tail"], types
        else:
            assert types == ["head", "body", "body", "tail"] * 2, types
        angles: dict[int, set[float]] = {m: set() for m in range(8) if run.robot.alive(m)}
        for _ in range(2 * caterpillar.clock_cycle):
            run.cycle()
            for m in angles:
                angles[m].add(round(run.world.joint_angles(m)[0]))
        frozen = [topo.names[m] for m, seen in angles.items() if max(seen) - min(seen) < 30]
        assert not frozen, f"joints that stopped after {event}: {frozen}"
    finally:
        run.close()
