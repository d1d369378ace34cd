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
