"""firmware.motion is sans-IO: readings in, joint targets and a latch request out, no simulator.

The motions here run on numbers alone: a chain whose servos reach every target at once
(the joints read what was sent), the infrared computed from the chain's own kinematics, the
tracker's poses set by hand. What they do on a floor is measured in tests/sim.
"""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest

from dh2rt.docking import End
from dh2rt.profile import CONRO
from firmware.motion.body import BACK as BACK_PART
from firmware.motion.body import DEFAULT_MODEL
from firmware.motion.crawl import HOLD_MM, Creep
from firmware.motion.gaits import creep as creep_gait
from firmware.motion.kinematics import Chain
from firmware.motion.reach import Reach
from firmware.motion.readings import FloorPoses, ModulePose, PartPose, Readings, TrackerMissing

MOTION = Path(__file__).resolve().parents[2] / "firmware" / "motion"
#: What a module's motion must not touch: a simulator, the test bench, sockets, files, clocks.
FORBIDDEN = {"pybullet", "sim", "hil", "tools", "socket", "time", "os", "pathlib", "threading", "asyncio", "random"}

FRONT, BACK = CONRO.connector_index("front"), CONRO.connector_index("back")
#: A snake of five: module k's back docked to module k+1's front.
LINKS: dict[End, End] = {}
for k in range(4):
    LINKS[(k, BACK)], LINKS[(k + 1, FRONT)] = (k + 1, FRONT), (k, BACK)


def test_the_motion_package_imports_no_simulator_socket_file_or_clock() -> None:
    modules = sorted(MOTION.glob("*.py"))
    motions = {"body", "kinematics", "readings", "reach", "gaits", "crawl", "clearing", "docking", "underway"}
    assert {p.stem for p in modules} >= motions
    for path in modules:
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            else:
                continue
            for name in names:
                assert name.split(".")[0] not in FORBIDDEN, f"{path.name} imports {name}"


def readings_of(chain: Chain, q_deg: dict[tuple[int, int], float], ir: tuple[float, float]) -> Readings:
    joints: dict[int, tuple[float, float]] = {}
    for (m, dof), v in q_deg.items():
        pos = list(joints.get(m, (0.0, 0.0)))
        pos[dof] = v
        joints[m] = (pos[0], pos[1])
    name = DEFAULT_MODEL.connector(chain.asking[1]).name
    return Readings(joints, {chain.asking[0]: {f"ir_{name}": ir[0], f"ir_{name}_align": ir[1]}})


def test_a_reach_on_ideal_servos_closes_the_loop_from_its_own_joint_angles() -> None:
    """The tail's back (module 4) to the head's front (module 0) of a snake of five: the
    motion reads only the joints it moved (ideal servos) and an infrared pair that sees the
    face once the kinematics put it within 2 cm; it asks for the latch then, and not before."""
    chain = Chain.along(DEFAULT_MODEL, (4, BACK), (FRONT,) * 4, LINKS.get, FRONT)
    start = dict.fromkeys(chain.joints, 0.0)
    reach = Reach(chain, readings_of(chain, start, (0.0, 180.0)), 0.02, 20.0, wiggle_deg=0.0)
    assert reach.modules == {0, 1, 2, 3, 4}
    q = start
    asked_at = None
    for cycle in range(400):
        gap = float(np.linalg.norm(chain.error(np.radians([q[j] for j in chain.joints]))[:3]))
        ir = (max(1.0, gap * 1000), 5.0) if gap < 0.02 else (0.0, 180.0)
        r = readings_of(chain, q, ir)
        if reach.asks_latch(r):
            asked_at = cycle
            reach.latch()
            break
        targets = reach.step(r)
        q = {(m, dof): targets[m][dof] for m, dof in chain.joints}
    assert asked_at is not None and reach.done and reach.latched
    final = chain.error(np.radians([q[j] for j in chain.joints]))
    assert float(np.linalg.norm(final[:3])) < 0.02


def test_a_reach_that_never_sees_the_face_gives_up_at_its_timeout() -> None:
    chain = Chain.along(DEFAULT_MODEL, (3, BACK), (FRONT, FRONT, FRONT), LINKS.get, FRONT)
    q = dict.fromkeys(chain.joints, 0.0)
    reach = Reach(chain, readings_of(chain, q, (0.0, 180.0)), 0.02, 20.0, timeout=30)
    for _ in range(30):
        reach.step(readings_of(chain, q, (0.0, 180.0)))
        assert not reach.done
    reach.step(readings_of(chain, q, (0.0, 180.0)))
    assert reach.done and not reach.latched and reach.cycles == 31


def test_a_reach_to_another_body_needs_the_tracker() -> None:
    """A target on a body no route reaches is found by the overhead tracker; without its
    report the motion says so instead of guessing."""
    chain = Chain.to_other(DEFAULT_MODEL, (3, BACK), (FRONT,), LINKS.get, (9, FRONT), free_distance=True)
    r = readings_of(chain, dict.fromkeys(chain.joints, 0.0), (0.0, 180.0))
    with pytest.raises(TrackerMissing, match="has not reported module 2"):
        Reach(chain, r, 0.02, 20.0)


def _straight_tail_and_foot(aside_m: float = 0.0) -> tuple[Chain, FloorPoses, float]:
    """Modules 2 and 3 lying along +x, 3 behind 2, and a foot (module 9) 5 cm behind module
    3's back face, square, facing it: the chain of module 3's back face to the foot's front,
    the tracker's report (module 3's parts ``aside_m`` off the line along y: its dock to
    module 2 gave under load, which the chain's kinematics cannot know), and the face's x."""
    model = DEFAULT_MODEL
    chain = Chain.to_other(model, (3, BACK), (FRONT,), LINKS.get, (9, FRONT), free_distance=True)
    face_x = -model.back.half[0] - model.length
    flat = PartPose(0.0, 0.0, 0.0)
    back = PartPose(face_x + model.back.half[0], aside_m, 0.0)  # module 3's back part
    inside = Chain.to_own_centre(model, (3, BACK))
    own = inside.target_part(np.zeros(len(inside.joints)))  # its centre, seen from there (joints at 0)
    centre_xy = back.transform() @ own[:, 3]
    centre = PartPose(float(centre_xy[0]), float(centre_xy[1]), 0.0)
    foot_front = PartPose(face_x - 0.05 - model.front.half[0], 0.0, 0.0)  # facing +x, towards the face
    floor = FloorPoses(
        {
            2: ModulePose(flat, flat, flat),  # module 2's back part at the origin: the chain's end
            3: ModulePose(centre, centre, back),
            9: ModulePose(flat, foot_front, flat),
        }
    )
    return chain, floor, face_x


def test_a_foot_square_behind_the_face_per_the_tracker_asks_for_no_bend() -> None:
    """The tracker puts module 2's back part at the origin facing +x and a foot's front 5 cm
    behind module 3's back face, square: the plan leaves the chain straight."""
    chain, floor, face_x = _straight_tail_and_foot()
    joints = readings_of(chain, dict.fromkeys(chain.joints, 0.0), (0.0, 180.0))
    reach = Reach(chain, Readings(joints.joints, joints.infrared, floor), 0.02, 20.0)
    assert chain.anchor == (2, BACK_PART)
    assert float(np.max(np.abs(np.degrees(reach.plan)))) < 1.0
    face = floor.face(DEFAULT_MODEL, 9, FRONT)
    assert face[:2] == pytest.approx((face_x - 0.05, 0.0)) and face[2:] == pytest.approx((1.0, 0.0))


@pytest.mark.parametrize("aside_m", [-0.02, 0.01, 0.02])
def test_a_reach_to_a_foot_sees_the_face_where_the_tracker_shows_it_not_where_the_docks_would_put_it(
    aside_m: float,
) -> None:
    """A dock gives under a bent chain's load (up to 9 degrees), so the asking face is not
    where the chain's kinematics from its far end put it. The reach reads where the foot lies
    from the asking module's own centre as the tracker shows it (seed 2's legs to snake: the
    kinematics said square while the face stood 2 cm aside of the foot for 400 cycles, and
    neither infrared pair ever saw the other). ``tracked=False`` is the chain alone."""
    chain, floor, _ = _straight_tail_and_foot(aside_m)
    joints = readings_of(chain, dict.fromkeys(chain.joints, 0.0), (0.0, 180.0))
    readings = Readings(joints.joints, joints.infrared, floor)
    seeing = Reach(chain, readings, 0.02, 20.0)
    lateral = chain.error_of(seeing.relative(readings))
    blind = Reach(chain, readings, 0.02, 20.0, tracked=False)
    assert float(lateral[1]) == pytest.approx(-aside_m, abs=1e-3)  # the foot lies -aside_m off the face's axis
    assert float(np.linalg.norm(blind.chain.error_of(blind.relative(readings))[:3])) < 1e-3


def test_creep_holds_when_its_front_infrared_reads_the_face_close() -> None:
    creep = Creep(5)
    far = Readings(infrared={5: {"ir_front": 40.0, "ir_front_align": 3.0}})
    near = Readings(infrared={5: {"ir_front": HOLD_MM - 1, "ir_front_align": 3.0}})
    assert creep.step(far) == creep_gait(1)
    assert creep.step(near) == (0.0, 0.0) and creep.holding
    with pytest.raises(KeyError, match="no ir_front reading of module 5"):
        creep.step(Readings())


def test_a_part_pose_turns_a_face_with_its_heading() -> None:
    pose = ModulePose(PartPose(1.0, 2.0, 0.0), PartPose(1.0, 2.0, math.pi / 2), PartPose(0.0, 0.0, 0.0))
    x, y, nx, ny = FloorPoses({4: pose}).face(DEFAULT_MODEL, 4, "front")
    assert (x, y, nx, ny) == pytest.approx((1.0, 2.0 + DEFAULT_MODEL.front.half[0], 0.0, 1.0))


def test_an_imu_tilt_turns_a_floor_pose_as_the_imu_reads_it() -> None:
    """Pitch > 0 is front end down (the profile's ``pitch``), roll > 0 left side up."""
    pose = PartPose(0.5, 0.0, math.pi / 2)
    pitched = pose.transform(0.0, 30.0)
    assert pitched[:3, 0] == pytest.approx((0.0, math.cos(math.radians(30)), -0.5))  # x axis: forward, down
    rolled = pose.transform(30.0, 0.0)
    assert rolled[2, 1] == pytest.approx(0.5)  # the left (y) axis rises
    assert pitched[:2, 3] == pytest.approx((0.5, 0.0))
