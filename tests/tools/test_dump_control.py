"""`dh2rt dump` shows the operator's control frames (:mod:`dh2rt.wire.operator`) as kind
``control``, one line a message, on CAN (segment trains reassembled) and on serial links; an
INJECT names its hormone when the capture carries the program; a broken or reserved frame is
an error that says why."""

from __future__ import annotations

import pytest

from dh2rt.hormone import Hormone
from dh2rt.program import CompiledProgram
from dh2rt.wire import motion as mw
from dh2rt.wire import operator as op
from dh2rt.wire.can_frames import segment
from dh2rt.wire.frame import program_digest
from dh2rt.wire.serial_framing import encode_serial
from tools.capture_reader import CanRecord, Record
from tools.decode import Decoder
from tools.serial_records import SerialRecord

FRONT, BACK = 1, 2
KEY_ID = bytes.fromhex("0011223344556677")


def records(payloads: list[bytes], medium: str) -> list[Record]:
    if medium == "serial":
        return [SerialRecord(at, 3, 0, encode_serial(p)) for at, p in enumerate(payloads)]
    return [CanRecord(at, f.arbitration_id, f.data, True) for at, p in enumerate(payloads) for f in segment(p, 5, 0)]


@pytest.mark.parametrize("medium", ["can", "serial"])
def test_control_frames_read_in_operator_terms(medium: str, caterpillar: CompiledProgram) -> None:
    digest = program_digest(caterpillar.image)
    content = caterpillar.vocabulary.encode_content(Hormone("X", ("A",)))
    messages: list[tuple[op.Message, str]] = [
        (
            op.Signed(op.Inject(digest, content, ((BACK, FRONT),)), 7, KEY_ID, bytes(64), 1),
            "INJECT #7 key 0011223344556677 hops 1, X(A) at back>front",
        ),
        (op.Signed(op.Pause(), 8, KEY_ID, bytes(64)), "PAUSE #8 key 0011223344556677 hops 0"),
        (
            op.Signed(op.Watch(100, 0), 11, KEY_ID, bytes(64)),
            "WATCH #11 key 0011223344556677 hops 0, hormone #0 for 100 cycles",
        ),
        (op.Watched(11, 42, BACK, bytes.fromhex("c10000")), "WATCHED #11 cycle 42 at back: c10000"),
        (
            op.Refused(9, 0, ((BACK, FRONT),), op.RefusalReason.REPLAYED),
            "REFUSED #9 from back>front, left 0: REPLAYED",
        ),
        (
            op.StateReply(10, 1, ((BACK, FRONT),), op.ModuleStatus(digest, 1, True, 3, 44, (0, 1, 0, 0))),
            "STATE_REPLY #10 from back>front, left 1: type 1, LocalTimer 3, cycle 44, status 0,1,0,0, paused",
        ),
    ]
    payloads = [op.encode(BACK, m) for m, _ in messages]
    hops = [h for h in Decoder([caterpillar]).hops(records(payloads, medium)) if h.kind != "segment"]
    texts = [h.text.removesuffix(" (reassembled)") for h in hops]  # a CAN segment train says so
    assert [(h.kind, h.sender) for h in hops] == [("control", "back")] * len(messages)
    assert texts == [text for _, text in messages]


@pytest.mark.parametrize("medium", ["can", "serial"])
def test_a_broken_control_frame_is_an_error_naming_the_reason(medium: str, caterpillar: CompiledProgram) -> None:
    pause = op.encode(BACK, op.Signed(op.Pause(), 8, KEY_ID, bytes(64)))
    broken = [bytes((0x22, 70)), pause + b"\x00"]
    hops = [h for h in Decoder([caterpillar]).hops(records(broken, medium)) if h.kind != "segment"]
    assert [h.error for h in hops] == [
        "control frame: message type 70 is reserved (docking motion, not yet defined)",
        "control frame PAUSE: 1 trailing byte(s)",
    ]


@pytest.mark.parametrize("medium", ["can", "serial"])
def test_motion_frames_read_in_docking_terms(medium: str, caterpillar: CompiledProgram) -> None:
    route = ((BACK, FRONT), (BACK, FRONT))
    way = "back>front back>front"
    messages: list[tuple[mw.MotionMessage, str]] = [
        (mw.Ask(3, 10, route, 1), f"ASK motion 3 #10 to {way}, hops 1"),
        (
            mw.Angles(3, 10, route, 5, (12.5, -40.0), (2, 0, 0, 0), 2),
            f"ANGLES motion 3 #10 from {way}, left 2: module 5, DOF1 12.5, DOF2 -40, links 2,0,0,0",
        ),
        (
            mw.Targets(3, 11, route, ((0, 30.0), (1, -7.25)), 2),
            f"TARGETS motion 3 #11 to {way}, hops 2: DOF1 30, DOF2 -7.25",
        ),
        (mw.End(3, 12, route[:1], 0), "END motion 3 #12 to back>front, hops 0"),
        (
            mw.SetOff(3, 13, route, 9, 2, (9, 8, 7), (4, 5), 2),
            f"SET_OFF motion 3 #13 to {way}, hops 2: to module 9 connector 2, body 9,8,7, others 4,5",
        ),
        (
            mw.SetOff(3, 14, route, 9, 2, (9,), (), 1),
            f"SET_OFF motion 3 #14 to {way}, hops 1: to module 9 connector 2, body 9, others none",
        ),
    ]
    payloads = [mw.encode(BACK, m) for m, _ in messages] + [bytes((0x22, 0x40, 0, 3))]
    hops = [h for h in Decoder([caterpillar]).hops(records(payloads, medium)) if h.kind != "segment"]
    texts = [h.text.removesuffix(" (reassembled)") for h in hops[:-1]]
    assert [(h.kind, h.sender) for h in hops[:-1]] == [("control", "back")] * len(messages)
    assert texts == [text for _, text in messages]
    assert hops[-1].kind == "error"
    assert hops[-1].error == "motion frame ASK: cut short in the motion, seq and hops at byte 2"
