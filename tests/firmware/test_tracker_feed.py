"""What a module hears from the overhead tracker (firmware.tracker_feed): each marker's latest
pose with its age, a missing or old pose a NoTrackerReading naming the marker and its age
(never a silent zero), garbage and reordered datagrams left out; over a real UDP socket on
loopback, polled without blocking."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator

import pytest

from dh2rt.errors import NoTrackerReading
from dh2rt.wire.tracker import MarkerPose, TrackerDatagram, encode
from firmware.tracker_feed import MAX_PER_POLL, TrackerFeed

MODULES = {10: "head", 11: "body1", 12: "tail"}


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def feed(clock: FakeClock) -> Iterator[TrackerFeed]:
    with TrackerFeed(MODULES, "body1", bind=("127.0.0.1", 0), max_age_s=0.2, clock=clock) as made:
        yield made


def frame(sequence: int, captured_us: int, *poses: tuple[int, float, float, float]) -> bytes:
    return encode(TrackerDatagram(sequence, captured_us, tuple(MarkerPose(m, x, y, h, 0.5) for m, x, y, h in poses)))


def test_a_pose_never_reported_is_no_reading_naming_the_marker(feed: TrackerFeed) -> None:
    with pytest.raises(NoTrackerReading) as caught:
        feed.own_pose()
    assert caught.value.marker == 11 and caught.value.module == "body1" and caught.value.age_s is None
    assert str(caught.value) == "no tracker reading of marker 11 (body1): never seen"


def test_latest_pose_with_its_age_then_too_old(feed: TrackerFeed, clock: FakeClock) -> None:
    assert feed.take(frame(1, 1000, (11, 50.0, -20.0, 90.0), (12, 1.0, 2.0, 3.0)), clock()) == 1
    clock.now += 0.05
    mine = feed.own_pose()
    assert (mine.module, mine.x_mm, mine.y_mm, mine.heading_deg) == ("body1", 50.0, -20.0, 90.0)
    assert mine.age_s == pytest.approx(0.05) and mine.sequence == 1 and mine.captured_us == 1000
    assert feed.pose("tail").x_mm == 1.0
    feed.take(frame(2, 2000, (11, 51.0, -20.0, 91.0)), clock())  # the tail left the camera's view
    clock.now += 0.19
    assert feed.own_pose().x_mm == 51.0
    with pytest.raises(NoTrackerReading) as caught:
        feed.pose("tail")
    assert caught.value.age_s == pytest.approx(0.24)
    assert "marker 12 (tail): last seen 0.240 s ago (bound 0.2 s)" in str(caught.value)
    assert feed.pose("tail", max_age_s=1.0).x_mm == 1.0  # the caller may allow older
    assert set(feed.fresh()) == {"body1"}


def test_garbage_is_counted_not_raised(feed: TrackerFeed, clock: FakeClock) -> None:
    assert feed.take(b"not a tracker datagram", clock()) == 0
    assert feed.rejected == 1 and feed.last_error is not None and feed.last_error.field == "magic"
    with pytest.raises(NoTrackerReading):
        feed.own_pose()


def test_a_reordered_datagram_never_takes_a_pose_back_in_time(feed: TrackerFeed, clock: FakeClock) -> None:
    feed.take(frame(5, 5000, (11, 5.0, 0.0, 0.0)), clock())
    assert feed.take(frame(4, 4000, (11, 4.0, 0.0, 0.0)), clock()) == 0
    assert feed.stale == 1 and feed.own_pose().x_mm == 5.0


def test_markers_of_no_module_are_ignored(feed: TrackerFeed, clock: FakeClock) -> None:
    feed.take(frame(1, 1, (3, 9.0, 9.0, 9.0)), clock())
    assert feed.fresh() == {}
    with pytest.raises(KeyError, match="no marker is given for module 'leg'"):
        feed.pose("leg")


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="own module 'foot'"):
        TrackerFeed(MODULES, "foot", bind=("127.0.0.1", 0))
    with pytest.raises(ValueError, match="two markers name one module"):
        TrackerFeed({1: "a", 2: "a"}, "a", bind=("127.0.0.1", 0))
    with pytest.raises(ValueError, match="max_age_s"):
        TrackerFeed(MODULES, "head", bind=("127.0.0.1", 0), max_age_s=0)


def test_poll_reads_loopback_datagrams_without_blocking() -> None:
    with (
        TrackerFeed(MODULES, "head", bind=("127.0.0.1", 0)) as feed,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tracker,
    ):
        started = time.perf_counter()
        assert feed.poll() == 0
        assert time.perf_counter() - started < 0.05  # nothing there: back at once
        for k in range(3):
            tracker.sendto(frame(k, 1000 + k, (10, float(k), 0.0, 0.0)), feed.address)
        tracker.sendto(b"\x00" * 30, feed.address)
        taken = 0
        deadline = time.monotonic() + 2.0
        while taken < 3 and time.monotonic() < deadline:
            taken += feed.poll()
        assert taken == 3 and feed.own_pose().x_mm == 2.0
        while feed.rejected == 0 and time.monotonic() < deadline:
            feed.poll()
        assert feed.rejected == 1


def test_one_poll_takes_a_bounded_number(clock: FakeClock) -> None:
    with (
        TrackerFeed(MODULES, "head", bind=("127.0.0.1", 0), clock=clock) as feed,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tracker,
    ):
        for k in range(MAX_PER_POLL + 5):
            tracker.sendto(frame(k, k, (10, float(k), 0.0, 0.0)), feed.address)
        time.sleep(0.05)
        assert feed.poll() == MAX_PER_POLL
        assert feed.poll() == 5
