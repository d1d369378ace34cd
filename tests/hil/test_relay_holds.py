"""The loop's relay thread measures how long the machine held it: a hold delays every byte the
test bench carries, which neither module's own lateness shows, so the loop's timing tests
allow for the holds that fell within what they time (tests/hil/test_flash_loop.py)."""

from __future__ import annotations

import os
import threading
import time

import pytest

from hil.link_emulator import held_within
from hil.ptys import HELD_KEEP_S, RELAY_NICE, PtyRelay


@pytest.mark.parametrize("hold_s", [0.03, 0.08])
def test_a_relay_held_up_says_when_and_for_how_long(hold_s: float) -> None:
    lock = threading.Lock()
    relay = PtyRelay("test-relay", lock, lambda fd, data: None, watch_held=True)
    try:
        time.sleep(0.05)
        before = time.monotonic()
        with lock:  # the thread cannot begin its next round: held, as a busy machine holds it
            time.sleep(hold_s)
        time.sleep(0.05)
        after = time.monotonic()
    finally:
        relay.stop()
    assert relay.held_s >= hold_s - 0.006  # the round that was waiting when the hold began
    long = [(ended, held) for ended, held in relay.holds if held >= hold_s - 0.006]
    assert long and all(before <= ended <= after for ended, _ in long), (long, before, after)
    assert held_within(relay.holds, before, after) >= hold_s - 0.006


def test_only_holds_worth_noting_are_kept() -> None:
    relay = PtyRelay("test-relay", threading.Lock(), lambda fd, data: None, watch_held=True)
    try:
        time.sleep(0.1)
    finally:
        relay.stop()
    assert all(held >= HELD_KEEP_S for _, held in relay.holds)


def test_an_unwatched_relay_measures_nothing() -> None:
    """The contact and slcan emulators' relays wait as long as nothing is due (no 5 ms rounds)."""
    lock = threading.Lock()
    relay = PtyRelay("test-relay", lock, lambda fd, data: None)
    try:
        with lock:
            time.sleep(0.03)
    finally:
        relay.stop()
    assert relay.held_s == 0.0 and not relay.holds


def test_held_within_adds_the_overlap_of_each_hold() -> None:
    holds = [(1.0, 0.2), (2.0, 0.5), (3.0, 0.1)]  # (ended, seconds): 0.8-1.0, 1.5-2.0, 2.9-3.0
    assert held_within(holds, 0.0, 4.0) == pytest.approx(0.8)
    assert held_within(holds, 0.9, 1.6) == pytest.approx(0.1 + 0.1)
    assert held_within(holds, 2.0, 2.9) == 0.0
    assert held_within([], 0.0, 1.0) == 0.0


def test_the_relay_thread_runs_above_the_modules() -> None:
    """A wire is never held up by a busy processor: the relay's thread gets RELAY_NICE, where
    the machine lets this process lower it (root here), and the rest of the process keeps its own."""
    base = os.getpriority(os.PRIO_PROCESS, 0)
    relay = PtyRelay("test-relay", threading.Lock(), lambda fd, data: None)
    try:
        deadline = time.monotonic() + 2.0
        assert relay.native_id is not None
        expected = RELAY_NICE if os.geteuid() == 0 else base
        while os.getpriority(os.PRIO_PROCESS, relay.native_id) != expected and time.monotonic() < deadline:
            time.sleep(0.01)
        assert os.getpriority(os.PRIO_PROCESS, relay.native_id) == expected
        assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == base
    finally:
        relay.stop()


def test_the_servo_emulators_thread_runs_as_hardware() -> None:
    """The servo emulator's thread, like the relays', plays hardware: RELAY_NICE where allowed."""
    from hil.servo_emulator import ServoEmulator

    base = os.getpriority(os.PRIO_PROCESS, 0)
    seen: list[int] = []
    before = {t.native_id for t in threading.enumerate()}
    emulator = ServoEmulator((1, 2)).start()
    try:
        deadline = time.monotonic() + 2.0
        expected = RELAY_NICE if os.geteuid() == 0 else base
        while time.monotonic() < deadline:
            new = [t.native_id for t in threading.enumerate() if t.native_id not in before and t.name == "dxl-emulator"]
            seen = [os.getpriority(os.PRIO_PROCESS, tid) for tid in new if tid is not None]
            if seen == [expected]:
                break
            time.sleep(0.01)
        assert seen == [expected]
    finally:
        emulator.stop()
