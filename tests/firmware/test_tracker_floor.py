"""A module that hears the overhead tracker itself (module.toml ``[tracker]``,
firmware/tracker_floor.py): its floor is every module whose three parts are fresh in its own
feed (a module with a part too old or never seen left out, so a motion that needs it raises
TrackerMissing), the world's ``Floor`` parts are not used but its IMU is; every ``[tracker]``
value checked (the key named, exit 2); the feed polled each cycle over a real UDP socket on
loopback and closed at the end; the loop's publisher (hil.tracker_udp) encodes what the
module decodes."""

from __future__ import annotations

import math
import queue
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dh2rt.bundled import compile_bundled
from dh2rt.errors import ModuleConfigError
from dh2rt.wire.tracker import MarkerPose, TrackerDatagram, encode
from firmware import main_loop
from firmware.config import ModuleConfig, TrackerSpec
from firmware.control import Command, Floor, Go, Report, Status
from firmware.main_loop import ModuleHost, _OwnSenses
from firmware.module_toml import dump_toml, load_toml
from firmware.motion.readings import FloorPoses, ModulePose, PartPose, TrackerMissing
from firmware.tracker_feed import TrackerFeed
from firmware.tracker_floor import floor_from_feed, markers, open_feed
from hil.tracker_udp import TrackerPublisher, free_ports
from hil.tracker_udp import markers as publish_markers
from tests.firmware.test_latch_config import module_toml


class FakeClock:
    def __init__(self) -> None:
        self.now = 50.0

    def __call__(self) -> float:
        return self.now


def frame(sequence: int, *parts: tuple[int, float, float, float]) -> bytes:
    poses = tuple(MarkerPose(marker, x, y, h, 0.3) for marker, x, y, h in parts)
    return encode(TrackerDatagram(sequence, 1000 * sequence, poses))


def module_parts(m: int, x_mm: float) -> list[tuple[int, float, float, float]]:
    """Module ``m``'s centre, front and back markers along +x, heading 270 degrees."""
    return [(3 * m + k, x_mm + 10.0 * k, -5.0, 270.0) for k in range(3)]


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def feed(clock: FakeClock) -> Iterator[TrackerFeed]:
    with TrackerFeed(markers(3), "m1.centre", bind=("127.0.0.1", 0), max_age_s=0.2, clock=clock) as made:
        yield made


def test_the_floor_is_every_module_whose_three_parts_are_fresh(feed: TrackerFeed, clock: FakeClock) -> None:
    assert floor_from_feed(feed, 3, 0.05).modules == {}  # nothing heard yet
    # module 0 whole, module 1 whole, module 2 without its back part
    feed.take(frame(1, *module_parts(0, 100.0), *module_parts(1, 300.0), *module_parts(2, 500.0)[:2]), clock())
    clock.now += 0.06
    floor = floor_from_feed(feed, 3, 0.05)
    assert sorted(floor.modules) == [0, 1]
    centre = floor.pose(0).centre
    assert centre.x == pytest.approx(0.1) and centre.y == pytest.approx(-0.005)
    assert centre.heading == pytest.approx(-math.pi / 2)  # 270 degrees, within +-pi
    assert floor.pose(1).front.x == pytest.approx(0.31) and floor.pose(1).back.x == pytest.approx(0.32)
    assert floor.pose(0).age == 1  # 60 ms old: one whole cycle of 50 ms
    with pytest.raises(TrackerMissing, match="module 2"):
        floor.pose(2)


def test_a_module_with_one_stale_part_is_left_out(feed: TrackerFeed, clock: FakeClock) -> None:
    feed.take(frame(1, *module_parts(0, 100.0), *module_parts(1, 300.0)), clock())
    clock.now += 0.15
    # module 1's front and back come again; its centre (marker 3) and module 0 do not
    feed.take(frame(2, *module_parts(1, 301.0)[1:]), clock())
    clock.now += 0.1  # the first frame is 0.25 s old now: past max_age_s 0.2
    assert floor_from_feed(feed, 3, 0.05).modules == {}
    feed.take(frame(3, (3, 302.0, -5.0, 0.0)), clock())
    assert sorted(floor_from_feed(feed, 3, 0.05).modules) == [1]


def test_the_publisher_sends_what_the_module_decodes() -> None:
    def part(m: int, k: int) -> PartPose:
        return PartPose(0.1 * m + 0.01 * k, 0.2, -0.5 + k)

    floor = FloorPoses({m: ModulePose(part(m, 0), part(m, 1), part(m, 2)) for m in (0, 2)})
    assert [p.marker for p in publish_markers(floor)] == [0, 1, 2, 6, 7, 8]
    spec = TrackerSpec(free_ports(1)[0], "127.0.0.1", 1.0, 3)
    with open_feed(spec, 2) as heard, TrackerPublisher([spec.port]) as publisher:
        publisher.publish(floor)
        deadline = time.monotonic() + 2.0
        while heard.datagrams == 0 and time.monotonic() < deadline:
            heard.poll()
            time.sleep(0.005)
        got = floor_from_feed(heard, 3, 0.05)
    assert publisher.sent == 1 and heard.datagrams == 1 and sorted(got.modules) == [0, 2]
    for m in (0, 2):
        for k, (sent, came) in enumerate(zip(_parts(floor, m), _parts(got, m), strict=True)):
            assert came.x == pytest.approx(sent.x, abs=1e-4) and came.y == pytest.approx(sent.y, abs=1e-4), k
            assert came.heading == pytest.approx(sent.heading, abs=1e-3), k


def _parts(floor: FloorPoses, m: int) -> tuple[PartPose, PartPose, PartPose]:
    pose = floor.pose(m)
    return pose.centre, pose.front, pose.back


# ------------------------------------------------------------ the module host


def config(port: int, **tracker: Any) -> ModuleConfig:
    image = compile_bundled("caterpillar.dh2").image
    spec = {"port": port, "modules": 2, "max_age_s": 0.5, **tracker}
    return ModuleConfig.from_json(
        {"module": 1, "image": image.hex(), "transport": "inproc:tracker-floor", "cycles": 40,
         "cycle_period": 0.005, "tracker": spec}
    )  # fmt: skip


def test_the_host_polls_its_feed_each_cycle_and_ignores_the_worlds_parts() -> None:
    port = free_ports(1)[0]
    commands: queue.Queue[Command] = queue.Queue()
    reports: list[Report] = []
    host = ModuleHost(config(port), commands, reports.append)
    assert host.tracker is not None and host.tracker.address == ("127.0.0.1", port)
    # the world's Floor: parts of a module 0 far away (not used), this module's IMU (used)
    world_parts = {0: ((9.0, 9.0, 0.0), (9.0, 9.0, 0.0), (9.0, 9.0, 0.0))}
    commands.put(Floor(world_parts, {1: (3.0, -4.0)}))
    senses = _OwnSenses(host)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        sender.sendto(frame(1, *module_parts(0, 100.0), *module_parts(1, 200.0)), ("127.0.0.1", port))
        deadline = time.monotonic() + 2.0
        while host.tracker.datagrams == 0 and time.monotonic() < deadline:
            host._take_commands(host.runtime)
            time.sleep(0.005)
    floor = senses.floor()
    assert sorted(floor.modules) == [0, 1] and floor.pose(0).centre.x == pytest.approx(0.1)
    assert any("tracker: the floor from the feed: modules [0, 1] fresh (1 datagrams" in x for x in host.runtime.log)
    assert senses.attitude() == {1: (3.0, -4.0)}
    assert host._status(host.runtime)["tracker"] == {"datagrams": 1, "rejected": 0, "stale": 0}
    assert any("tracker: the floor from UDP 127.0.0.1:" in line for line in host.runtime.log)
    commands.put(Go())
    assert host.serve() == 0  # the feed is closed when the module ends
    assert host.tracker._sock.fileno() == -1
    final = [r for r in reports if isinstance(r, Status) and r.final]
    assert final and final[0].status["tracker"]["datagrams"] == 1


def test_with_alpha_the_feeds_poses_are_smoothed() -> None:
    """``alpha``: the floor filter the physics runs' filtered variant uses, on the feed's
    poses: a jump of a still part's report moves the estimate by about alpha of it."""
    port = free_ports(1)[0]
    host = ModuleHost(config(port, alpha=0.3), queue.Queue(), lambda _r: None)
    try:
        assert host.tracker is not None and host.floor_filter is not None and host.floor_filter.alpha == 0.3
        senses = _OwnSenses(host)
        host.tracker.take(frame(1, *module_parts(0, 100.0), *module_parts(1, 200.0)), time.monotonic())
        assert senses.floor().pose(0).centre.x == pytest.approx(0.1)  # the first report starts the track
        host.runtime.step()
        host.tracker.take(frame(2, *module_parts(0, 110.0), *module_parts(1, 200.0)), time.monotonic())
        smoothed = senses.floor().pose(0).centre.x
        assert smoothed == pytest.approx(0.1 + 0.3 * 0.01, abs=1e-6)  # raw: 0.11
        assert any("smoothed, alpha 0.3" in line for line in host.runtime.log)
    finally:
        if host.tracker is not None:
            host.tracker.close()
        host.runtime.close()


def test_without_a_tracker_the_worlds_parts_are_the_floor() -> None:
    image = compile_bundled("caterpillar.dh2").image
    cfg = ModuleConfig.from_json({"module": 0, "image": image.hex(), "transport": "inproc:no-tracker"})
    commands: queue.Queue[Command] = queue.Queue()
    host = ModuleHost(cfg, commands, lambda _r: None)
    try:
        assert host.tracker is None
        host._command(Floor({0: ((0.1, 0.2, 0.3), (0.1, 0.2, 0.3), (0.1, 0.2, 0.3))}, {}))
        assert _OwnSenses(host).floor().pose(0).centre.x == 0.1
    finally:
        host.runtime.close()


def test_a_port_taken_is_a_config_error_naming_tracker_port() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        with pytest.raises(ModuleConfigError, match=rf"\[tracker\] port: cannot listen on 127.0.0.1:{port}"):
            ModuleHost(config(port), queue.Queue(), lambda _r: None)


# ------------------------------------------------------------ module.toml


BAD = [
    ("[tracker]\nport = 0\nmodules = 2\n", "[tracker] port: expected an integer 1..65535, got 0"),
    ("[tracker]\nport = 70000\nmodules = 2\n", "[tracker] port: expected an integer 1..65535, got 70000"),
    ('[tracker]\nport = "x"\nmodules = 2\n', "[tracker] port: expected an integer 1..65535, got 'x'"),
    ("[tracker]\nmax_age_s = 0\nmodules = 2\n", "[tracker] max_age_s: expected seconds in (0, 60], got 0"),
    ("[tracker]\nmax_age_s = -1\nmodules = 2\n", "[tracker] max_age_s: expected seconds in (0, 60], got -1"),
    ("[tracker]\nmax_age_s = nan\nmodules = 2\n", "[tracker] max_age_s: expected seconds in (0, 60], got nan"),
    (
        "[tracker]\nmodules = 2\nfilter = 1\n",
        "[tracker] filter: unknown key (known: port, bind, max_age_s, modules, alpha)",
    ),
    ("[tracker]\nmodules = 2\nalpha = 0\n", "[tracker] alpha: expected a gain in (0, 1]"),
    ("[tracker]\nmodules = 2\nalpha = 1.5\n", "[tracker] alpha: expected a gain in (0, 1]"),
    ('[tracker]\nmodules = 2\nalpha = "0.3"\n', "[tracker] alpha: expected a gain in (0, 1]"),
    ("[tracker]\nport = 47328\n", "[tracker] modules: missing: how many modules the robot has"),
    ("[tracker]\n", "[tracker] modules: missing"),
    ("[tracker]\nmodules = 34\n", "[tracker] modules: expected an integer 1..33, got 34"),
    ("[tracker]\nmodules = 2\nbind = 1\n", "[tracker] bind: expected an address to listen on"),
    ("[hil]\nmodule = 2\n[tracker]\nmodules = 2\n", "[tracker] modules: 2, but this module's index is 2"),
]


@pytest.mark.parametrize(("body", "message"), BAD)
def test_a_bad_tracker_is_named_and_exit_2(
    tmp_path: Path, body: str, message: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    path = module_toml(tmp_path, body)
    with pytest.raises(ModuleConfigError) as caught:
        load_toml(path)
    assert message in str(caught.value)
    monkeypatch.setattr(main_loop, "lean_process", lambda: None)
    assert main_loop.main(["--config", str(path), "--check-config"]) == 2
    out, err = capsys.readouterr()
    assert message in err and "Traceback" not in out + err


def test_check_config_says_what_the_tracker_is_and_the_toml_round_trips(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    path = module_toml(tmp_path, '[tracker]\nport = 47400\nbind = ""\nmax_age_s = 0.3\nmodules = 5\n')
    loaded = load_toml(path)
    assert loaded.tracker == TrackerSpec(47400, "", 0.3, 5)
    monkeypatch.setattr(main_loop, "lean_process", lambda: None)
    assert main_loop.main(["--config", str(path), "--check-config"]) == 0
    out = capsys.readouterr().out
    assert "tracker: UDP *:47400, markers 0..14 of 5 modules, poses within 0.3 s, raw" in out
    again = tmp_path / "again.toml"
    again.write_text(dump_toml(loaded, tmp_path / "flash2"))
    assert load_toml(again).tracker == loaded.tracker
    assert ModuleConfig.from_json(loaded.to_json()).tracker == loaded.tracker
    assert load_toml(module_toml(tmp_path, "")).tracker is None
    smoothed = load_toml(module_toml(tmp_path, "[tracker]\nmodules = 2\nalpha = 0.3\n"))
    assert smoothed.tracker == TrackerSpec(47328, "127.0.0.1", 0.25, 2, 0.3)
    again.write_text(dump_toml(smoothed, tmp_path / "flash3"))
    assert load_toml(again).tracker == smoothed.tracker
    assert ModuleConfig.from_json(smoothed.to_json()).tracker == smoothed.tracker
