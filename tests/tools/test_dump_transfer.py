"""`dh2rt dump` shows flashing's transfer frames (:mod:`dh2rt.wire.transfer`) as kind
``transfer``, one line per message in flash terms, on CAN and on serial links, and not as
"wire version" errors (issue 27); a transfer frame that does not decode stays an error that
says why."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dh2rt.program import CompiledProgram
from dh2rt.wire import transfer
from dh2rt.wire.can_frames import segment
from dh2rt.wire.serial_framing import encode_serial
from dh2rt.wire.transfer import Commit, Message, Offer, Outcome, Report, Segment
from tests.hil.flashing import capture_a_flash
from tools.capture_reader import CanRecord, Record
from tools.decode import Decoder
from tools.dump import main
from tools.serial_records import SerialRecord

FRONT, BACK = 1, 2
IMAGE = bytes.fromhex("1a2b3c4d5e6f7a8b")
#: Each message, and the line dump gives it.
MESSAGES: list[tuple[Message, str]] = [
    (Commit(IMAGE, 105_900, 2), "COMMIT 1a2b3c4d5e6f7a8b in 105.9 ms (hops 2)"),
    (Segment(0x1234, 12, bytes(80)), "SEGMENT tag 4660 #12 (80 bytes)"),
    (
        Offer(2, IMAGE, 1843, 80, 12, path=((FRONT, FRONT), (BACK, FRONT))),
        "OFFER v2 1a2b3c4d5e6f7a8b 1843 bytes, segments of 80, held 12, path front>front back>front",
    ),
    (
        Report(0x1A2B, 3, Outcome.REFUSED, 1, 1, ((BACK, FRONT),), "bad-signature", "signed by another key"),
        "REPORT refused v1 tag 6699 #3, path back>front, left 1, bad-signature, signed by another key",
    ),
]


def records(payloads: list[bytes], medium: str) -> list[Record]:
    """The capture records of ``payloads``, one a second: on CAN, the frames that carry each
    on side 0 of link 5 (several for a long one); on serial, one frame each on link 3."""
    if medium == "serial":
        return [SerialRecord(at, 3, 0, encode_serial(p)) for at, p in enumerate(payloads)]
    return [CanRecord(at, f.arbitration_id, f.data, True) for at, p in enumerate(payloads) for f in segment(p, 5, 0)]


@pytest.mark.parametrize("medium", ["can", "serial"])
def test_transfer_frames_read_in_flash_terms(medium: str, caterpillar: CompiledProgram) -> None:
    payloads = [transfer.encode(BACK, message) for message, _text in MESSAGES]
    hops = [hop for hop in Decoder([caterpillar]).hops(records(payloads, medium)) if hop.kind != "segment"]
    assert [hop.kind for hop in hops] == ["transfer"] * len(MESSAGES)
    assert [hop.text.removesuffix(" (reassembled)") for hop in hops] == [text for _m, text in MESSAGES]
    assert {hop.sender for hop in hops} == {"back"} and {hop.medium for hop in hops} == {medium}
    shown = hops[0].to_json()
    assert (shown["kind"], shown["sender"], shown["text"]) == ("transfer", "back", hops[0].text)
    assert "transfer  COMMIT 1a2b3c4d5e6f7a8b in 105.9 ms (hops 2)" in hops[0].describe()


@pytest.mark.parametrize("medium", ["can", "serial"])
def test_a_broken_transfer_frame_is_an_error_naming_the_reason(medium: str, caterpillar: CompiledProgram) -> None:
    commit = transfer.encode(BACK, Commit(IMAGE, 0, 0))
    broken = [commit[:1] + b"\x63" + commit[2:], commit + b"\x00"]  # an unknown type; a trailing byte
    hops = [hop for hop in Decoder([caterpillar]).hops(records(broken, medium)) if hop.kind != "segment"]
    assert [hop.kind for hop in hops] == ["error", "error"]
    assert hops[0].error == "transfer frame: unknown message type 99"
    assert hops[1].error == "transfer frame COMMIT: 1 trailing byte(s)"


@pytest.mark.realtime  # modules run in real time
def test_a_flash_run_dumps_without_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A loop run with a flash event, captured, then dumped: every rollout frame is shown."""
    bus_log = tmp_path / "bus.log"
    code = capture_a_flash(tmp_path, bus_log)
    assert code == 0, capsys.readouterr()
    capsys.readouterr()
    assert main([str(bus_log)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert not [line for line in lines if "wire version" in line]
    assert any(" transfer  COMMIT " in line for line in lines)
    assert main([str(bus_log), "--kind", "transfer", "--json"]) == 0
    objs = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert objs and {o["kind"] for o in objs} == {"transfer"}
    assert {o["text"].split()[0] for o in objs} >= {"OFFER", "SEGMENT", "COMMIT", "REPORT"}
