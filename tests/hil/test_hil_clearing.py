"""The robot crawls clear of a dead foot in the loop (hil.reach_loop, firmware.motion.clearing).

legs_to_snake on the dragon with the PyBullet stand-in; left_leg0 is killed, let go of the
body and laid behind the tail's back, front to it, where a foot killed as its dock began
lies. When the next winner's round begins, the robot's body crawls (the caterpillar's wave
through the modules' own servos, firmware.control.Hold) until nothing lies on the spot, the
world pushing the tail ``docking`` = 1 meanwhile, and only then does the foot let go and set
off. The same staging in one process: tests/sim/test_clearing.py.
"""

from __future__ import annotations

import math
import re
import time
from pathlib import Path

import pytest

from dh2rt.compiler import compile_file
from dh2rt.events import parse_event
from dh2rt.profile import CONRO
from dh2rt.topology import parse_spec
from hil.world import World
from tests.marks import LONG

ROOT = Path(__file__).resolve().parents[2]
FRONT, BACK = CONRO.connector_index("front"), CONRO.connector_index("back")
#: Where the dead foot's centre is laid, behind the tail's back (m).
BEHIND_M = 0.12


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


@LONG  # a whole reconfiguration in the loop (in physics: tests/sim/test_clearing.py)
def test_the_robot_crawls_clear_of_a_dead_foot_in_the_loop() -> None:
    program = compile_file(str(ROOT / "examples" / "legs_to_snake.dh2"))
    dragon = parse_spec("dragon")
    dead, tail = dragon.names.index("left_leg0"), dragon.names.index("tail4")
    world = World(program, dragon, "serial", seed=0, cycle_period=0.05, cycles=1200, stand_in="pybullet")
    reaches, physics = world.reaches, world.physics
    assert reaches is not None and physics is not None
    docking_sent: list[int | None] = []
    try:
        world.start()
        while world.cycle < 20:
            world.tick()
            time.sleep(0.01)
        world.kill(dead)
        world.cut(dead, FRONT)
        with physics.lock:
            pw = physics.world
            (px, py, pz), (nx, ny, _) = pw.connector_pose(tail, BACK)
            pw.set_module_pose(dead, (px + nx * BEHIND_M, py + ny * BEHIND_M, pz), math.degrees(math.atan2(-ny, -nx)))
        while world.cycle < 50:
            world.tick()
            time.sleep(0.01)
        world.apply(parse_event("50:inject:spine0:LTS", dragon, program.vocabulary))
        deadline = time.monotonic() + 90
        while not reaches.docking.trips and not world.done() and time.monotonic() < deadline:
            world.tick()
            if reaches.docking.clearings:
                docking_sent.append(reaches.docking_sent.get(tail))
            time.sleep(world.idle(0.01))  # as the launcher: woken for the motions' step
        log = list(world.log)
        assert reaches.docking.trips, log[-10:]
        winner = reaches.docking.trips[0].trip.module
        with physics.lock:
            (px, py, _), _ = physics.world.connector_pose(tail, BACK)
            lying = math.dist((px, py), physics.world.module_position(dead)[:2])
        taken = reaches.spot_taken((tail, BACK), winner)  # reads the tracker under the lock itself
    finally:
        world.stop()
    asked = [i for i, line in enumerate(log) if "lies behind tail4.back; the robot crawls clear first" in line]
    crawled = [i for i, line in enumerate(log) if "tail4.back: crawled" in line]
    released = [i for i, line in enumerate(log) if f"{dragon.names[winner]}.front released" in line]
    assert len(asked) == 1 and "left_leg0 lies behind" in log[asked[0]], log
    assert len(crawled) == 1 and "the spot clear" in log[crawled[0]], log
    found = re.search(r"crawled (\d+) gait cycles \((\d+) world cycles missed\)", log[crawled[0]])
    assert found is not None
    gait_cycles, missed = int(found[1]), int(found[2])
    assert missed <= gait_cycles * 4, log[crawled[0]]  # at most a tenth of its 40-cycle gait cycles
    assert released and asked[0] < crawled[0] < released[0], log  # the foot let go only after
    # the tail was told it is docking while the robot crawled (its countdown pauses)
    assert docking_sent and docking_sent[-1] == 1
    assert taken is None and lying > BEHIND_M + 0.08, lying
