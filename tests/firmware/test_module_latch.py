"""The module's own latch in a reach (firmware.main_loop._ModuleLatch): a dock is aligned only
on latch closed and the connector's link verified; a latch fault or a link that does not come
within LATCH_LINK_CYCLES refuses it and opens the latch again."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from drivers.latch import Position, Sensed
from drivers.recording import RecordingLatch
from firmware.control import Effect, LatchAnswer
from firmware.main_loop import LATCH_LINK_CYCLES, _ModuleLatch


class JammedLatch(RecordingLatch):
    """Told to close, the horn stays open (the faces are not within the dock tolerance)."""

    def _sense(self, target: Position | None) -> Sensed:
        return Sensed(Position.OPEN, "jammed open")


def _host(verified: set[int], reported: list[Any] | None = None) -> Any:
    runtime = SimpleNamespace(verified=lambda c: c in verified, log=[])
    return SimpleNamespace(runtime=runtime, report=(reported if reported is not None else []).append)


def test_dock_completes_only_on_closed_and_link() -> None:
    linked: set[int] = set()
    driver = RecordingLatch()
    latch = _ModuleLatch(_host(linked), driver, 2)
    assert not latch.aligned(1, 2, 3, 4)  # told to close
    assert driver.history == [Position.CLOSED]
    assert not latch.aligned(1, 2, 3, 4)  # closed, no link yet
    linked.add(2)
    assert latch.aligned(1, 2, 3, 4)
    assert latch.latch(1, 2, 3, 4)
    latch.release(1)  # another connector's release: the latch stays closed
    assert driver.history == [Position.CLOSED]
    latch.release(2)
    assert driver.history == [Position.CLOSED, Position.OPEN]


def test_no_link_in_the_bound_is_refused_and_opened() -> None:
    driver = RecordingLatch()
    host = _host(set())
    latch = _ModuleLatch(host, driver, 2)
    answers = [latch.aligned(1, 2, 3, 4) for _ in range(LATCH_LINK_CYCLES + 2)]
    assert not any(answers)  # refused: not aligned yet, the motion goes on
    assert driver.history == [Position.CLOSED, Position.OPEN]
    assert "refused" in host.runtime.log[-1] and "link not verified" in host.runtime.log[-1]
    assert not latch.aligned(1, 2, 3, 4)  # the motion asks again: the latch closes again
    assert driver.history == [Position.CLOSED, Position.OPEN, Position.CLOSED]


class SlowLatch(RecordingLatch):
    """A horn that takes ``cycles`` state reads to get where it was told (moving meanwhile)."""

    def __init__(self, start: Position, cycles: int) -> None:
        super().__init__()
        self.adopt(start)
        self.cycles = cycles
        self.reads = cycles  # at rest where it started

    def _drive(self, target: Position) -> None:
        super()._drive(target)
        self.reads = 0

    def _sense(self, target: Position | None) -> Sensed:
        self.reads += 1
        if target is not None and self.reads <= self.cycles:
            return Sensed(Position.BETWEEN, "moving")
        return Sensed(target or Position.CLOSED, f"at {target}")


def test_a_latch_closed_on_no_link_opens_before_it_closes() -> None:
    """A latch still closed from a link the male face's module released (it cannot open this
    latch) moves nothing when told to close: the pins in front would never be taken (the
    loop's snake to quadruped: m2's horn stayed past the pins through 7 asks, and the world
    never saw it close). It opens first, and closes once it reads open."""
    linked: set[int] = set()
    driver = SlowLatch(Position.CLOSED, cycles=2)
    latch = _ModuleLatch(_host(linked), driver, 1)
    asks = [latch.aligned(1, 1, 3, 4) for _ in range(4)]
    assert not any(asks)
    assert driver.history == [Position.OPEN, Position.CLOSED]  # opened, read open, then closed
    linked.add(1)
    while not latch.aligned(1, 1, 3, 4):
        assert len(asks) < 12
        asks.append(False)
    assert latch.latch(1, 1, 3, 4)


def test_a_jammed_latch_is_refused_and_opened() -> None:
    clock = [0.0]
    driver = JammedLatch(timeout_s=0.1)
    driver._clock = lambda: clock[0]  # the latch's own timeout judges the jam
    host = _host({2})
    latch = _ModuleLatch(host, driver, 2)
    cycles = 0
    while driver.history[-1:] != [Position.OPEN] and cycles < LATCH_LINK_CYCLES:
        assert not latch.aligned(1, 2, 3, 4)
        clock[0] += 0.05
        cycles += 1
    assert driver.history == [Position.CLOSED, Position.OPEN] and cycles < LATCH_LINK_CYCLES  # the jam, not the link
    assert "refused (latch fault" in host.runtime.log[-1]
    assert not latch.latch(1, 2, 3, 4)


def test_a_dock_on_another_connector_is_asked_of_the_world() -> None:
    """A male face's dock is held by the other module's latch: the world answers it."""
    reported: list[Any] = []
    driver = RecordingLatch()
    latch = _ModuleLatch(_host({1, 2}, reported), driver, 2)
    assert not latch.aligned(1, 1, 3, 4)
    assert reported == [Effect("latch", [1, 3, 4])] and driver.history == []
    latch.answered(LatchAnswer(1, True))
    assert latch.aligned(1, 1, 3, 4) and latch.latch(1, 1, 3, 4)
    assert driver.history == []
