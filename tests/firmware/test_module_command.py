"""`dh2rt module --config module.toml`: the program a module runs on its own processor.

Its config is checked before anything starts (each error names its key and exits 2), it
starts cycling with no controller, SIGTERM stops it with a final status line, it imports only
what its config needs, and modules started with nothing but their config files (ports of
the link emulator, which plays the infrared pairs) find each other, type themselves and run
Table I's wave, as a capture of their links shows."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from dh2rt.bundled import compile_bundled
from dh2rt.signed_image import pack, public_key_path, read_private_key, write_key_pair
from hil.link_emulator import LinkEmulator
from hil.servo_emulator import ServoEmulator
from tests.hil.holds import assert_rows_not_held_by_themselves
from tests.marks import sweep
from tools.capture_sink import FileSink
from tools.reading import open_capture

ROOT = Path(__file__).resolve().parents[2]


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


def signer(tmp_path: Path) -> tuple[bytes, Path]:
    """A signing key of this test's (made once), and its public key file."""
    key = tmp_path / "signer.key"
    if not key.exists():
        write_key_pair(key)
    return read_private_key(key), public_key_path(key)


def module_dir(tmp_path: Path, name: str, body: str, version: int = 1) -> Path:
    """A module's folder: module.toml, and a flash holding the caterpillar signed by the
    test's key, which the module trusts."""
    private, public = signer(tmp_path)
    folder = tmp_path / name
    (folder / "flash").mkdir(parents=True)
    image = pack(compile_bundled("caterpillar.dh2").image, version, private)
    (folder / "flash" / "program.img").write_bytes(image)
    program = f'name = "{name}"\n[program]\nflash = "flash"\ntrust = ["{public}"]\n'
    (folder / "module.toml").write_text(program + body)
    return folder / "module.toml"


def run_module(config: Path, *args: str, timeout: float = 30) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "dh2rt", "module", "--config", str(config), *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def start_module(config: Path, **env: str) -> subprocess.Popen[str]:
    cmd = [sys.executable, "-m", "dh2rt", "module", "--config", str(config)]
    return subprocess.Popen(
        cmd, stderr=subprocess.PIPE, text=True, cwd=ROOT, env={**os.environ, **env}, start_new_session=True
    )


def stop(proc: subprocess.Popen[str], signalled: bool = False) -> tuple[int, list[dict[str, Any]]]:
    """SIGTERM (once), as systemd stops a unit; the exit code and the JSON log lines."""
    if not signalled:
        proc.send_signal(signal.SIGTERM)
    _out, err = proc.communicate(timeout=20)
    return proc.returncode, [json.loads(line) for line in err.splitlines() if line.startswith("{")]


INPROC = '[transport]\nkind = "inproc"\n'

BAD = [
    ("", '[program]\nflash = "flash"\nallow_unsigned = true\n', "[transport]: missing table"),
    (INPROC, '[program]\nflash = "flash"\n', "[program] trust: empty: list the public keys"),
    (INPROC, '[program]\nflash = "flash"\ntrust = ["nokey.pub"]\n', "[program] trust[0]: "),
    (INPROC, '[program]\nflash = "flash"\ntrust = "x.pub"\n', "[program] trust: expected a list"),
    ('[transport]\nkind = "radio"\n', "", "[transport] kind: expected one of can, serial"),
    ('[transport]\nkind = "can"\nchannel = "can0"\n', "", "[transport] interface: missing"),
    (
        '[transport]\nkind = "can"\ninterface = "slcan"\nchannel = "/dev/ttyACM0"\nbitrate = "fast"\n',
        "",
        "[transport] bitrate: expected an integer",
    ),
    (
        '[transport]\nkind = "can"\ninterface = "pcan"\nchannel = "PCAN_USBBUS1"\ndata_bitrate = 2000000\n',
        "",
        "[transport] data_bitrate: is CAN FD's data phase",
    ),
    (
        '[transport]\nkind = "serial"\n[transport.connectors]\nnose = "/dev/ttyAMA1"\n',
        "",
        "[transport.connectors] nose: no such connector",
    ),
    ('[transport]\nkind = "serial"\n', "", "[transport.connectors]: missing table"),
    (INPROC + '[servos]\nport = "/dev/ttyUSB0"\ndof1_id = 1\ndof2_id = 1\n', "", "[servos] dof2_id: DOF1 and DOF2"),
    (INPROC + '[servos]\nport = "/dev/ttyUSB0"\ndof1_id = 300\n', "", "[servos] dof1_id: expected an integer 0..252"),
    (INPROC + '[servos]\nport = "/dev/ttyUSB0"\nmodel = "XL999"\n', "", "[servos] model: unknown Dynamixel model"),
    (INPROC + '[servos]\nstand_in = "robot"\n', "", "[servos] stand_in: expected one of recording, none"),
    (INPROC + "[servos]\nbaud = 57600\n", "", "[servos] baud: only with a servo port"),
    (INPROC + "[cycle]\nperiod_ms = 0\n", "", "[cycle] period_ms: expected a positive number"),
    (INPROC + "[cycle]\nsilence_cycles = true\n", "", "[cycle] silence_cycles: expected an integer"),
    (INPROC + "[cycle]\nperiod_ms = nan\n", "", "[cycle] period_ms: expected a positive number at most 60000"),
    (INPROC + "[cycle]\nperiod_ms = inf\n", "", "[cycle] period_ms: expected a positive number"),
    (INPROC + "[cycle]\nperiod_ms = 1e12\n", "", "[cycle] period_ms: expected a positive number"),
    (INPROC + "[cycle]\nhandshake_s = nan\n", "", "[cycle] handshake_s: expected a number from 0 to 600"),
    (INPROC + "[cycle]\nhandshake_s = inf\n", "", "[cycle] handshake_s: expected a number from 0"),
    (INPROC + "[cycle]\nhandshake_s = -1\n", "", "[cycle] handshake_s: expected a number from 0"),
    (INPROC + "[cycle]\nsilence_cycles = 100000000\n", "", "[cycle] silence_cycles: expected an integer 1..10000"),
    (INPROC + '[servos]\nport = "/dev/ttyUSB0"\nlatency_ms = nan\n', "", "[servos] latency_ms: expected a positive"),
    (INPROC + "[sensors]\nservo_every = 10000000000\n", "", "[sensors] servo_every: expected an integer 1.."),
    (INPROC + "[log]\nstatus_every = 0\n", "", "[log] status_every: expected an integer 1.."),
    (INPROC + 'colour = "red"\n', "", "[transport] colour: unknown key"),
    (INPROC + "[cycles]\n", "", "cycles: unknown key"),
    (INPROC + "[cycle\n", "", "not valid TOML: Expected ']' at the end of a table declaration (at line"),
]


@pytest.mark.parametrize(("body", "program", "words"), BAD)
def test_every_config_error_names_its_key_and_exits_2(body: str, program: str, words: str, tmp_path: Path) -> None:
    config = module_dir(tmp_path, "m", body)
    if program:  # a [program] table written twice is itself an error: replace the whole file
        config.write_text(program + body)
    proc = run_module(config, "--check-config")
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert str(config) in proc.stderr and words in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr


def test_a_flash_without_a_program_says_how_to_write_one(tmp_path: Path) -> None:
    config = module_dir(tmp_path, "m", INPROC)
    (config.parent / "flash" / "program.img").unlink()
    proc = run_module(config, "--check-config")
    assert proc.returncode == 2 and "[program] flash:" in proc.stderr and "holds no program" in proc.stderr
    assert "dh2rt image" in proc.stderr


def test_check_config_says_what_it_sets_up(tmp_path: Path) -> None:
    adapter, servos = tmp_path / "ttyACM0", tmp_path / "ttyUSB0"  # the devices, there (see below)
    adapter.touch()
    servos.touch()
    body = (
        f'[transport]\nkind = "can"\ninterface = "slcan"\nchannel = "{adapter}"\nbitrate = 1000000\n'
        "[transport.links]\nback = { link_id = 4, side = 0 }\n"
        f'[servos]\nport = "{servos}"\ndof1_id = 3\ndof2_id = 4\nmodel = "XM430-W210"\n'
    )
    proc = run_module(module_dir(tmp_path, "spine0", body), "--check-config")
    assert proc.returncode == 0, proc.stderr
    assert (
        "program caterpillar" in proc.stdout and "interface=slcan" in proc.stdout and "bitrate=1000000" in proc.stdout
    )
    assert "back: BusEnd(link_id=4, side=0)" in proc.stdout and "ids (3, 4)" in proc.stdout


def test_check_config_names_every_missing_device(tmp_path: Path) -> None:
    """A device the config needs and that is not there is found by --check-config (exit 2,
    each named by its key), and a module on its own refuses to start without it."""
    there = tmp_path / "ttyAMA1"
    there.touch()
    body = (
        f'[transport]\nkind = "serial"\n[transport.connectors]\nfront = "{there}"\nback = "/dev/no-such-uart"\n'
        '[servos]\nport = "/dev/no-such-servos"\n'
    )
    config = module_dir(tmp_path, "m", body)
    for args in (("--check-config",), ()):
        proc = run_module(config, *args)
        assert proc.returncode == 2, proc.stdout + proc.stderr
        assert "[transport.connectors] back: /dev/no-such-uart: no such device" in proc.stderr
        assert "[servos] port: /dev/no-such-servos: no such device" in proc.stderr
        assert str(there) not in proc.stderr and "Traceback" not in proc.stderr
    channels = module_dir(
        tmp_path, "c", '[transport]\nkind = "virtual"\n[connectors]\nfront = { device = "/dev/no-such-ir", '
        'contact = "/sys/class/gpio/no-such-pin/value" }\n'
    )  # fmt: skip
    proc = run_module(channels, "--check-config")
    assert proc.returncode == 2
    assert "[connectors] front device: /dev/no-such-ir" in proc.stderr
    assert "[connectors] front contact: /sys/class/gpio/no-such-pin/value" in proc.stderr


def test_ctrl_c_ends_a_module_with_130_after_winding_down(tmp_path: Path) -> None:
    config = module_dir(tmp_path, "solo", INPROC + "[log]\nstatus_every = 5\n")
    proc = start_module(config)
    assert proc.stderr is not None
    for line in proc.stderr:  # cycling (its handlers in place) once it reports a status
        if '"status"' in line:
            break
    proc.send_signal(signal.SIGINT)
    code, lines = stop(proc, signalled=True)
    assert code == 130
    assert lines[-1]["event"] == "final" and lines[-1]["failed"] is False


def test_sigterm_stops_cleanly_with_a_final_status(tmp_path: Path) -> None:
    config = module_dir(tmp_path, "solo", INPROC + '[log]\nstatus_every = 10\nstatus_file = "status.json"\n')
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)  # systemd's end of sd_notify
    notify_path = str(tmp_path / "notify.sock")
    notify.bind(notify_path)
    notify.settimeout(10)
    try:
        proc = start_module(config, NOTIFY_SOCKET=notify_path)
        messages = [notify.recv(4096).decode() for _ in range(3)]
        code, lines = stop(proc)
        while True:
            try:
                messages.append(notify.recv(4096).decode())
            except TimeoutError:
                break
            notify.settimeout(0.5)
    finally:
        notify.close()
    assert code == 0
    assert messages[0] == "READY=1" and messages[1].startswith("WATCHDOG=1\nSTATUS=cycle ") and "STOPPING=1" in messages
    assert lines[0]["event"] == "log" and lines[0]["message"].startswith("started: module solo")
    assert all(line["module"] == "solo" and line["time"].endswith("Z") for line in lines)
    final = lines[-1]
    assert final["event"] == "final" and final["failed"] is False and final["cycle"] >= 10
    assert json.loads((config.parent / "status.json").read_text())["event"] == "final"


#: Run in a module process before ``main``: SIGTERM after its 30th cycle, however slow the machine
#: (its signal handlers are in place by then).
STOP_AFTER_30_CYCLES = (
    "import firmware.main_loop as mp\n"
    "end_cycle = mp.ModuleHost.end_cycle\n"
    "def counted(host, rt):\n"
    "    end_cycle(host, rt)\n"
    "    if rt.cycle == 30:\n"
    "        os.kill(os.getpid(), signal.SIGTERM)\n"
    "mp.ModuleHost.end_cycle = counted\n"
)


def run_probed(config: Path, modules: tuple[str, ...]) -> tuple[list[str], dict[str, Any]]:
    """``dh2rt module`` (its ``main``) in a subprocess for 30 cycles; which of ``modules`` it had
    imported when it stopped, and its final log line. It must exit 0."""
    code = (
        "import os, signal, sys\n"
        + STOP_AFTER_30_CYCLES
        + f"rc = mp.main(['--config', {str(config)!r}])\n"
        + f"print(json.dumps(sorted(m for m in {modules!r} if sys.modules.get(m) is not None)))\n"
        "sys.exit(rc)\n"
    )
    proc = subprocess.run([sys.executable, "-c", "import json\n" + code], capture_output=True, text=True, timeout=120,
                          cwd=ROOT)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = [json.loads(line) for line in proc.stderr.splitlines() if line.startswith("{")]
    assert lines[-1]["event"] == "final" and lines[-1]["cycle"] >= 30, lines[-1]
    return json.loads(proc.stdout), lines[-1]


def test_a_module_with_servos_imports_no_pybullet(tmp_path: Path) -> None:
    with ServoEmulator((1, 2)) as emulator:
        emulator.start()
        config = module_dir(tmp_path, "m", INPROC + f'[servos]\nport = "{emulator.port_path}"\n')
        loaded, final = run_probed(config, ("pybullet", "matplotlib", "PIL", "numpy", "sim"))
    assert loaded == []
    assert final["actuator_fault"] is None  # the servos were driven


def test_a_module_on_a_bus_loads_no_openssl(tmp_path: Path) -> None:
    """python-can imports asyncio, which would load OpenSSL; a module process never does
    (docs/firmware.md, "Footprint"), and python-can works without it."""
    bus = '[transport]\nkind = "virtual"\nchannel = "lean"\n[transport.links]\nback = { link_id = 3, side = 0 }\n'
    loaded, _final = run_probed(module_dir(tmp_path, "m", bus), ("can", "ssl", "_ssl"))
    assert loaded == ["can"]


def test_a_module_loads_the_rollout_off_its_cycle_and_never_argparse(tmp_path: Path) -> None:
    """Booted from its flash with nothing to roll out, a module started as systemd starts it
    carries no argparse and no event parser (docs/firmware.md, "Footprint"); the rollout's code
    is loaded by the door's background thread as it boots, so that no first transfer frame
    holds a cycle up importing it (firmware/flash/door.py); tests/firmware/test_flash_module_host.py
    opens the rollout when an image comes."""
    bus = '[transport]\nkind = "virtual"\nchannel = "door"\n[transport.links]\nback = { link_id = 3, side = 0 }\n'
    # every file of dh2rt.flash
    machinery = tuple(f"dh2rt.flash.{p.stem}" for p in sorted((ROOT / "dh2rt" / "flash").glob("[!_]*.py")))
    assert "dh2rt.flash.rollout" in machinery and "dh2rt.flash.flasher" in machinery
    never = ("argparse", "gettext", "dh2rt.events")
    loaded, final = run_probed(module_dir(tmp_path, "m", bus), (*never, *machinery, "firmware.flash.module_host",
                                                                  "firmware.flash.door"))  # fmt: skip
    assert not set(never) & set(loaded), loaded
    # the module's own part in rollouts is loaded, ready before an image comes; the flasher's is not
    assert {"firmware.flash.door", "firmware.flash.module_host", "dh2rt.flash.rollout"} <= set(loaded), loaded
    assert "dh2rt.flash.flasher" not in loaded, loaded
    assert final["program"]["version"] == 1  # booted from the flash, so it takes part in rollouts


VALID_ARGS = [
    ["--config", "m.toml"],
    ["--config=m.toml"],
    ["--check-config", "--config", "m.toml"],
    ["--config", "m.toml", "--check-config"],
    ["--config=m.toml", "--check-config"],
    ["--config", ""],
    ["--config", "dir with spaces/m.toml"],
    ["--config", '{"module": 1}'],
    ["--config", "@m.json"],
]
OTHER_ARGS = [
    [],
    ["--check-config"],
    ["--config"],
    ["--config="],
    ["--config", "-x"],
    ["--conf", "m.toml"],
    ["--config", "a", "--config", "b"],
    ["--check-config", "--check-config", "--config", "m.toml"],
    ["--config", "m.toml", "extra"],
    ["-h"],
    ["--help"],
    ["--config", "m.toml", "--help"],
]


@pytest.mark.parametrize("argv", VALID_ARGS, ids=" ".join)
def test_a_module_reads_its_usual_arguments_as_argparse_does(argv: list[str]) -> None:
    from firmware.main_loop import build_parser, plain_arguments

    plain = plain_arguments(argv)
    assert plain is not None
    ns = build_parser().parse_args(argv)
    assert (plain.config, plain.check_config) == (ns.config, ns.check_config)


@pytest.mark.parametrize("argv", OTHER_ARGS, ids=lambda a: " ".join(a) or "nothing")
def test_anything_else_goes_to_argparse(argv: list[str]) -> None:
    from firmware.main_loop import plain_arguments

    assert plain_arguments(argv) is None


def test_help_and_mistakes_are_argparses(tmp_path: Path) -> None:
    shown = subprocess.run([sys.executable, "-m", "dh2rt", "module", "--help"], capture_output=True, text=True,
                           timeout=60, cwd=ROOT)  # fmt: skip
    assert shown.returncode == 0 and "usage: dh2rt module" in shown.stdout and "--check-config" in shown.stdout
    wrong = subprocess.run([sys.executable, "-m", "dh2rt", "module", "--config"], capture_output=True, text=True,
                           timeout=60, cwd=ROOT)  # fmt: skip
    assert wrong.returncode == 2 and "--config: expected one argument" in wrong.stderr
    assert "Traceback" not in wrong.stderr


@pytest.mark.realtime
@pytest.mark.parametrize("count", sweep([8, 2]))
def test_modules_alone_on_serial_links_find_each_other_and_run_the_wave(count: int, tmp_path: Path) -> None:
    """A snake of `count` modules: each given only its module.toml naming its connectors'
    UARTs (the link emulator's ptys: the infrared pairs). Nobody tells them their neighbours,
    their types or when to start."""
    program = compile_bundled("caterpillar.dh2")
    sink = FileSink(tmp_path / "snake.pcapng", [program.image])

    def tap(t: float, link: int, side: int, wire: bytes, lost: bool) -> None:
        sink.serial_frame(t, link, side, wire, lost=lost)

    procs: list[subprocess.Popen[str]] = []
    with LinkEmulator(tap=tap) as links:
        ports: dict[tuple[int, str], str] = {}
        for i in range(count - 1):  # module i's back to module i+1's front
            pair = links.add_link(i)
            ports[(i, "back")], ports[(i + 1, "front")] = pair.paths
        try:
            for m in range(count):
                connectors = "".join(f'{c} = "{ports[(m, c)]}"\n' for c in ("front", "back") if (m, c) in ports)
                body = (
                    '[transport]\nkind = "serial"\n[transport.connectors]\n'
                    + connectors
                    + "[cycle]\nperiod_ms = 30\nsilence_cycles = 6\n"
                    '[log]\nstatus_every = 10\nstatus_file = "status.json"\n'
                )
                procs.append(start_module(module_dir(tmp_path, f"m{m}", body)))
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and not _cycled(tmp_path, count, 120):
                time.sleep(0.2)
            # the robot running: each module's last status before any was stopped
            running = [json.loads((tmp_path / f"m{m}" / "status.json").read_text()) for m in range(count)]
            for p in procs:  # power off all at once (one by one, the last would miss the first)
                p.send_signal(signal.SIGTERM)
            results = [stop(p, signalled=True) for p in procs]
            relay_held_ms = links.held_s * 1000
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
                    p.wait()
    sink.close()
    assert all(code == 0 for code, _ in results), [
        (code, [x.get("message") or x["event"] for x in lines[-4:]]) for code, lines in results
    ]
    assert all(lines[-1]["event"] == "final" for _, lines in results)
    assert [r["type"] for r in running] == ["head"] + ["body"] * (count - 2) + ["tail"]
    assert all(r["counters"]["refused"] == 0 for r in running), [(r["name"], r["counters"]) for r in running]
    # no link lost, unless the machine held a module (or the relay) as long as the liveness
    # bound: eight processes share two cores here, where a robot has a processor a module
    # (CI once saw every module start one cycle late at the same moment, and one link lost)
    assert_rows_not_held_by_themselves(running, period_s=0.030, silence_cycles=6, relay_held_ms=relay_held_ms)
    # Table I on the wire: the head's X(A) goes down link 0, the next module answers with X(B)
    # on link 1 within a cycle or two, and so on down the snake
    hormones = [h for h in open_capture(tmp_path / "snake.pcapng").hops() if h.kind == "hormone"]
    assert all(h.side == 0 and h.sender == "back" for h in hormones)  # head to tail, through backs
    phases = "ABCD"
    # waves that start once the whole snake carries them: modules that start on their own link
    # up at their own pace, and a wave sent before the tail's link was up reaches no tail
    whole = min(h.time for h in hormones if h.link == count - 2)
    starts = [h for h in hormones if h.link == 0 and h.time > whole][:4]
    assert len(starts) == 4, len(starts)
    for start in starts:
        assert start.hormone is not None
        phase = phases.index(str(start.hormone.args[0]))
        t = start.time
        for link in range(1, count - 1):
            phase = (phase + 1) % 4
            nxt = next(h for h in hormones if h.link == link and h.time > t)
            assert nxt.text == f"X({phases[phase]})", (link, nxt.text)
            assert nxt.time - t < 0.1, (link, nxt.time - t)
            t = nxt.time


def _cycled(tmp_path: Path, count: int, cycles: int) -> bool:
    for m in range(count):
        try:
            status = json.loads((tmp_path / f"m{m}" / "status.json").read_text())
        except (OSError, ValueError):
            return False
        if status.get("cycle", 0) < cycles:
            return False
    return True


def test_the_documented_module_toml_is_valid(tmp_path: Path) -> None:
    """docs/firmware.md's module.toml (its flash put here) passes the checks as written."""
    import re
    import tomllib

    from firmware.module_toml import parse_toml

    doc = (ROOT / "docs" / "firmware.md").read_text()
    text = re.findall(r"```toml\n(.*?)```", doc, re.S)[0]
    data = tomllib.loads(text)
    flash = tmp_path / "flash"
    flash.mkdir()
    (flash / "program.img").write_bytes(pack(compile_bundled("caterpillar.dh2").image, 1, signer(tmp_path)[0]))
    data["program"]["flash"] = str(flash)
    data["program"]["trust"] = [str(signer(tmp_path)[1])]
    config = parse_toml(data, "firmware.md", tmp_path)
    assert config.transport == "can" and config.bus_options["interface"] == "socketcan"
    assert sorted(config.connector_channels) == [1, 2, 3, 4] and config.servo_port == "/dev/ttyUSB0"
