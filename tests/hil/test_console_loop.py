"""``dh2rt console`` in the loop: the launcher's ``--console FILE`` plugs a cable (a pty of its
link emulator) into the first module's free connector, and the console talks to the module
processes through it. A command signed with another key and a replayed one are refused and
counted; the run's frames still add up (the console's counted as the link carried them).
The whole operator's signal, LTS injected at the cable and the dragon becoming a snake, is a
long run."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from dh2rt import cli
from dh2rt.signed_image import private_key_pem
from dh2rt.wire import operator as op
from hil.pace import PACE
from tests.marks import LONG
from tools import console
from tools.console_link import ConsoleLink
from tools.flash import open_cable

pytestmark = pytest.mark.realtime

ROOT = Path(__file__).resolve().parents[2]
L2S = ROOT / "examples" / "legs_to_snake.dh2"
KEY = bytes(range(32))
OTHER = bytes(range(60, 92))


def wait_for(path: Path, timeout: float) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists():
            return path.read_text().strip()
        time.sleep(0.05)
    raise AssertionError(f"{path} never appeared")


class Operator(threading.Thread):
    """The console's side of a run, in a thread: waits for the cable, then runs ``work``."""

    def __init__(self, cable_file: Path, work: Callable[[str], object]) -> None:
        super().__init__(daemon=True)
        self.cable_file, self.work = cable_file, work
        self.error: BaseException | None = None
        self.result: object = None

    def run(self) -> None:
        try:
            self.result = self.work(wait_for(self.cable_file, 60))
        except BaseException as exc:  # the test reports it
            self.error = exc


def run_loop(operator: Operator, topology: str, cycles: int, key: Path, transport: str = "serial") -> int:
    """legs to snake on ``topology`` over ``transport`` at 40 ms, the console's cable in, the
    operator's thread started beside it; the launcher's exit code once both are done."""
    operator.start()
    code = PACE.call(
        cli.main,
        ["--transport", transport, "--program", str(L2S), "--topology", topology, "--cycles", str(cycles),
         "--cycle-ms", "40", "--silence-cycles", "6", "--key", str(key), "--console", str(operator.cable_file),
         "--json", "--stand-in", "recording"],
    )  # fmt: skip
    operator.join(timeout=30)
    return code


def keys(tmp_path: Path) -> tuple[Path, Path]:
    (tmp_path / "robot.key").write_bytes(private_key_pem(KEY))
    (tmp_path / "other.key").write_bytes(private_key_pem(OTHER))
    return tmp_path / "robot.key", tmp_path / "other.key"


@LONG  # 10 s of module processes; tests/tools/test_console.py covers the same on module threads
def test_console_states_and_refusals_in_the_loop(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    key, other = keys(tmp_path)
    cable_file = tmp_path / "cable"
    script = tmp_path / "commands.txt"
    script.write_text("state .\nstate back>front\npause\nresume\n")

    def work(port: str) -> dict[str, object]:
        time.sleep(0.5)  # the modules are cycling
        argv = ["--port", port, "--program", str(L2S), "--cycle-ms", "40"]
        codes: dict[str, object] = {"script": console.main([*argv, "--key", str(key), "--script", str(script)])}
        codes["other"] = console.main([*argv, "--key", str(other), "--script", str(script)])
        transport = open_cable(port, 115200)
        link = ConsoleLink(transport, KEY, period=0.04).start()
        try:
            first = link.command(op.StateRequest(()), 2.0)
            link.send_signed(op.sign(op.StateRequest(()), first.counter, KEY))  # the same again: a replay
            time.sleep(0.5)
        finally:
            link.close()
            transport.close()
        return codes

    operator = Operator(cable_file, work)
    code = run_loop(operator, "snake:2", 250, key)
    captured = capsys.readouterr()
    assert operator.error is None, operator.error
    assert operator.result == {"script": 0, "other": 1}, captured.out[-3000:]
    out = captured.out
    assert "module .: " in out and "module back>front: " in out and "paused (flooded" in out
    assert "refused by the module at .: UNTRUSTED_KEY" in out
    assert "refused by the module at back>front: UNTRUSTED_KEY" in out  # the routed STATE's end answers
    assert code == 0, captured.err[-3000:]
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["frames"]["unaccounted"] == 0, summary["frames"]
    first = summary["modules"][0]["operator"]
    assert first["refused_untrusted_key"] == 4 and first["refused_replayed"] == 1, first  # the whole script
    assert first["accepted"] == 5, first  # two states, pause, resume; the link's state
    second = summary["modules"][1]["operator"]
    assert second["accepted"] == 3, second  # its state, pause, resume
    assert second["refused_untrusted_key"] == 3, second  # the same three, signed with the other key
    assert not cable_file.exists()


@LONG
def test_lts_injected_at_the_cable_makes_the_dragon_a_snake(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """As tests/hil/test_launcher.py's --event 5:inject:tail2:LTS, but the operator's signal
    comes from dh2rt console through the cable into the first module's free connector."""
    key, _other = keys(tmp_path)
    cable_file = tmp_path / "cable"
    script = tmp_path / "commands.txt"
    script.write_text("inject LTS\n")

    def work(port: str) -> int:
        time.sleep(0.3)
        return console.main(["--port", port, "--program", str(L2S), "--cycle-ms", "40", "--key", str(key),
                             "--script", str(script)])  # fmt: skip

    operator = Operator(cable_file, work)
    code = run_loop(operator, "dragon", 400, key)
    captured = capsys.readouterr()
    assert operator.error is None and operator.result == 0, (operator.error, captured.out[-2000:])
    assert code == 0, captured.err[-3000:]
    summary = json.loads(captured.out.strip().splitlines()[-1])
    types = sorted(m["type"] for m in summary["modules"])
    assert types == ["body"] * (len(types) - 2) + ["head", "tail"], types
    assert sum("docked to" in line for line in summary["log"]) == 4


@LONG  # a loop run: modules as threads of the launcher on python-can's virtual bus
def test_console_on_a_bus_through_the_launchers_adapter(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """On a bus the launcher plays a serial-to-bus adapter: the console opens a pty as ever,
    the adapter's node negotiates a link with the first module's free connector over its
    contact and carries the control frames (segment trains) both ways; its frames are the
    run's, which still add up."""
    key, _other = keys(tmp_path)
    cable_file = tmp_path / "cable"
    script = tmp_path / "commands.txt"
    script.write_text("state .\nstate back>front\npause\nresume\ntopology\n")

    def work(port: str) -> int:
        time.sleep(1.0)  # the adapter's link negotiated
        return console.main(["--port", port, "--program", str(L2S), "--cycle-ms", "40", "--key", str(key),
                             "--script", str(script)])  # fmt: skip

    operator = Operator(cable_file, work)
    code = run_loop(operator, "snake:2", 200, key, transport="virtual")
    captured = capsys.readouterr()
    assert operator.error is None and operator.result == 0, (operator.error, captured.out[-3000:])
    assert "module back>front: tail (T2)" in captured.out and "(cable): head (T1)" in captured.out
    assert code == 0, captured.err[-3000:]
    summary = json.loads(captured.out.strip().splitlines()[-1])
    assert summary["frames"]["unaccounted"] == 0, summary["frames"]
    assert [m["operator"]["accepted"] for m in summary["modules"]] == [6, 4]
