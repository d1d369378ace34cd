"""`dh2rt flash IMAGE --port DEV`: a robot on the bench flashed through a programming cable.

The robot is the loop's: 4 module processes on serial links run the caterpillar (signed as
version 1 with the world's key), and the cable is a pty of the link emulator plugged into the
head's free front connector (``World.plug_cable``). The command runs in a thread, as it would
in a shell, while this thread ticks the world. What is checked is what the command prints and
exits with, and what the modules say they run. Bad input needs no robot; neither does a
cable with nobody at the other end (a pty whose other side stays silent).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from contextlib import AbstractContextManager
from pathlib import Path

import pytest

from dh2rt.signed_image import new_private_key, pack, read_private_key, write_key_pair
from hil.world import World
from tests.hil.flashing import beside, caterpillar, running_snake, tick_until, versions
from tools.flash import main

ROOT = Path(__file__).resolve().parents[2]
N = 4
HEAD, FRONT = 0, 1  # the head's front connector is free: the cable goes there
WAIT = 60.0  # seconds a rollout, or a status report, may take on a loaded machine


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


def bench_robot() -> AbstractContextManager[World]:
    """A snake of N module processes on serial links, started and running; always stopped."""
    return running_snake("serial", N, wait=WAIT)


def bus_robot() -> AbstractContextManager[World]:
    """A snake of N modules on python-can's virtual bus (threads of this process, which the
    command, in a thread too, joins as a node), started and running; always stopped."""
    return running_snake("virtual", N, wait=WAIT)


def flash(world: World, image: Path, *options: str) -> int:
    """``dh2rt flash IMAGE --port <a cable into the head's front> OPTIONS``, the world
    ticking meanwhile; the cable is pulled out afterwards. The exit code."""
    link_id, port = world.plug_cable(HEAD, FRONT)
    argv = [str(image), "--port", port, "--timeout", str(WAIT), *options]
    try:
        return beside(world, lambda: main(argv), WAIT + 10)
    finally:
        world.unplug_cable(HEAD, FRONT, link_id)


def test_every_module_commits_the_new_version(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    new = caterpillar(20)
    with bench_robot() as world:
        assert world.signer is not None and versions(world) == [1] * N
        image = tmp_path / "cat2.simg"
        image.write_bytes(pack(new.image, 2, world.signer))
        code = flash(world, image, "--json")
        out, err = capsys.readouterr()
        assert code == 0, (out, err, world.log[-20:])
        # the modules say so too: every one runs version 2 (its status, every few cycles)
        tick_until(world, lambda: versions(world) == [2] * N, WAIT)
        assert versions(world) == [2] * N, (versions(world), world.log[-20:])
    report = json.loads(out)
    assert report["image"] == str(image) and report["version"] == 2 and report["sha256"] == new.hash
    assert report["succeeded"] is True and report["failure"] is None
    modules = report["modules"]
    paths = [m["path"] for m in modules]
    # one module per hop from the cable, each named by its path: front>front back>front ...
    assert len(set(paths)) == N and sorted(len(p.split()) for p in paths) == list(range(1, N + 1))
    assert paths[0] == "front>front" and paths[1] == "front>front back>front"
    assert all(m["outcome"] in ("committed", "confirmed") and m["version"] == 2 for m in modules), modules
    assert "flash: sending:" in err and "Traceback" not in err


def test_on_a_bus_the_cable_negotiates_its_link_and_every_module_commits(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``dh2rt flash IMAGE --interface virtual --channel C --contact DEV``: the cable's
    connector-local channel touches the head's free front, the two negotiate a link as
    docking modules do, and the image crosses the bus."""
    with bus_robot() as world:
        assert world.signer is not None and versions(world) == [1] * N
        image = tmp_path / "cat2.simg"
        image.write_bytes(pack(caterpillar(20).image, 2, world.signer))
        mate, contact = world.touch_cable(HEAD, FRONT)
        channel = world.transport_spec.partition(":")[2]
        argv = [str(image), "--interface", "virtual", "--channel", channel, "--contact", contact,
                "--timeout", str(WAIT), "--json", "--confirm"]  # fmt: skip
        try:
            code = beside(world, lambda: main(argv), WAIT + 10)
        finally:
            world.pull_cable(HEAD, FRONT, mate)
        out, err = capsys.readouterr()
        assert code == 0, (out, err, world.log[-20:])
        tick_until(world, lambda: versions(world) == [2] * N, WAIT)
        assert versions(world) == [2] * N
    report = json.loads(out)
    assert [m["outcome"] for m in report["modules"]] == ["confirmed"] * N, report
    assert report["modules"][0]["path"] == "back>front"  # the cable is a back against the head's front
    assert "link negotiated" in err and "bus virtual" in err


def test_an_image_signed_by_another_key_is_refused_by_the_head(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    image = tmp_path / "stranger.simg"
    image.write_bytes(pack(caterpillar(20).image, 2, new_private_key()))
    with bench_robot() as world:
        code = flash(world, image, "--json", "--quiet")
        out, err = capsys.readouterr()
        # the head's status counts the refusal; by then every module has said what it runs
        tick_until(world, lambda: world.views[HEAD].status.get("program", {}).get("refused"), 10.0)
        assert versions(world) == [1] * N, versions(world)
        head_refused = world.views[HEAD].status.get("program", {}).get("refused")
    assert code == 1, (out, err)
    assert err == ""  # --quiet: nothing but the report
    report = json.loads(out)
    assert report["succeeded"] is False and "refused" in report["failure"]
    refusals = [m for m in report["modules"] if m["outcome"] == "refused"]
    assert [m["path"] for m in refusals] == ["front>front"], report["modules"]
    (head,) = refusals
    assert head["verdict"] == "wrong key" and head["reason"] and head["version"] == 1
    # the head passes on no image it refused: none of the others ran or reported it
    assert all(m["outcome"] in ("refused", "withheld") for m in report["modules"]), report["modules"]
    assert head_refused == {"wrong key": 1}, head_refused


def test_with_confirm_every_module_confirms(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with bench_robot() as world:
        assert world.signer is not None
        image = tmp_path / "cat2.simg"
        image.write_bytes(pack(caterpillar(20).image, 2, world.signer))
        code = flash(world, image, "--json", "--quiet", "--confirm")
    report = json.loads(capsys.readouterr().out)
    assert [m["outcome"] for m in report["modules"]] == ["confirmed"] * N, report
    assert code == 0


def test_text_report_when_nobody_answers(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A cable with nobody at the other end: the flasher gives up (the module at the cable is
    silent) and says no module answered."""
    image = tmp_path / "cat2.simg"
    image.write_bytes(pack(caterpillar(20).image, 2, new_private_key()))
    master, slave = os.openpty()
    try:
        code = main([str(image), "--port", os.ttyname(slave), "--timeout", "30"])
    finally:
        os.close(slave)
        os.close(master)
    out, err = capsys.readouterr()
    assert code == 1
    assert out.startswith(f"{image}: version 2, sha256 ") and "no module answered through the cable" in out
    assert "flash: done: 0 module(s) heard of" in err


def test_ctrl_c_stops_the_flasher_and_exits_130(tmp_path: Path) -> None:
    """At a 1 s cycle a silent cable takes 25 s to give up: Ctrl-C ends it within a cycle,
    the report so far on standard output, no traceback."""
    image = tmp_path / "cat2.simg"
    image.write_bytes(pack(caterpillar(20).image, 2, new_private_key()))
    master, slave = os.openpty()
    argv = [str(image), "--port", os.ttyname(slave), "--cycle-ms", "1000", "--timeout", "60"]
    code = "import sys; from tools.flash import main; sys.exit(main(sys.argv[1:]))"
    proc = subprocess.Popen([sys.executable, "-c", code, *argv], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert proc.stderr is not None
        first = proc.stderr.readline()  # the command is up and its Ctrl-C handler in place
        assert first.startswith("flash: "), first
        proc.stderr.readline()  # the first progress line: the flasher runs
        proc.send_signal(signal.SIGINT)
        out, rest = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        os.close(slave)
        os.close(master)
    assert proc.returncode == 130, (out, rest)
    assert "interrupted in phase sending" in out and "interrupted" in rest and "Traceback" not in rest


@pytest.mark.parametrize(
    ("what", "argv", "says"),
    [
        ("garbage image", ["{junk}", "--port", "{port}"], "{junk}: not a DH2 program image"),
        ("missing image", ["{missing}", "--port", "{port}"], "{missing}: cannot read the image"),
        ("an image cut short", ["{short}", "--port", "{port}"], "{short}: signed image: cut short"),
        (
            "--cycle-ms 0",
            ["{image}", "--port", "{port}", "--cycle-ms", "0"],
            "--cycle-ms: expected a number more than 0 and at most 60000, got '0'",
        ),
        (
            "--cycle-ms inf",
            ["{image}", "--port", "{port}", "--cycle-ms", "inf"],
            "--cycle-ms: expected a number more than 0 and at most 60000, got 'inf'",
        ),
        ("--timeout nan", ["{image}", "--port", "{port}", "--timeout", "nan"], "--timeout nan: must be a positive"),
        ("--timeout -1", ["{image}", "--port", "{port}", "--timeout", "-1"], "--timeout -1: must be a positive"),
        ("--baudrate 0", ["{image}", "--port", "{port}", "--baudrate", "0"], "--baudrate 0: must be a positive"),
        ("a slow line", ["{image}", "--port", "{port}", "--baudrate", "9600"], "a 9600-baud serial line gives"),
        ("no such port", ["{image}", "--port", "{nowhere}"], "--port {nowhere}: cannot open the serial port"),
        ("not a port", ["{image}", "--port", "{tmp}"], "--port {tmp}: cannot open the serial port"),
        (
            "--cycle-ms abc",
            ["{image}", "--port", "{port}", "--cycle-ms", "abc"],
            "--cycle-ms: expected a number more than 0 and at most 60000, got 'abc'",
        ),
        ("no cable", ["{image}"], "give the cable: --port DEV (serial links) or --interface I"),
        ("two cables", ["{image}", "--port", "{port}", "-i", "virtual"], "give the cable: --port DEV"),
        ("no --channel", ["{image}", "-i", "virtual", "--contact", "{port}"], "--channel is missing"),
        ("no --contact", ["{image}", "-i", "virtual", "-c", "x"], "--contact is missing"),
        (
            "--bitrate 0",
            ["{image}", "-i", "virtual", "-c", "x", "--contact", "{port}", "-b", "0"],
            "--bitrate: expected a whole number 10000..12000000, got '0'",
        ),
        (
            "a slow bus",
            ["{image}", "-i", "virtual", "-c", "x", "--contact", "{port}", "-b", "125000"],
            "a 125000 bit/s CAN bus gives a rollout",
        ),
        (
            "no such interface",
            ["{image}", "-i", "nosuchbus", "-c", "x", "--contact", "{port}"],
            "--interface nosuchbus --channel x: cannot open the bus",
        ),
        (
            "no such contact",
            ["{image}", "-i", "virtual", "-c", "x", "--contact", "{nowhere}"],
            "--contact {nowhere}: cannot open the cable's connector-local channel",
        ),
    ],
)
def test_bad_input_exits_2_naming_what_is_wrong(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], what: str, argv: list[str], says: str
) -> None:
    image = tmp_path / "cat2.simg"
    data = pack(caterpillar(20).image, 2, new_private_key())
    image.write_bytes(data)
    (tmp_path / "junk.simg").write_bytes(b"no image at all\n" * 4)
    (tmp_path / "short.simg").write_bytes(data[:100])
    master, slave = os.openpty()
    names = {
        "image": str(image),
        "junk": str(tmp_path / "junk.simg"),
        "short": str(tmp_path / "short.simg"),
        "missing": str(tmp_path / "missing.simg"),
        "nowhere": str(tmp_path / "ttyNOWHERE"),
        "tmp": str(tmp_path),
        "port": os.ttyname(slave),
    }
    try:
        code = main([a.format(**names) for a in argv])
    finally:
        os.close(slave)
        os.close(master)
    out, err = capsys.readouterr()
    assert code == 2, (what, out, err)
    assert out == ""
    assert says.format(**names) in err, (what, err)
    assert "Traceback" not in err


def test_help_names_the_exit_codes(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "usage: dh2rt flash" in out and "exit codes:" in out and "130  interrupted" in out


@pytest.mark.parametrize("case", ["unsigned", "tampered"])
def test_an_unsigned_or_tampered_image_is_refused_before_a_byte_is_sent(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str
) -> None:
    """Exit 2 before the port is written: the unsigned program image (key id none), and,
    against the robot's key (--trust), a signed image with a byte of its header changed."""
    write_key_pair(tmp_path / "robot.key")
    key = read_private_key(tmp_path / "robot.key")
    program = caterpillar(20).image
    if case == "unsigned":
        data = program  # today's DH2IMG1 program image: an unsigned image of version 0
    else:
        signed = bytearray(pack(program, 2, key))
        signed[8] ^= 0x01  # the program version, covered by the signature only
        data = bytes(signed)
    image = tmp_path / f"{case}.simg"
    image.write_bytes(data)
    master, slave = os.openpty()
    os.set_blocking(master, False)
    try:
        trust = [] if case == "unsigned" else ["--trust", str(tmp_path / "robot.key.pub")]  # unsigned: no key needed
        code = main([str(image), "--port", os.ttyname(slave), *trust, "--quiet"])
        try:
            sent = os.read(master, 4096)
        except BlockingIOError:
            sent = b""
    finally:
        os.close(slave)
        os.close(master)
    out, err = capsys.readouterr()
    assert code == 2, (out, err)
    assert sent == b"", sent
    says = "unsigned image (key id (none))" if case == "unsigned" else "tampered: the signature does not match"
    assert says in err and "Traceback" not in err, err
