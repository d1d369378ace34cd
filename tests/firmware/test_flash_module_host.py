"""The rollout inside the module program, in one process: ModuleHosts (each booted from its
own flash directory, a real one) on the in-process bus, stepped on one virtual clock, with a
FlashCable at the head's free front connector. Deterministic and quick, so the switch and
the recovery rules are swept over seeds and kill timings here; tests/hil/test_flash_loop.py
does the same with one OS process per module over serial links.
"""

from __future__ import annotations

import itertools
import queue
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from dh2rt.compiler import compile_file, compile_source
from dh2rt.errors import TransportError
from dh2rt.flash.pacing import Pacing
from dh2rt.signed_image import new_private_key, pack, public_key
from dh2rt.transport.base import BusEnd, FrameFamily
from dh2rt.transport.inproc import InprocTransport
from dh2rt.wire.transfer import Outcome, serial_cost
from firmware.config import ModuleConfig
from firmware.control import Command, Report, TraceRecord
from firmware.flash.cable import FlashCable, FlashResult, hello_codec
from firmware.flash.door import RolloutDoor
from firmware.main_loop import ModuleHost

ROOT = Path(__file__).resolve().parents[2]
PROGRAM = ROOT / "examples" / "caterpillar.dh2"
PERIOD = 0.02
FRONT, BACK = 1, 2
NEXT = {"A": "B", "B": "C", "C": "D", "D": "A"}
TABLE_I = {"A": -45.0, "B": -45.0, "C": 45.0, "D": 45.0}
CABLE_LINK = 999


def caterpillar(clock_cycle: int) -> Any:
    text = PROGRAM.read_text(encoding="utf-8")
    return compile_source(text.replace("const ClockCycle = 40", f"const ClockCycle = {clock_cycle}"))


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


class Robot:
    """A snake of ``n`` module hosts on an in-process bus: link k joins m(k).back (side 0)
    to m(k+1).front (side 1)."""

    def __init__(
        self, tmp: Path, n: int, seed: int, *, signer: bytes, image: bytes, trial_cycles: int = 30,
        images: dict[int, bytes] | None = None,
    ) -> None:  # fmt: skip
        self.tmp, self.n, self.signer = tmp, n, signer
        self.channel = f"rollout-host-{id(self):x}"
        self.clock = Clock()
        self.trial_cycles = trial_cycles
        self.phases = [(seed * 7 + 13 * m) % 40 for m in range(n)]
        self.records: list[dict[str, Any]] = []
        self.hosts: list[ModuleHost | None] = [None] * n
        self.lives = [0] * n
        self.cycle = 0
        for m in range(n):
            flash = tmp / f"m{m}"
            flash.mkdir()
            (flash / "program.img").write_bytes((images or {}).get(m, image))
            self.start(m)

    def start(self, m: int) -> None:
        attach: dict[int, Any] = {}
        if m > 0:
            attach[FRONT] = BusEnd(m - 1, 1)
        if m < self.n - 1:
            attach[BACK] = BusEnd(m, 0)
        config = ModuleConfig(
            module=m, name=f"m{m}", flash=str(self.tmp / f"m{m}"), trust=(public_key(self.signer),),
            transport=f"inproc:{self.channel}", timer_phase=self.phases[m], cycle_period=PERIOD, trace=True,
            trial_cycles=self.trial_cycles, driver="recording", life=self.lives[m],
        )  # fmt: skip
        self.lives[m] += 1
        commands: queue.Queue[Command] = queue.Queue()
        host = ModuleHost(config, commands, self._report(m))
        host.runtime.clock = self.clock
        for c, end in attach.items():
            host.runtime.attach(c, end)
        self.hosts[m] = host

    def _report(self, m: int) -> Callable[[Report], None]:
        def report(rep: Report) -> None:
            if isinstance(rep, TraceRecord):
                self.records.append(dict(rep.record))

        return report

    def kill(self, m: int) -> None:
        host = self.hosts[m]
        assert host is not None
        host.runtime.close()
        self.hosts[m] = None

    def step(self, cable: FlashCable | None = None) -> None:
        self.clock.t += PERIOD
        self.cycle += 1
        # tail first: what a module sends towards the tail is taken in at the next cycle, as
        # over a real link (the in-process bus delivers at once)
        for host in reversed(self.hosts):
            if host is not None and not host.stop_event.is_set():
                host.runtime.step()
                host.end_cycle(host.runtime)
        if cable is not None and not cable.flasher.done:
            cable.step(self.clock.t)
        for host in self.hosts:
            if host is not None:
                host.flush()

    def run(self, cycles: int, cable: FlashCable | None = None) -> None:
        for _ in range(cycles):
            self.step(cable)

    def cable(self, image: bytes) -> FlashCable:
        head = self.hosts[0]
        assert head is not None
        head.runtime.attach(FRONT, BusEnd(CABLE_LINK, 0))
        transport = InprocTransport(hello_codec(), channel=self.channel)
        transport.attach(1, BusEnd(CABLE_LINK, 1))
        pacing = Pacing(184, serial_cost)
        return FlashCable(image, transport, period=PERIOD, pacing=pacing, segment_size=80, clock=self.clock)

    def flash(self, image: bytes, limit: int = 1500) -> FlashResult:
        cable = self.cable(image)
        for _ in range(limit):
            if cable.flasher.done:
                break
            self.step(cable)
        head = self.hosts[0]
        if head is not None:
            head.runtime.detach(FRONT)  # the cable is pulled out
        return cable.result()

    def program_of(self, m: int) -> dict[str, Any]:
        host = self.hosts[m]
        assert host is not None
        status = host.program_status()
        assert status is not None
        return status


def door(robot: Robot, m: int) -> RolloutDoor:
    host = robot.hosts[m]
    assert host is not None and host.rollout is not None
    return host.rollout


def switch_cycles(robot: Robot) -> dict[int, int]:
    """Module -> the robot cycle it switched at, from its log."""
    out: dict[int, int] = {}
    for m, host in enumerate(robot.hosts):
        assert host is not None
        for line in host.runtime.log:
            if "switched to program" in line:
                out[m] = int(line.split()[1].rstrip(":"))
    return out


@pytest.fixture
def signer() -> bytes:
    return new_private_key()


@pytest.mark.parametrize("seed", [0, 1, 2, 5])
@pytest.mark.parametrize("start", [3, 47, 101])
def test_every_module_switches_at_one_cycle_and_the_wave_carries_on(
    tmp_path: Path, signer: bytes, seed: int, start: int
) -> None:
    old, new = compile_file(str(PROGRAM)), caterpillar(20)
    robot = Robot(tmp_path, 8, seed, signer=signer, image=pack(old.image, 1, signer))
    robot.run(start)
    result = robot.flash(pack(new.image, 2, signer))
    robot.run(200)
    assert result.succeeded, (result.failure, [m.describe() for m in result.modules])
    assert sorted(len(m.path) for m in result.modules) == list(range(1, 9))
    assert {m.outcome for m in result.modules} <= {Outcome.COMMITTED, Outcome.CONFIRMED}
    switched = switch_cycles(robot)
    assert len(switched) == 8 and len(set(switched.values())) == 1, switched
    at = switched[0]
    emitted = [r["cycle"] for r in sorted(robot.records, key=lambda r: r["cycle"]) if r["module"] == 0 and r["sent"]]
    assert {b - a for a, b in itertools.pairwise(emitted) if b < at} == {10}  # the pair across the switch is either
    assert {b - a for a, b in itertools.pairwise(emitted) if a >= at} == {5}
    # Table I hop by hop after the switch: module m gets in cycle k+1 what m-1 passed on in k
    sent = {(r["module"], r["cycle"]): r["sent"][0]["hormone"] for r in robot.records if r["sent"]}
    for r in robot.records:
        if r["module"] > 0 and r["cycle"] > at + 1 and r["received"]:
            (got,) = r["received"]
            assert sent[(r["module"] - 1, r["cycle"] - 1)] == got["hormone"], r
            assert r["actuators"]["DOF1"] == TABLE_I[got["hormone"][2]]
    for m in range(8):
        program = robot.program_of(m)
        assert program["version"] == 2 and not program["trial"], (m, program)
        host = robot.hosts[m]
        assert host is not None and host.runtime.counters["refused"] == 0
        # at most the one hormone in flight across the switch (sent by the old program in the
        # cycle before, read by the new one) is dropped as foreign
        assert host.runtime.stats.foreign_hormones <= 1


# -- the rollout's machinery is loaded when an image concerns the module (firmware/flash/door.py)


@pytest.mark.parametrize("seed", [0, 3])
def test_the_rollout_opens_at_the_first_transfer_frame_and_not_before(tmp_path: Path, signer: bytes, seed: int) -> None:
    old, new = compile_file(str(PROGRAM)), caterpillar(20)
    robot = Robot(tmp_path, 4, seed, signer=signer, image=pack(old.image, 1, signer))
    robot.run(120)  # Hellos, keep-alives and hormones only, every module on version 1
    assert [door(robot, m).host for m in range(4)] == [None] * 4
    result = robot.flash(pack(new.image, 2, signer))
    robot.run(100)
    assert result.succeeded, result.failure
    for m in range(4):
        assert door(robot, m).opened_by == f"a transfer frame through connector {FRONT}", m
        assert door(robot, m).switched and robot.program_of(m)["version"] == 2
    # the door stays the transport's one transfer handler once the host it opened takes them
    transport = door(robot, 0).rt.transport
    with pytest.raises(TransportError, match="transfer frames already go to"):
        transport.listen(FrameFamily.TRANSFER, lambda frame: None)
    assert transport.counters.unhandled == 0


def test_a_rollout_opened_between_ticks_answers_before_the_next(tmp_path: Path, signer: bytes) -> None:
    """The door hands its host the cycle under way (``Node.join_cycle``): the head's REQUEST
    to the cable's OFFER goes out in the cycle the OFFER opened the host in, before the
    host's first tick (a Rollout not told the cycle sent nothing before it)."""
    old, new = compile_file(str(PROGRAM)), caterpillar(20)
    robot = Robot(tmp_path, 2, 0, signer=signer, image=pack(old.image, 1, signer))
    robot.run(40)
    cable = robot.cable(pack(new.image, 2, signer))
    for _ in range(20):
        robot.step(cable)
        host = door(robot, 0).host
        if host is not None:
            break
    assert host is not None
    assert host.rollout.tick_count == 0  # opened in this cycle, after its start
    assert host.rollout.counters.units_sent > 0


def test_a_cycles_hormones_go_out_before_its_transfer_frames(
    tmp_path: Path, signer: bytes, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What the Rollout lets out in a cycle (its tick, and frames read in the cycle) goes
    through a connector after that cycle's hormones and beacons (``cycle_sent``): the line
    is the hormones' at each cycle start, as the pacing promises."""
    old, new = compile_file(str(PROGRAM)), caterpillar(20)
    robot = Robot(tmp_path, 3, 0, signer=signer, image=pack(old.image, 1, signer))
    robot.run(40)
    host = robot.hosts[1]
    assert host is not None
    rt = host.runtime
    sent: list[tuple[str, int]] = []  # ("step", 0), then ("link" or "transfer", connector)
    step, send, send_raw = rt.step, rt.transport.send, rt.transport.send_raw

    def traced_step() -> None:
        sent.append(("step", 0))
        step()

    def traced_send(through: int, frame: Any) -> bool:
        sent.append(("link", through))
        return send(through, frame)

    def traced_send_raw(through: int, payload: bytes) -> bool:
        sent.append(("transfer", through))
        return send_raw(through, payload)

    monkeypatch.setattr(rt, "step", traced_step)
    monkeypatch.setattr(rt.transport, "send", traced_send)
    monkeypatch.setattr(rt.transport, "send_raw", traced_send_raw)
    result = robot.flash(pack(new.image, 2, signer))
    assert result.succeeded, result.failure
    cycles = [list(g) for k, g in itertools.groupby(sent[1:], key=lambda e: e[0] == "step") if not k]
    both = 0
    for cycle in cycles:
        for connector in {c for kind, c in cycle if kind == "transfer"}:
            kinds = [kind for kind, c in cycle if c == connector]
            if "link" in kinds:
                both += 1
                assert kinds.index("transfer") > max(i for i, k in enumerate(kinds) if k == "link"), (connector, kinds)
    assert both > 10  # cycles in which both went through one connector


@pytest.mark.parametrize("behind", [0, 2, 3])
def test_a_neighbour_on_a_lower_version_opens_the_rollout_and_is_brought_up_to_date(
    tmp_path: Path, signer: bytes, behind: int
) -> None:
    """Module ``behind`` boots version 1 among modules on version 2 (a module swapped in from
    the shelf): its neighbours open their rollouts at its Hello and offer it their image."""
    old, new = compile_file(str(PROGRAM)), caterpillar(20)
    images = {behind: pack(old.image, 1, signer)}
    robot = Robot(tmp_path, 4, 1, signer=signer, image=pack(new.image, 2, signer), images=images)
    robot.run(400)
    neighbours = {m for m in (behind - 1, behind + 1) if 0 <= m < 4}
    for m in neighbours:
        assert (door(robot, m).opened_by or "").startswith("a neighbour on version 1"), m
    for m in set(range(4)) - neighbours - {behind}:
        assert door(robot, m).host is None, m  # nothing concerned it
    assert "transfer frame" in (door(robot, behind).opened_by or "")
    assert robot.program_of(behind)["version"] == 2


def test_an_image_received_in_part_before_a_restart_opens_the_rollout_at_boot(tmp_path: Path, signer: bytes) -> None:
    old, new = compile_file(str(PROGRAM)), caterpillar(20)
    robot = Robot(tmp_path, 4, 0, signer=signer, image=pack(old.image, 1, signer))
    robot.run(40)
    cable = robot.cable(pack(new.image, 2, signer))
    for _ in range(400):  # until module 2 holds part of the image, then it loses power
        robot.step(cable)
        host = door(robot, 2).host
        if host is not None and 0 < host.rollout.received < cable.flasher.info.length:
            break
    robot.kill(2)
    robot.start(2)
    assert door(robot, 2).opened_by == "an image received in part before this start"


def test_a_clean_trial_is_confirmed_on_the_writer_thread_and_said_once_written(tmp_path: Path, signer: bytes) -> None:
    """The confirmation's state write (two fsyncs) goes to the flash's writer thread, as the
    switch's does: the module's cycle never waits for it, and the module says "confirmed" (its
    log, its status, the rollout's CONFIRMED) only once it is on the flash."""
    import threading

    old, new = compile_file(str(PROGRAM)), caterpillar(20)
    robot = Robot(tmp_path, 3, 0, signer=signer, image=pack(old.image, 1, signer), trial_cycles=20)
    robot.run(10)
    where: dict[int, list[str]] = {m: [] for m in range(3)}
    for m in range(3):
        host = robot.hosts[m]
        assert host is not None
        confirm = host.flash.confirm  # type: ignore[union-attr]

        def on_writer(m: int = m, confirm: Callable[[], None] = confirm) -> None:
            where[m].append(threading.current_thread().name)
            confirm()

        host.flash.confirm = on_writer  # type: ignore[method-assign,union-attr]
    cable = robot.cable(pack(new.image, 2, signer))
    for _ in range(300):
        robot.step(cable)
        for m in range(3):
            opened = door(robot, m).host
            if opened is not None:  # writes in its own thread, as on the module's own clock
                opened.writer.threaded = lambda: True
        for host in robot.hosts:
            assert host is not None and host.rollout is not None
            host.rollout.settle()  # the virtual clock does not wait for the disk: wait here
    assert cable.result().succeeded, cable.result().failure
    assert where == {m: ["dh2rt-flash-writer"] for m in range(3)}, where
    for m in range(3):
        host = robot.hosts[m]
        assert host is not None
        assert sum("confirmed after its trial" in line for line in host.runtime.log) == 1, host.runtime.log[-5:]
        assert robot.program_of(m)["version"] == 2 and not robot.program_of(m)["trial"]
