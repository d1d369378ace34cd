"""`dh2rt capture` records what a python-can bus carries; `dh2rt stats` counts it."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import can
import numpy as np
import pytest

from dh2rt.hormone import Hormone
from dh2rt.testing import contract_codec
from dh2rt.wire.can_frames import SINGLE, make_arbitration_id
from tools.capture import main as capture
from tools.dump import main as dump
from tools.pcap import CapturedFrame, write_pcap
from tools.stats import frame_bits
from tools.stats import main as stats

ROOT = Path(__file__).resolve().parents[2]
CONTRACT = (
    "program contract\nconst ClockCycle = 4\nhormone X(a: A | B)\nhormone N(n: int)\n"
    "hormone P(n: int, m: int, d: up | down)\n"
)


@pytest.fixture
def program(tmp_path: Path) -> Path:
    path = tmp_path / "contract.dh2"
    path.write_text(CONTRACT)
    return path


@pytest.mark.parametrize("suffix", [".pcapng", ".pcap", ".log", ".blf"])
def test_capture_records_what_the_bus_carries(
    suffix: str, program: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # digits at the end of a channel's name become a channel number in BLF and ASC: this one
    # does not fit their 16 bits, and the frames must be captured all the same
    channel = f"capture-{suffix[1:]}-2026112305"
    codec = contract_codec()
    payload = codec.encode(2, Hormone("N", (7,)))
    can_id = make_arbitration_id(0, SINGLE, 0, 4, 1)

    # the sender's bus is open before the capture starts: a virtual bus nobody else in the
    # process has open is refused (nothing could ever be sent on it)
    bus = can.Bus(interface="virtual", channel=channel)

    def send() -> None:
        with bus:
            time.sleep(0.3)  # let the capture open its bus first
            for _ in range(25):
                bus.send(can.Message(arbitration_id=can_id, data=payload, is_extended_id=True))

    sender = threading.Thread(target=send)
    sender.start()
    out = tmp_path / f"cap{suffix}"
    try:
        args = ["-o", str(out), "-i", "virtual", "-c", channel, "--count", "25", "--duration", "10"]
        assert capture([*args, "--program", str(program)]) == 0
    finally:
        sender.join()
    assert f"{out}: 25 frames" in capsys.readouterr().out
    assert dump([str(out)]) == 0  # the program went with the capture (inside a pcapng, beside the others)
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 25 and all("link    4 side 1  hormone   N(7) via back" in line for line in lines)


def test_capture_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert capture(["-o", str(tmp_path / "x.txt"), "-i", "virtual", "-c", "c"]) == 2
    assert ".pcap" in capsys.readouterr().err
    assert capture(["-o", str(tmp_path / "x.pcap"), "-i", "nosuchbus", "-c", "c"]) == 2
    assert "cannot open python-can nosuchbus bus" in capsys.readouterr().err
    assert capture(["-o", str(tmp_path / "x.pcap"), "-i", "virtual", "-c", "c", "--count", "0"]) == 2


def test_frame_bits_worst_case_stuffing() -> None:
    # extended id, n data bytes: 67 + 8n fixed bits, one stuff bit per 4 of the 54 + 8n stuffed
    assert list(frame_bits(np.array([0, 4, 8]))) == [67 + 13, 67 + 32 + 21, 67 + 64 + 29]


def test_stats_counts_links_kinds_load_and_errors(
    program: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    codec = contract_codec()
    x = codec.encode(1, Hormone("X", ("A",)))
    frames = [CapturedFrame(i * 0.01, make_arbitration_id(0, SINGLE, 0, 2, 0), x) for i in range(101)]
    frames += [CapturedFrame(0.5, make_arbitration_id(0, SINGLE, 0, 3, 1), b"\xff")]  # does not decode
    path = tmp_path / "s.pcap"
    write_pcap(path, frames)
    assert stats([str(path), "--program", str(program)]) == 0
    out = capsys.readouterr().out
    assert "102 frames in 1.000 s (102.0 frames/s)" in out
    bits = 101 * int(frame_bits(np.array([len(x)]))[0]) + int(frame_bits(np.array([1]))[0])
    assert f"({bits:,} bits)" in out and f"{bits / 1_000_000:.1%}" in out
    assert "     2 hormone         101     101.0" in out
    assert "errors: 1 frame(s)" in out


@pytest.mark.parametrize("command", ["capture", "stats", "follow"])
def test_help_of_each_capture_command(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    from dh2rt.cli import main as dh2rt

    assert dh2rt([command, "--help"]) == 0
    assert f"usage: dh2rt {command}" in capsys.readouterr().out
