"""Bad images are refused by every module of a running robot, in the loop, and the robot keeps
running its old program.

The robot: 4 modules on python-can's virtual bus (threads of this process) run the caterpillar
signed as version 1. On a bus a programming cable can touch any free connector (the head's
front, the others' left), so each module in turn is offered each bad image directly through
``dh2rt flash``: tampered (one bit of the signature flipped), signed by a key no module trusts,
and rolled back (version 0, signed by the robot's own key). Each is refused by the module at the
cable with its verdict, counted in that module's status, and passed on to nobody; no module
switches, and the wave goes on. An unsigned image never reaches a module: ``dh2rt flash`` refuses
it before it sends a byte (exit 2); the modules' own refusal of one is tested in
tests/firmware/test_flash_slots.py.
"""

from __future__ import annotations

import contextlib
import functools
import io
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dh2rt.signed_image import new_private_key, pack
from hil.world import World
from tests.hil.flashing import beside, caterpillar, running_snake, tick_until
from tools.flash import main

N = 4
WAIT = 40.0
LEFT = 3


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


@pytest.fixture(scope="module")
def robot() -> Iterator[World]:
    with running_snake("virtual", N, seed=1, wait=WAIT) as world:
        yield world


def bad_images(world: World) -> dict[str, bytes]:
    assert world.signer is not None
    good = pack(caterpillar(20).image, 2, world.signer)
    # one bit of the signature (a bit of the body would not even decompress, and dh2rt flash
    # refuses to send an image it cannot read: the modules would never see it)
    tampered = bytearray(good)
    tampered[-1] ^= 0x10
    return {
        "unsigned": caterpillar(20).image,
        "tampered": bytes(tampered),
        "wrong key": pack(caterpillar(20).image, 2, new_private_key()),
        "rollback": pack(caterpillar(20).image, 0, world.signer),
    }


def flash_at(world: World, module: int, image: Path) -> tuple[int, dict[str, Any]]:
    """``dh2rt flash`` with the cable against ``module``'s free connector; (exit code, report),
    the report being ``{"error": message}`` when the command refused before sending."""
    connector = 1 if module == 0 else LEFT
    mate, contact = world.touch_cable(module, connector)
    channel = world.transport_spec.partition(":")[2]
    argv = [str(image), "-i", "virtual", "-c", channel, "--contact", contact, "--cable-connector",
            world.profile.connector_name(mate), "--timeout", str(WAIT), "--json", "--quiet"]  # fmt: skip

    def run() -> tuple[int, str]:
        buf, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(err):
            code = main(argv)
        return code, buf.getvalue() or err.getvalue()

    try:
        code, text = beside(world, run, WAIT + 10)
    finally:
        world.pull_cable(module, connector, mate)
    if code == 2:
        return code, {"error": text}
    assert text.startswith("{"), (code, text)
    return code, json.loads(text)


def refused(world: World, module: int) -> dict[str, int]:
    return dict(world.views[module].status.get("program", {}).get("refused", {}))


@pytest.mark.parametrize("module", range(N))
def test_every_module_refuses_every_bad_image_and_runs_on(robot: World, module: int, tmp_path: Path) -> None:
    world = robot
    for kind, data in bad_images(world).items():
        image = tmp_path / f"{kind.replace(' ', '-')}.img"
        image.write_bytes(data)
        verdict = "rollback" if kind == "unsigned" else kind
        before = refused(world, module).get(verdict, 0)
        cycle = world.cycle
        code, report = flash_at(world, module, image)
        if kind == "unsigned":  # refused by the flasher before a byte crossed: nobody counts it
            assert code == 2 and "unsigned image" in report["error"], report
            assert refused(world, module).get(verdict, 0) == before, refused(world, module)
            continue
        assert code == 1, (kind, report)
        (at_cable,) = [m for m in report["modules"] if len(m["path"].split()) == 1]
        # an unsigned image states version 0, below the one running: the module declines it at
        # its offer, before a byte crosses, as a rollback
        verdict = "rollback" if kind == "unsigned" else kind
        assert at_cable["outcome"] == "refused" and at_cable["verdict"] == verdict, (kind, at_cable)
        assert all(m["outcome"] != "committed" for m in report["modules"]), report
        # the module counts it (its status, every few cycles), and every module runs version 1 still
        counted = functools.partial(lambda v, n: refused(world, module).get(v, 0) == n, verdict, before + 1)
        assert tick_until(world, counted, 10.0), (kind, refused(world, module))
        versions = [v.status.get("program", {}).get("version") for v in world.views]
        assert versions == [1] * N, (kind, versions)
        assert not any("switched to program" in line for line in world.log), world.log[-10:]
        assert world.cycle > cycle and all(v.alive and not v.failed for v in world.views)
    # the wave went on: the head kept emitting and the tail kept receiving
    counters = [v.status.get("counters", {}) for v in world.views]
    assert counters[-1].get("hormones_received", 0) > 0, counters[-1]
