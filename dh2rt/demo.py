"""``dh2rt demo``: the paper's results on the in-process robot, shown in a terminal.

1. The caterpillar wave on an 8-module snake (DOF1 of each module, one row per cycle).
2. Live surgery: the snake cut in two, then four; every piece's front module becomes head.
3. Legs to snake: the dragon (11 modules) reconfigures itself into an 11-module snake.
"""

from __future__ import annotations

from typing import IO

from dh2rt.bundled import compile_bundled
from dh2rt.events import parse_event
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec


def _wave_row(robot: Robot) -> str:
    cells = []
    for e in robot.engines:
        if e is None:
            cells.append(" x ")
            continue
        mark = "^" if e.dof[0] > 0 else "v" if e.dof[0] < 0 else "-"
        head = "H" if e.topo_type.name == "head" else " "
        cells.append(f"{head}{mark} ")
    return "".join(cells)


def run_demo(cycles: int, out: IO[str]) -> int:
    """Run the three scenes; return 0 when every scene shows what the paper reports."""
    ok = True
    caterpillar = compile_bundled("caterpillar.dh2")
    topo = parse_spec("snake:8")
    robot = Robot(caterpillar, topo, seed=7)
    print("1. Caterpillar (Table I) on snake:8 -- DOF1 per module (^ +45, v -45), H = head", file=out)
    first_wave = 0
    for c in robot.iter_cycles(min(cycles, 120)):
        if robot.engine(0).dof[0] != 0 and not first_wave:
            first_wave = c
        if first_wave and c - first_wave < 14:
            print(f"   cycle {c:4d}  {_wave_row(robot)}", file=out)

    print("\n2. Live surgery: cut snake:8 into 2, then 4 snakes", file=out)
    events = [
        parse_event(e, topo, caterpillar.vocabulary) for e in ("130:cut:m3.back", "170:cut:m1.back", "170:cut:m5.back")
    ]
    for c in robot.iter_cycles(max(cycles - robot.cycle, 100), events):
        if c in (129, 131, 171, 200):
            names = [topo.names[i] for i, e in enumerate(robot.engines) if e and e.topo_type.name == "head"]
            print(f"   cycle {c:4d}  {_wave_row(robot)}  heads: {', '.join(names)}", file=out)
    heads = sum(1 for e in robot.engines if e and e.topo_type.name == "head")
    ok &= heads == 4
    print(f"   -> {heads} snakes, each with its own head and wave", file=out)

    print("\n3. Legs to snake on the dragon (Fig. 5, Fig. 7)", file=out)
    l2s = compile_bundled("legs_to_snake.dh2")
    dragon = parse_spec("dragon")
    robot = Robot(l2s, dragon, seed=1)
    robot.run(300, [parse_event("5:inject:spine0:LTS", dragon, l2s.vocabulary)])
    for line in robot.log:
        print(f"   {line}", file=out)
    types = [e.topo_type.name for e in robot.engines if e]
    snake = types.count("head") == 1 and types.count("tail") == 1 and types.count("body") == len(types) - 2
    ok &= snake
    print(
        f"   -> {'an' if snake else 'NOT an'} {len(types)}-module snake: {types.count('head')} head, "
        f"{types.count('body')} body, {types.count('tail')} tail",
        file=out,
    )
    print("\ndemo " + ("ok" if ok else "FAILED"), file=out)
    return 0 if ok else 1
