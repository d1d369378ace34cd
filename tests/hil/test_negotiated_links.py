"""Links on a shared bus with no central assigner: the modules of each docked pair agree on a
link id over their connectors' local channels and claim it on the bus (dh2rt.negotiation);
the HIL world only plays the contacts.

Each test reads which link each module took from the module's own log line ("link
negotiated: connector C is link L side S"): nothing else knows it."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import can
import pytest

from dh2rt.bundled import compile_bundled
from dh2rt.topology import parse_spec
from dh2rt.wire.negotiation import MANAGEMENT_ID, BusMessage, BusOp, encode_bus
from hil.netns import in_namespace, namespace_problem
from hil.pace import PACE
from hil.world import World
from tests.marks import LONG, sweep

ROOT = Path(__file__).resolve().parents[2]
LINE = re.compile(r"^(m\d+): link (negotiated|given up): connector (\d+)(?: is link (\d+) side ([01]))?$")


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


def negotiations(log: list[str]) -> list[tuple[str, str, int, int | None, int | None]]:
    """(module, "negotiated" | "given up", connector, link, side), in log order."""
    out = []
    for line in log:
        if m := LINE.match(line):
            link = None if m[4] is None else int(m[4])
            side = None if m[5] is None else int(m[5])
            out.append((m[1], m[2], int(m[3]), link, side))
    return out


def current_links(log: list[str]) -> dict[int, set[tuple[str, int, int]]]:
    """Link id -> the (module, connector, side) ends holding it at the end of the log."""
    held: dict[tuple[str, int], tuple[int, int]] = {}
    for module, what, connector, link, side in negotiations(log):
        if what == "negotiated" and link is not None and side is not None:
            held[(module, connector)] = (link, side)
        else:
            held.pop((module, connector), None)
    links: dict[int, set[tuple[str, int, int]]] = defaultdict(set)
    for (module, connector), (link, side) in held.items():
        links[link].add((module, connector, side))
    return dict(links)


def launch(*args: str, timeout: float = 180) -> tuple[int, dict[str, Any], str]:
    cmd = [sys.executable, "-m", "hil.launcher", "--json", "--stand-in", "none", *args]
    proc = PACE.run(cmd, text=True, timeout=timeout, cwd=ROOT)
    return proc.returncode, json.loads(proc.stdout), proc.stderr


@LONG  # the scale sweep of test_eight_modules_alone_on_a_shared_bus's seven docks
def test_twenty_docks_at_once_on_one_bus_get_distinct_links() -> None:
    """A snake of 21: twenty pairs in contact at power-up, all negotiating at once."""
    code, summary, err = launch("--transport", "virtual", "--module-count", "21", "--cycles", "150", "--cycle-ms", "40")
    assert code == 0, (summary["problems"], err[-2000:])
    links = current_links(summary["log"])
    assert len(links) == 20
    for ends in links.values():  # each id held by exactly the two ends of one dock, opposite sides
        assert len(ends) == 2 and {side for _m, _c, side in ends} == {0, 1}, ends
        (m1, c1, _), (m2, c2, _) = sorted(ends)
        assert {c1, c2} == {1, 2} and abs(int(m1[1:]) - int(m2[1:])) == 1, ends
    rows = summary["modules"]
    assert [r["type"] for r in rows] == ["head"] + ["body"] * 19 + ["tail"]
    assert summary["frames"]["unaccounted"] == 0


@pytest.mark.parametrize("seed", sweep([0, 1]))
def test_undock_and_redock_get_a_fresh_link_and_a_restarted_module_rejoins(seed: int) -> None:
    code, summary, err = launch(
        "--transport", "virtual", "--module-count", "5", "--cycles", "320", "--cycle-ms", "20", "--seed", str(seed),
        "--event", "60:cut:m2.back", "--event", "100:dock:m2.back-m3.front",
        "--event", "140:kill:m4", "--event", "160:restart:m4",  # 160 cycles left to boot in
    )  # fmt: skip
    assert code == 0, (summary["problems"], err[-2000:])
    log = summary["log"]
    steps = negotiations(log)

    def links_of(module: str, connector: int) -> list[int]:
        return [link for m, what, c, link, _s in steps if m == module and c == connector and link is not None]

    assert len(links_of("m2", 2)) == 2 and len(set(links_of("m2", 2))) == 2  # re-docked: a fresh id
    assert links_of("m2", 2) == links_of("m3", 1)
    assert len(links_of("m4", 1)) == 2 and len(set(links_of("m4", 1))) == 2  # restarted: rejoined, fresh id
    assert links_of("m3", 2) == links_of("m4", 1)  # the neighbour followed it
    assert ("m2", "given up", 2, None, None) in steps and ("m3", "given up", 1, None, None) in steps
    assert [r["type"] for r in summary["modules"]] == ["head", "body", "body", "body", "tail"]
    assert len(current_links(log)) == 4


@pytest.mark.realtime
def test_an_injected_id_collision_is_resolved() -> None:
    """A forged HOLD of a link's id with the lowest tag there is, on the robot's own bus:
    the pair holding that id loses it by the rule, negotiates a fresh one, and the robot runs
    on with every link."""
    program = compile_bundled("caterpillar.dh2")
    topology = parse_spec("snake:3")
    channel = f"collision-{os.getpid()}"
    world = World(program, topology, f"virtual:{channel}", cycle_period=0.02, cycles=250, stand_in="none")
    intruder = can.Bus(interface="virtual", channel=channel)
    try:
        world.start()
        deadline = time.monotonic() + 30
        forged = False
        while not world.done() and time.monotonic() < deadline:
            world.tick()
            if not forged and world.cycle >= 60:
                link = min(current_links(world.log))
                data = encode_bus(BusMessage(BusOp.HOLD, link, 1))
                for _ in range(3):  # a few cycles of it, as a real rival would re-announce
                    intruder.send(can.Message(arbitration_id=MANAGEMENT_ID, data=data, is_extended_id=True))
                    time.sleep(0.02)
                forged = True
            time.sleep(0.01)
    finally:
        intruder.shutdown()
        world.stop()
    assert forged
    after = current_links(world.log)
    assert link not in after and len(after) == 2  # the pair took another id
    given_up = [s for s in negotiations(world.log) if s[1] == "given up"]
    assert len(given_up) == 2  # both ends of that one pair, nobody else
    assert [v.status.get("type") for v in world.views] == ["head", "body", "tail"]


@pytest.mark.realtime
def test_eight_modules_alone_on_a_shared_bus(tmp_path: Path) -> None:
    """Eight `dh2rt module` processes on python-can udp_multicast (inside a private network
    namespace), each with only its module.toml; the contact emulator plays the infrared pairs.
    No world: nobody assigns links, says when to start, or tells a module its type."""
    if why := namespace_problem():
        pytest.skip(why)
    script = ROOT / "tests" / "hil" / "alone_on_a_bus.py"
    cmd = in_namespace([sys.executable, str(script), str(tmp_path)])
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180, cwd=ROOT, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.splitlines()[-1])
    finals = result["finals"]
    assert all(code == 0 for code in result["codes"]), result["codes"]
    assert [f["type"] for f in finals] == ["head"] + ["body"] * 6 + ["tail"]
    assert all(f["counters"]["refused"] == 0 for f in finals)
    links = current_links(result["log"])
    assert len(links) == 7 and all(len(ends) == 2 for ends in links.values())
    # Table I on the wire: each X arrives down the snake, one hop a cycle, the phase advancing
    hormones = result["hormones"]  # [time, link, side, text] of every hormone frame
    order = [links_by_position(links, k) for k in range(7)]
    starts = [h for h in hormones if h[1] == order[0]][3:6]
    assert starts
    phases = "ABCD"
    for start in starts:
        t, phase = start[0], phases.index(start[3][2])
        for k in range(1, 7):
            phase = (phase + 1) % 4
            nxt = next(h for h in hormones if h[1] == order[k] and h[0] > t)
            assert nxt[3] == f"X({phases[phase]})" and nxt[0] - t < 0.1, (k, nxt)
            t = nxt[0]


def links_by_position(links: dict[int, set[tuple[str, int, int]]], k: int) -> int:
    """The link between module k (its back) and k + 1."""
    return next(link for link, ends in links.items() if (f"m{k}", 2) in {(m, c) for m, c, _s in ends})
