"""The module runtime in one process on the inproc transport, with injected clocks.

Modules are stepped one after another (A then B then ...): on the inproc bus a frame sent in
A's cycle n is in B's mailbox for B's cycle n, so every count here is exact.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from dh2rt.compiler import compile_file
from dh2rt.hormone import Hormone
from dh2rt.program import CompiledProgram
from dh2rt.runtime import SILENCE_CYCLES, ModuleRuntime
from dh2rt.testing import FakeClock, runtime_chain, step_all
from dh2rt.transport.base import BusEnd
from dh2rt.transport.inproc import InprocBus, InprocTransport
from dh2rt.wire.frame import NO_PROGRAM, FrameCodec, Hello, KeepAlive
from drivers.recording import RecordingDriver

ROOT = Path(__file__).resolve().parents[2]
FRONT, BACK = 1, 2
TABLE_I = {"A": -45.0, "B": -45.0, "C": 45.0, "D": 45.0}  # body receptors: DOF1 per hormone got


@pytest.fixture(scope="module")
def caterpillar() -> CompiledProgram:
    return compile_file(str(ROOT / "examples" / "caterpillar.dh2"))


def make(program: CompiledProgram, bus: InprocBus, phase: int = 0, **kw: object) -> ModuleRuntime:
    codec = FrameCodec(program.vocabulary, program.profile.connector_count)
    return ModuleRuntime(program, InprocTransport(codec, bus=bus), timer_phase=phase, clock=FakeClock(0.001), **kw)  # type: ignore[arg-type]


def snake(program: CompiledProgram, n: int, phases: list[int] | None = None) -> list[ModuleRuntime]:
    """n runtimes docked back-to-front on a fresh bus, links attached (Hellos exchanged)."""
    return runtime_chain(program, n, phases=phases, driver=lambda _i: RecordingDriver(), record=True)


@pytest.fixture
def closing() -> Iterator[list[ModuleRuntime]]:
    made: list[ModuleRuntime] = []
    yield made
    for m in made:
        m.close()


def test_hellos_verify_links_and_set_topological_types(
    caterpillar: CompiledProgram, closing: list[ModuleRuntime]
) -> None:
    mods = snake(caterpillar, 3)
    closing.extend(mods)
    step_all(mods, 2)
    assert [m.engine.topo_type.alias for m in mods] == [1, 16, 2]
    assert all(m.verified(c) for m, c in ((mods[0], BACK), (mods[1], FRONT), (mods[1], BACK), (mods[2], FRONT)))
    assert mods[1].engine.status == [BACK, FRONT, 0, 0]
    assert all(m.counters["refused"] == 0 for m in mods)


def test_wave_follows_table_one_and_drives_the_servos(
    caterpillar: CompiledProgram, closing: list[ModuleRuntime]
) -> None:
    # the head emits X(A) at its timer 0 (cycle 9); the others' timers never hit a head
    # receptor's value in the first cycles, before the Hellos made them bodies
    mods = snake(caterpillar, 4, phases=[31, 1, 1, 1])
    closing.extend(mods)
    # stepped tail first, a hormone crosses one link per cycle, as in the in-process Robot
    step_all(mods[::-1], 30)
    for k in range(1, 4):
        got = [(r["cycle"], r["received"][0]["hormone"]) for r in mods[k].records if r["received"]]
        assert got, f"module {k} received nothing"
        cycle, hormone = got[0]
        assert cycle == 9 + k  # the head emits in its cycle 9, module k gets it k cycles later
        phase = hormone[2]
        expected = "ABCD"[(k - 1) % 4]
        assert phase == expected
        assert mods[k].records[cycle]["actuators"]["DOF1"] == TABLE_I[phase]
        driver = mods[k].driver
        assert isinstance(driver, RecordingDriver) and (TABLE_I[phase], 0.0) in driver.history
    # nothing lost on a clean link: every hormone sent through back arrived at the next front
    for k in range(3):
        sent = [s["hormone"] for r in mods[k].records for s in r["sent"]]
        got = [a["hormone"] for r in mods[k + 1].records for a in r["received"]]
        assert got == sent[: len(got)] and len(sent) - len(got) <= 1
    assert all(m.counters["beacons_missed"] == 0 and m.counters["frames_dropped"] == 0 for m in mods)


def test_liveness_bound_is_exact(caterpillar: CompiledProgram, closing: list[ModuleRuntime]) -> None:
    a, b = snake(caterpillar, 2)
    closing.extend((a, b))
    step_all([a, b], 5)
    assert a.engine.status[BACK - 1] == FRONT
    # b falls silent after its cycle 4; a (stepped before b) hears that in its cycle 5
    a.step()
    for silent in range(1, SILENCE_CYCLES):
        a.step()
        assert a.engine.status[BACK - 1] == FRONT, f"fell after only {silent} silent cycles"
    a.step()
    assert a.engine.status[BACK - 1] == 0
    # and the engine already ran that cycle alone: its trace record shows it
    assert a.records[-1]["status"]["back"] == "0"
    assert a.counters["links_lost"] == 1
    # b comes back: the link is up again as soon as b is heard (after a Hello)
    b.step()
    a.step()
    b.step()
    a.step()
    assert a.engine.status[BACK - 1] == FRONT


def test_restarted_peer_is_answered_and_verified(caterpillar: CompiledProgram, closing: list[ModuleRuntime]) -> None:
    bus = InprocBus()
    a = make(caterpillar, bus)
    b = make(caterpillar, bus)
    closing.extend((a, b))
    a.attach(BACK, BusEnd(1, 0))
    b.attach(FRONT, BusEnd(1, 1))
    step_all([a, b], 4)
    b.close()  # b reboots before a notices the silence
    b2 = make(caterpillar, bus, phase=7)
    closing.append(b2)
    b2.attach(FRONT, BusEnd(1, 1))
    step_all([a, b2], 3)
    assert b2.verified(FRONT) and b2.engine.status[FRONT - 1] == BACK
    assert a.engine.status[BACK - 1] == FRONT


def test_neighbour_with_another_program_is_refused(
    caterpillar: CompiledProgram, closing: list[ModuleRuntime], tmp_path: Path
) -> None:
    text = (ROOT / "examples" / "caterpillar.dh2").read_text().replace("ClockCycle = 40", "ClockCycle = 20")
    other_file = tmp_path / "fast.dh2"
    other_file.write_text(text)
    other = compile_file(str(other_file))
    assert other.image != caterpillar.image
    bus = InprocBus()
    a = make(caterpillar, bus, phase=0)
    b = make(other, bus, phase=0)
    closing.extend((a, b))
    b.attach(FRONT, BusEnd(3, 1))
    a.attach(BACK, BusEnd(3, 0))
    b.inject(Hormone("X", ("A",)))
    step_all([a, b], 12)
    # a hormone from the refused neighbour (its X has another meaning there) is not fed to a
    assert b.transport.send(FRONT, Hormone("X", ("A",)))
    a.step()
    assert a.engine.status == [0, 0, 0, 0] and b.engine.status == [0, 0, 0, 0]
    assert a.counters["refused"] > 0 and b.counters["refused"] > 0
    assert a.counters["engine_received"] == 0 and b.counters["engine_received"] == 1  # only b's own injection
    assert a.counters["ignored"] == 1
    assert any("another program" in line for line in a.log)
    assert not a.verified(BACK)


def test_a_peer_on_a_connector_that_cannot_dock_there_is_ignored_not_a_crash(
    caterpillar: CompiledProgram, closing: list[ModuleRuntime]
) -> None:
    """Two fronts (both female) cannot dock: a peer that says so (a bad cable, a miswired
    harness) is told once in the log and ignored; the module keeps its type and runs on."""
    bus = InprocBus()
    a = make(caterpillar, bus)
    b = make(caterpillar, bus)
    closing.extend((a, b))
    a.attach(FRONT, BusEnd(5, 0))
    b.attach(FRONT, BusEnd(5, 1))
    step_all([a, b], 6)
    assert a.engine.status == [0, 0, 0, 0] and b.engine.status == [0, 0, 0, 0]
    assert sum("cannot dock here" in line for line in a.log) == 1
    assert a.cycle == 6 and b.cycle == 6


def test_a_programming_cable_is_neither_linked_nor_refused(
    caterpillar: CompiledProgram, closing: list[ModuleRuntime]
) -> None:
    bus = InprocBus()
    a = make(caterpillar, bus)
    closing.append(a)
    cable = InprocTransport(FrameCodec(caterpillar.vocabulary, 4), bus=bus)
    a.attach(FRONT, BusEnd(6, 0))
    cable.attach(FRONT, BusEnd(6, 1))  # front to front: a cable claims no connector that docks
    for _ in range(5):
        assert cable.send(FRONT, Hello(NO_PROGRAM))
        a.step()
    cable.close()
    assert a.engine.status == [0, 0, 0, 0] and a.counters["refused"] == 0
    assert a.liveness.settled and sum("a programming cable" in line for line in a.log) == 1


def test_run_paces_cycles_on_the_injected_clock(caterpillar: CompiledProgram, closing: list[ModuleRuntime]) -> None:
    bus = InprocBus()
    clock = FakeClock(step=0.0)
    codec = FrameCodec(caterpillar.vocabulary, 4)
    rt = ModuleRuntime(caterpillar, InprocTransport(codec, bus=bus), cycle_period=0.01, clock=clock)
    closing.append(rt)
    slept: list[float] = []

    def sleep(seconds: float) -> None:
        slept.append(seconds)
        clock.now += seconds

    assert rt.run(cycles=5, sleep=sleep) == 5
    assert rt.cycle == 5 and rt.counters["late_cycles"] == 0
    assert slept == pytest.approx([0.01] * 5)

    def slow_sleep(seconds: float) -> None:
        clock.now += seconds + 0.02  # every wait overshoots by two periods

    rt.run(cycles=3, sleep=slow_sleep)
    assert rt.counters["late_cycles"] == 2  # the first of the three started on time


def test_work_between_cycle_starts_tells_a_module_held_by_itself_from_one_held_by_the_machine(
    caterpillar: CompiledProgram, closing: list[ModuleRuntime]
) -> None:
    """Two late cycles at a 10 ms period: one 30 ms late after a wait in which the machine ran
    something else (the module's CPU clock stood still), one 21 ms late after 21 ms of the
    module's own work (its CPU clock ran with the wall clock). lateness_ms sees both alike;
    work_ms only the second."""
    clock = FakeClock(step=0.0)
    cpu = FakeClock(step=0.0)
    codec = FrameCodec(caterpillar.vocabulary, 4)
    rt = ModuleRuntime(
        caterpillar, InprocTransport(codec, bus=InprocBus()), cycle_period=0.01, clock=clock, cpu_clock=cpu
    )
    closing.append(rt)
    # each wait: (the machine holds the module, the module works on), in s
    waits = itertools.chain([(0.0, 0.0), (0.03, 0.0), (0.0, 0.0), (0.0, 0.021)], itertools.repeat((0.0, 0.0)))

    def sleep(seconds: float) -> None:
        held, worked = next(waits)
        clock.now += seconds + held + worked
        cpu.now += worked + 0.001  # and a millisecond of each cycle's own step

    assert rt.run(cycles=6, sleep=sleep) == 6
    work, late = rt.work_ms(), rt.lateness_ms()
    assert work is not None and late is not None
    assert work["p50"] == pytest.approx(1.0) and work["max"] == pytest.approx(22.0)
    assert late["max"] == pytest.approx(30.0)
    assert rt.status()["work_ms"] == work


@pytest.mark.parametrize("overshoot", [0.006, 0.007, 0.013, 0.025])
def test_every_period_the_schedule_lost_is_counted(
    caterpillar: CompiledProgram, closing: list[ModuleRuntime], overshoot: float
) -> None:
    """A late start restarts the schedule from now, so its whole lateness is lost, fractions
    too: the cycles that ran and the periods counted skipped fill the time the run took."""
    clock = FakeClock(step=0.0)
    codec = FrameCodec(caterpillar.vocabulary, 4)
    rt = ModuleRuntime(caterpillar, InprocTransport(codec, bus=InprocBus()), cycle_period=0.01, clock=clock)
    closing.append(rt)

    def slow_sleep(seconds: float) -> None:
        clock.now += seconds + overshoot  # every wait overshoots: 0.6 to 2.5 periods

    ran = rt.run(until=1.0, sleep=slow_sleep)
    periods = int(1.0 / 0.01)
    assert rt.counters["late_cycles"] == ran - 1  # all but the first, which was due at once
    assert periods - 2 <= ran + rt.counters["cycles_skipped"] <= periods + 2, (ran, rt.counters["cycles_skipped"])


def test_detach_drops_the_link_at_once(caterpillar: CompiledProgram, closing: list[ModuleRuntime]) -> None:
    a, b = snake(caterpillar, 2)
    closing.extend((a, b))
    step_all([a, b], 2)
    a.detach(BACK)
    assert a.engine.status[BACK - 1] == 0
    assert not a.transport.send(BACK, Hormone("X", ("A",)))


def test_frames_waiting_at_a_detached_connector_are_lost_in_flight(caterpillar: CompiledProgram) -> None:
    """What came in through a connector between two cycles and was not yet taken in dies
    with the link when it is detached: it must not set ConnectorStatus back to the dead link."""
    a, b = snake(caterpillar, 2)
    try:
        step_all([a, b], 3)  # Hellos exchanged: both verified
        assert b.engine.status[FRONT - 1] == BACK
        a.step()  # a beacons through its back
        b.take_in()  # b waits between cycles: frames kept for its next one
        b.detach(FRONT)
        b.step()
        assert b.engine.status[FRONT - 1] == 0
        assert b.counters["lost_in_flight"] >= 1
    finally:
        a.close()
        b.close()


def _pair_on_the_real_clock(program: CompiledProgram) -> tuple[ModuleRuntime, InprocTransport]:
    """A runtime on the monotonic clock, its back linked to a bare transport (the neighbour)."""
    bus = InprocBus()
    codec = FrameCodec(program.vocabulary, program.profile.connector_count)
    rt = ModuleRuntime(program, InprocTransport(codec, bus=bus), clock=time.monotonic)
    peer = InprocTransport(FrameCodec(program.vocabulary, program.profile.connector_count), bus=bus)
    rt.attach(BACK, BusEnd(0, 0))
    peer.attach(FRONT, BusEnd(0, 1))
    return rt, peer


@pytest.mark.parametrize("gap_s", [0.01, 0.03, 0.045])
def test_the_drain_waits_for_frames_a_late_medium_delivers(caterpillar: CompiledProgram, gap_s: float) -> None:
    """After its last cycle a module reads on until the link has been quiet for ``quiet``
    seconds: frames that come late, each within ``quiet`` of the last, are all counted
    received, even long after a fixed window would have closed (slcan adapters under load
    delivered the last 24 of 780 frames after the old three periods)."""
    rt, peer = _pair_on_the_real_clock(caterpillar)
    try:
        sent = 12

        def late_neighbour() -> None:
            for _ in range(sent):
                time.sleep(gap_s)
                peer.send(FRONT, KeepAlive())

        sender = threading.Thread(target=late_neighbour)
        started = time.monotonic()
        sender.start()
        got = rt.drain(quiet=0.06 + gap_s, most=5.0)
        sender.join()
        assert got == sent, f"{got} of {sent} late frames taken in"
        assert rt.counters["frames_received"] == sent
        assert time.monotonic() - started < sent * gap_s + 1.0
    finally:
        rt.close()
        peer.close()


def test_the_drain_ends_at_its_bound_on_a_link_that_never_goes_quiet(caterpillar: CompiledProgram) -> None:
    rt, peer = _pair_on_the_real_clock(caterpillar)
    stop = threading.Event()

    def chatter() -> None:
        while not stop.is_set():
            peer.send(FRONT, KeepAlive())
            time.sleep(0.005)

    sender = threading.Thread(target=chatter)
    sender.start()
    try:
        started = time.monotonic()
        got = rt.drain(quiet=0.05, most=0.3)
        took = time.monotonic() - started
        assert got > 10
        assert 0.3 <= took < 0.3 + 0.5, took
    finally:
        stop.set()
        sender.join()
        rt.close()
        peer.close()


def test_the_drain_of_a_quiet_link_takes_its_quiet_window(caterpillar: CompiledProgram) -> None:
    rt, peer = _pair_on_the_real_clock(caterpillar)
    try:
        started = time.monotonic()
        assert rt.drain(quiet=0.05, most=5.0) == 0
        assert 0.05 <= time.monotonic() - started < 0.05 + 0.5
    finally:
        rt.close()
        peer.close()
