"""The Wireshark dissector (``tools/wireshark/dh2rt.lua``): the real tshark, loading it, reads
a capture of real frames (CAN, segmented and not, and serial links, lost and corrupted) and
shows each frame as ``dh2rt dump`` does, and so it does for random frames, broken or not, and
with two passes as with one; flashing's transfer frames, of a real flash in the loop and
of every message type, broken or not, read as dump reads them (issue 27); the committed Lua
is what the generator writes from the codec's layout, and a codec whose layout moved would
make it differ.

tshark is installed here when missing (as root, with apt-get); the tests skip, saying why,
only where that is impossible.
"""

from __future__ import annotations

import dataclasses
import os
import random
import re
import shutil
import struct
import subprocess
from pathlib import Path

import pytest

from dh2rt.compiler import compile_file, compile_source
from dh2rt.hormone import Hormone
from dh2rt.program import CompiledProgram
from dh2rt.wire import can_frames, motion, operator, transfer
from dh2rt.wire.can_frames import FIRST, LAST, Segmenter, make_arbitration_id, parse_arbitration_id, segment
from dh2rt.wire.frame import WIRE_VERSION, FrameCodec, FrameKind, Hello, KeepAlive, program_digest
from dh2rt.wire.negotiation import MANAGEMENT_ID, BusMessage, BusOp, encode_bus
from dh2rt.wire.serial_framing import encode_serial
from tests.hil.flashing import capture_a_flash
from tools import serial_records, transfer_view
from tools.decode import REFUSED, Hop
from tools.pcap import CAN_EFF_FLAG
from tools.pcapng import CAN_INTERFACE, SERIAL_INTERFACE, PcapngWriter
from tools.reading import open_capture
from tools.wireshark import layout
from tools.wireshark.command import main
from tools.wireshark.generate import dissector, lua, lua_string, template

ROOT = Path(__file__).resolve().parents[2]
COMMITTED = ROOT / "tools" / "wireshark" / "dh2rt.lua"
FRONT, BACK, LEFT, RIGHT = 1, 2, 3, 4
COUNTERS = """program counters
const ClockCycle = 4
hormone GROW(by: int)
hormone W(phase: A | B, n: int, opposite: A | B)
hormone LTS
receptor grow when T == T1 and H == GROW(?n) { emit LTS via back }
"""
#: Byte 0 of a hormone frame, sender and kind bits clear: the wire version alone.
HEADER = WIRE_VERSION << 6
FIELDS = ("frame.number", "dh2rt.medium", "dh2rt.link", "dh2rt.side", "dh2rt.kind", "dh2rt.text", "_ws.col.Info")


# -- tshark ------------------------------------------------------------------------------


def _apt_install() -> str:
    """Install tshark with apt-get (refreshing the lists if the first try fails); the output
    of the last try."""
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    install = ["apt-get", "install", "-y", "--no-install-recommends", "tshark"]
    out = ""
    for commands in ([install], [["apt-get", "update"], install]):
        for command in commands:
            done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=900, check=False)
            out = done.stdout[-1000:] + done.stderr[-1000:]
        if shutil.which("tshark"):
            break
    return out


@pytest.fixture(scope="module")
def tshark() -> str:
    """The tshark to run: the installed one, or one apt-get installs now."""
    found = shutil.which("tshark")
    if found is None:
        if os.geteuid() != 0:
            pytest.skip("tshark is not installed, and installing it (apt-get install tshark) needs root")
        if shutil.which("apt-get") is None:
            pytest.skip("tshark is not installed, and this machine has no apt-get to install it")
        out = _apt_install()
        found = shutil.which("tshark")
        if found is None:
            pytest.skip(f"tshark is not installed, and apt-get install tshark failed: {out}")
    version = subprocess.run([found, "-v"], capture_output=True, text=True, timeout=60, check=False).stdout
    if not re.search(r"with Lua|Lua \d", version):
        pytest.skip(f"this tshark has no Lua: {version.splitlines()[0] if version else 'no version'}")
    return found


def run_tshark(
    tshark: str, script: Path, capture: Path, home: Path, *options: str, fields: tuple[str, ...] = FIELDS
) -> list[list[str]]:
    """tshark with ``script`` over ``capture``: per frame, the values of ``fields``. HOME is a
    fresh folder, so no personal plugin or preference interferes."""
    home.mkdir(exist_ok=True)
    env = {**os.environ, "HOME": str(home), "XDG_CONFIG_HOME": str(home / ".config")}
    command = [tshark, "-n", *options, "-X", f"lua_script:{script}", "-r", str(capture)]
    command += ["-T", "fields", "-E", "separator=/t"]
    for field in fields:
        command += ["-e", field]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, env=env, check=False)
    assert done.returncode == 0, done.stderr
    assert "Lua" not in done.stderr, done.stderr  # a script that fails to load leaves tshark running without it
    return [line.split("\t") for line in done.stdout.splitlines()]


# -- the capture -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def programs() -> tuple[CompiledProgram, CompiledProgram]:
    return compile_file(str(ROOT / "examples" / "caterpillar.dh2")), compile_source(COUNTERS, "counters.dh2")


class Recorder:
    """Writes frames into a pcapng, each on the CAN bus or on a serial link."""

    def __init__(self, path: Path, programs: tuple[CompiledProgram, ...]) -> None:
        self.writer = PcapngWriter(path, [p.image for p in programs])
        self.time = 10.0

    def _write(self, interface: int, data: bytes) -> None:
        self.writer.write(interface, self.time, data)
        self.time += 0.000250

    def can_raw(self, can_id: int, data: bytes, extended: bool = True) -> None:
        head = struct.pack(">IB3x", can_id | (CAN_EFF_FLAG if extended else 0), len(data))
        self._write(CAN_INTERFACE, head + data)

    def can(self, payload: bytes, link: int, side: int) -> int:
        """Send ``payload`` as the transport does (segmented when long); how many frames."""
        frames = segment(payload, link, side)
        for frame in frames:
            self.can_raw(frame.arbitration_id, frame.data)
        return len(frames)

    def serial(self, wire: bytes, link: int, side: int, *, lost: bool = False, corrupted: bool = False) -> None:
        record = serial_records.SerialRecord(self.time, link, side, wire, lost, corrupted)
        self._write(SERIAL_INTERFACE, serial_records.pack(record))


def flip(wire: bytes, index: int) -> bytes:
    """``wire`` with one bit of byte ``index`` flipped: a bit error on the line."""
    return wire[:index] + bytes((wire[index] ^ 0x10,)) + wire[index + 1 :]


def record_traffic(rec: Recorder, caterpillar: CompiledProgram, counters: CompiledProgram) -> None:
    """A caterpillar and a second program on one CAN bus and two serial links, with every
    kind of frame and the ways a frame goes wrong."""
    cat = FrameCodec(caterpillar.vocabulary, 4)
    cnt = FrameCodec(counters.vocabulary, 4)
    long_path = tuple((FRONT, BACK) for _ in range(10))  # 12 bytes and a check: two frames
    # CAN link 5: the caterpillar's head (side 0) and its neighbour (side 1)
    rec.can(cat.encode(BACK, Hello(program_digest(caterpillar.image))), 5, 0)
    rec.can(cat.encode(BACK, Hormone("X", ("A",))), 5, 0)
    rec.can(cat.encode(FRONT, KeepAlive(7)), 5, 1)
    assert rec.can(cat.encode(BACK, Hormone("X", ("B",), long_path)), 5, 0) == 2
    rec.can(cat.encode(FRONT, Hormone("X", ("D",), ((BACK, FRONT), (LEFT, RIGHT)), (BACK, RIGHT))), 5, 1)
    rec.can(cat.encode(FRONT, Hormone("X", ("C",), (), ())), 5, 1)  # routed, nothing left to go
    # a three-segment hormone whose middle segment the bus lost
    parts = segment(cat.encode(BACK, Hormone("X", ("A",), ((FRONT, BACK),) * 20)), 5, 0)
    assert [parse_arbitration_id(p.arbitration_id).segment for p in parts] == [FIRST, 2, LAST]
    rec.can_raw(parts[0].arbitration_id, parts[0].data)
    rec.can_raw(parts[2].arbitration_id, parts[2].data)
    # CAN link 9: a module of the second program, named by its Hello
    rec.can(cnt.encode(LEFT, Hello(program_digest(counters.image))), 9, 1)
    rec.can(cnt.encode(LEFT, Hormone("GROW", (-5,))), 9, 1)
    rec.can(cnt.encode(LEFT, Hormone("GROW", (2**31 - 1,))), 9, 1)
    assert rec.can(cnt.encode(LEFT, Hormone("W", ("B", -(2**31), "A"), ((RIGHT, LEFT),))), 9, 1) == 2
    rec.can(cnt.encode(LEFT, Hormone("LTS", (), ((FRONT, BACK),), (RIGHT,))), 9, 1)
    # CAN link 11: a Hello of a program the capture does not carry; 11-bit frames are not dh2rt's
    rec.can(cat.encode(RIGHT, Hello(bytes.fromhex("abcdef012345"))), 11, 0)
    rec.can(cat.encode(RIGHT, Hormone("X", ("C",))), 11, 0)
    rec.can_raw(0x123, b"\x40\x00\x00", extended=False)
    # serial link 3: the caterpillar over infrared, with a lost and two corrupted frames
    rec.serial(encode_serial(cat.encode(BACK, Hello(program_digest(caterpillar.image)))), 3, 0)
    hormone = encode_serial(cat.encode(BACK, Hormone("X", ("C",), ((BACK, FRONT),))))
    rec.serial(hormone, 3, 0)
    rec.serial(hormone, 3, 0, lost=True)
    rec.serial(flip(hormone, 1), 3, 0, corrupted=True)  # a bit error in the header: fails the CRC
    rec.serial(hormone[:4] + b"\x00" + hormone[5:], 3, 0, corrupted=True)  # a zero inside: bad COBS
    rec.serial(encode_serial(cat.encode(FRONT, KeepAlive(200))), 3, 1)
    rec.serial(encode_serial(cat.encode(FRONT, Hormone("X", ("B",), (), (BACK, BACK)))), 3, 1)
    # frames that pass the CRC and still do not decode: the codec's own errors
    rec.serial(encode_serial(b"\x42\x00"), 3, 1)  # wire version 1 (2 is the transfer family: dump reads it)
    rec.serial(encode_serial(bytes((HEADER | 1, 0, 7, 0))), 3, 1)  # hormone index 7
    rec.serial(encode_serial(cat.encode(FRONT, Hormone("X", ("B",))) + b"\x99"), 3, 1)  # trailing byte
    # serial link 4: the second program
    rec.serial(encode_serial(cnt.encode(RIGHT, Hello(program_digest(counters.image)))), 4, 1)
    rec.serial(encode_serial(cnt.encode(RIGHT, Hormone("W", ("A", 300, "B")))), 4, 1, lost=True)


@pytest.fixture(scope="module")
def capture(programs: tuple[CompiledProgram, CompiledProgram], tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("wireshark") / "robot.pcapng"
    rec = Recorder(path, programs)
    try:
        record_traffic(rec, *programs)
    finally:
        rec.writer.close()
    return path


def dump_hops(capture: Path) -> list[Hop]:
    return list(open_capture(capture).hops())


def dump_line(hop: Hop, capture: Path) -> str:
    """The line ``dh2rt dump`` prints for ``hop``, without its time."""
    line = hop.describe(open_capture(capture).program.profile)
    assert line[17:19] == "  ", line
    return line[19:]


# -- the dissector against dump ----------------------------------------------------------


def test_the_dissector_shows_every_frame_as_dump_does(tshark: str, capture: Path, tmp_path: Path) -> None:
    script = tmp_path / "dh2rt.lua"
    assert main(["--capture", str(capture), "-o", str(script)]) == 0
    rows = run_tshark(tshark, script, capture, tmp_path / "home")
    hops = dump_hops(capture)
    assert len(rows) == len(hops) == 30
    kinds = {h.kind for h in hops}
    assert kinds == {"hello", "hormone", "routed", "keepalive", "segment", "error"}
    not_ours = [int(row[0]) for row in rows if row[1] == ""]
    assert not_ours == [18]  # the 11-bit frame, which dump marks as not dh2rt's
    assert hops[17].kind == "error" and "11-bit" in (hops[17].error or "")
    for row, hop in zip(rows, hops, strict=True):
        if int(row[0]) in not_ours:
            continue
        number, medium, link, side, kind, text, info = row
        shown = (medium, int(link), int(side), kind, text)
        assert shown == (hop.medium, hop.link, hop.side, hop.kind, hop.text), number
        assert info == dump_line(hop, capture), number
    # two passes (as Wireshark's GUI, which dissects a frame again when it is clicked) show the same
    assert run_tshark(tshark, script, capture, tmp_path / "home", "-2") == rows


def test_what_the_capture_shows(tshark: str, capture: Path, tmp_path: Path) -> None:
    """A few of the lines in full: names from the right program, segments reassembled."""
    script = tmp_path / "dh2rt.lua"
    assert main(["--capture", str(capture), "-o", str(script)]) == 0
    info = {int(row[0]): row[-1] for row in run_tshark(tshark, script, capture, tmp_path / "home")}
    assert info[2] == "link    5 side 0  hormone   X(A) via back"
    assert info[4] == "link    5 side 0  segment   #0"
    assert info[5].startswith("link    5 side 0  hormone   X(B) (reassembled) via back  path front>back front>back")
    assert info[6] == "link    5 side 1  routed    X(D) via front  path back>front left>right  route back right"
    assert info[9] == "link    5 side 0  error       !! segment 2 out of order: lost"
    assert info[12] == "link    9 side 1  hormone   GROW(2147483647) via left"
    assert info[14] == "link    9 side 1  hormone   W(B, -2147483648, A) (reassembled) via left  path right>left"
    assert info[16].endswith("hello     abcdef012345 (a program this capture does not carry) via right")
    assert info[22] == "ir      3 side 0  error       !! corrupted on the link: serial frame failed its CRC"
    assert info[30] == "ir      4 side 1  hormone   W(A, 300, B) via right  !! lost on the link (never delivered)"


def test_the_generic_dissector_shows_indices(tshark: str, capture: Path, tmp_path: Path) -> None:
    """The committed file knows no program: a hormone is #INDEX and its argument bytes; all
    else (kinds, links, sides, paths, routes) as dump shows it."""
    rows = run_tshark(tshark, COMMITTED, capture, tmp_path / "home")
    hops = dump_hops(capture)
    generic = re.compile(r"#\d+\((0x[0-9a-f]+)?\)")
    compared = 0
    for row, hop in zip(rows, hops, strict=True):
        if hop.kind not in ("hormone", "routed", "keepalive", "segment"):
            continue
        _, medium, link, side, kind, text, info = row
        assert (medium, int(link), int(side), kind) == (hop.medium, hop.link, hop.side, hop.kind)
        expected = dump_line(hop, capture)
        if hop.hormone is not None:
            content = text.removesuffix(" (reassembled)")
            assert generic.fullmatch(content), text
            expected = expected.replace(hop.hormone.content(), content, 1)
        assert info == expected
        compared += 1
    assert compared >= 15
    assert rows[1][5] == "#0(0x00)" and rows[10][5] == "#0(0x09)"  # X(A); GROW(-5) zig-zags to 9


def random_frame(rng: random.Random, codec: FrameCodec) -> bytes:
    """A frame of the second program, valid or with one byte changed, cut or added."""
    args: dict[str, tuple[str | int, ...]] = {
        "GROW": (rng.randint(-(2**31), 2**31 - 1),),
        "W": (rng.choice("AB"), rng.choice((0, -1, 63, -64, 8191, rng.randint(-(2**31), 2**31 - 1))), rng.choice("AB")),
        "LTS": (),
    }
    name = rng.choice(sorted(args))
    path = tuple((rng.randint(1, 4), rng.randint(1, 4)) for _ in range(rng.choice((0, 1, 2, 5, 13))))
    route = rng.choice((None, (), tuple(rng.randint(1, 4) for _ in range(rng.randint(1, 6)))))
    frame = codec.encode(rng.randint(1, 4), Hormone(name, args[name], path, route))
    damage = rng.random()
    if damage < 0.2:
        at = rng.randrange(len(frame))
        frame = frame[:at] + bytes((rng.randrange(256) if at else HEADER | rng.randrange(64),)) + frame[at + 1 :]
    elif damage < 0.3:
        frame = frame[: rng.randrange(1, len(frame))]
    elif damage < 0.4:
        frame += bytes((rng.randrange(256),))
    return frame


def test_random_frames_show_as_dump_does(
    tshark: str, programs: tuple[CompiledProgram, CompiledProgram], tmp_path: Path
) -> None:
    """Frames of every shape, and broken in every way, read as dump reads them: the same
    hormones, the same reassembly, the same errors."""
    rng = random.Random(12)
    codec = FrameCodec(programs[1].vocabulary, 4)
    path = tmp_path / "random.pcapng"
    rec = Recorder(path, (programs[1], programs[0]))  # the second program names them by default
    try:
        for _ in range(300):
            frame = random_frame(rng, codec)
            link, side = rng.randrange(3), rng.randrange(2)
            if rng.random() < 0.5:
                rec.can(frame, link, side)
            else:
                rec.serial(encode_serial(frame), link, side, lost=rng.random() < 0.1)
    finally:
        rec.writer.close()
    script = tmp_path / "dh2rt.lua"
    assert main(["--capture", str(path), "-o", str(script)]) == 0
    rows = run_tshark(tshark, script, path, tmp_path / "home")
    hops = dump_hops(path)
    assert [row[-1] for row in rows] == [dump_line(hop, path) for hop in hops]
    kinds = [hop.kind for hop in hops]
    assert min(kinds.count(k) for k in ("hormone", "routed", "segment", "error")) >= 20, kinds


def test_management_frames_and_refused_trains_show_as_dump_does(
    tshark: str, programs: tuple[CompiledProgram, CompiledProgram], tmp_path: Path
) -> None:
    """Link negotiation's management frames (valid and not), segment trains spliced or cut,
    and an over-long integer: the dissector reads each as dump does."""
    cnt = FrameCodec(programs[1].vocabulary, 4)
    path = tmp_path / "management.pcapng"
    rec = Recorder(path, (programs[1],))
    try:
        for op, link, tag in ((BusOp.CLAIM, 17, 0x1234), (BusOp.HOLD, 262142, 0xFFFFFFFF), (BusOp.RELEASE, 1, 7)):
            rec.can_raw(MANAGEMENT_ID, encode_bus(BusMessage(op, link, tag)))
        for garbage in (
            b"\x01\x00\x00",
            bytes((9, 0, 0, 17, 0, 0, 0, 1)),
            bytes((1, 0, 0, 0, 0, 0, 0, 1)),
            bytes((3, 0, 0, 17, 0, 0, 0, 0)),
            b"",
        ):
            rec.can_raw(MANAGEMENT_ID, garbage)
        a = cnt.encode(LEFT, Hormone("W", ("A", 100, "B"), ((RIGHT, LEFT),) * 3))
        b = cnt.encode(LEFT, Hormone("W", ("B", -700, "A"), ((LEFT, RIGHT),) * 3))
        restarted = [segment(p, 9, 1) for p in (a, b)]  # both trains tag 0: the check refuses the splice
        sender = Segmenter()
        trains = [sender.segment(p, 9, 1) for p in (a, b)]  # tags 0 and 1: the seq tells them apart
        for frame in (restarted[0][0], restarted[1][1], trains[0][0], trains[1][1], *trains[1]):
            rec.can_raw(frame.arbitration_id, frame.data)
        rec.can_raw(make_arbitration_id(0, 0, 0, 9, 1), bytes((HEADER | LEFT, 0, 0, 0x8A, 0x00)))  # GROW(5), padded
        rec.can_raw(make_arbitration_id(0, 0, 0, 9, 1), cnt.encode(LEFT, Hormone("GROW", (5,))))
    finally:
        rec.writer.close()
    script = tmp_path / "dh2rt.lua"
    assert main(["--capture", str(path), "-o", str(script)]) == 0
    hops = dump_hops(path)
    # the generic dissector (no program) reads all but the hormones' contents alike: the first 13
    generic = run_tshark(tshark, COMMITTED, path, tmp_path / "home")
    for rows, compared in ((run_tshark(tshark, script, path, tmp_path / "home"), 16), (generic, 13)):
        assert len(rows) == len(hops) == 16
        for row, hop in zip(rows[:compared], hops, strict=False):
            number, medium, link_id, side, kind, text, line = row
            link_and_side = ("" if hop.link is None else str(hop.link), "" if hop.side is None else str(hop.side))
            assert (medium, (link_id, side), kind, text) == ("can", link_and_side, hop.kind, hop.text), number
            assert line == dump_line(hop, path), number
    info = [row[-1] for row in run_tshark(tshark, script, path, tmp_path / "home")]
    assert info[:3] == [
        "link   17 side -  link      CLAIM tag 00001234",
        "link 262142 side -  link      HOLD tag ffffffff",
        "link    1 side -  link      RELEASE tag 00000007",
    ]
    assert info[3] == "link    ? side ?  error       !! link negotiation: management frame of 3 bytes; it must be 8"
    assert info[4].endswith("!! link negotiation: management op 9 is unknown")
    assert info[5].endswith("!! link negotiation: management frame names link id 0, outside 1..262142")
    assert info[6].endswith("!! link negotiation: management frame with tag 0 (no pair has it)")
    assert info[7] == "link    ? side ?  error       !! link negotiation: management frame of 0 bytes; it must be 8"
    assert info[8] == info[10] == "link    9 side 1  segment   #0"
    assert info[9] == "link    9 side 1  error       !! segment 1: " + REFUSED
    assert REFUSED == "train refused: its check fails (spliced from two hormones, or a piece lost)"
    assert info[11] == "link    9 side 1  error       !! segment 2 out of order: lost"
    assert info[12] == "link    9 side 1  segment   #1"
    assert (
        info[13]
        == "link    9 side 1  hormone   W(B, -700, A) (reassembled) via left  path left>right left>right left>right"
    )
    assert info[14] == "link    9 side 1  error       !! varint not in its shortest form"
    assert info[15] == "link    9 side 1  hormone   GROW(5) via left"


# -- transfer frames (flashing) ----------------------------------------------------------

IMAGE = bytes.fromhex("1a2b3c4d5e6f7a8b")
#: A message of every type, flags and texts set and not.
TRANSFER_MESSAGES: list[transfer.Message] = [
    transfer.Offer(2, IMAGE, 1843, 80, 12, path=((FRONT, FRONT), (BACK, FRONT))),
    transfer.Offer(3, IMAGE, 100, 50, 2, True),
    transfer.Request(IMAGE, 7, 8),
    transfer.Request(IMAGE, 0, 1, True),
    transfer.Segment(0x1234, 12, bytes(80)),
    transfer.Ack(0x1234, 13, 0x0005),
    transfer.Decline(IMAGE, transfer.DeclineReason.NEWER, 4),
    transfer.Cancel(IMAGE, "bad-signature"),
    transfer.Commit(IMAGE, 105_900, 2),
    transfer.Commit(IMAGE, 0, 0),
    transfer.CommitAck(IMAGE),
    transfer.Report(
        0x1A2B,
        3,
        transfer.Outcome.REFUSED,
        1,
        1,
        ((BACK, FRONT),),
        "bad-signature",
        "sign\u00e9 par une autre cl\u00e9",
    ),
    transfer.Report(0x1A2B, 4, transfer.Outcome.CONFIRMED, 2, 2, ((BACK, FRONT), (LEFT, RIGHT))),
    transfer.ReportAck(4),
]


def broken_transfer_frames() -> list[bytes]:
    """Transfer frames the codec refuses, each for another reason (and one it takes, sent
    through a connector CONRO does not have)."""
    commit = transfer.encode(BACK, transfer.Commit(IMAGE, 0, 0))
    offer = transfer.encode(BACK, transfer.Offer(2, IMAGE, 1843, 80, 12, path=((FRONT, BACK),)))
    request = transfer.encode(BACK, transfer.Request(IMAGE, 7, 8))
    report = transfer.encode(BACK, transfer.Report(1, 2, transfer.Outcome.STAGED, 1, 1, ((BACK, FRONT),), "ok", "fine"))
    segment_frame = transfer.encode(BACK, transfer.Segment(1, 2, b"\x01"))
    return [
        commit[:1] + b"\x63" + commit[2:],  # an unknown type
        commit + b"\x00",  # a trailing byte
        commit[:1],  # no type
        bytes((commit[0] & 0xF0,)) + commit[1:],  # sender connector 0
        bytes((commit[0] ^ 0x30,)) + commit[1:],  # the class of another type
        offer[:9],  # cut short in the fixed fields
        offer[:-1],  # cut short in the path
        offer[:20] + b"\x00\x64" + offer[22:],  # 100 segments held of 24
        offer[:-1] + b"\x10",  # a path hop naming connector 0
        offer[:-2] + b"\x41" + offer[-1:],  # a path of 65 hops
        offer[:14] + bytes(4) + offer[18:],  # an image of 0 bytes
        offer[:-3] + b"\x02" + offer[-2:],  # unknown flags
        request[:-2] + b"\x00" + request[-1:],  # window 0
        transfer.encode(BACK, transfer.Decline(IMAGE, transfer.DeclineReason.HAVE, 1))[:10]
        + b"\x09"
        + bytes(4),  # unknown reason
        report[:6] + b"\x63" + report[7:],  # unknown outcome
        report[:11] + b"\x02" + report[12:],  # two hops left of a one-hop path
        report[:15] + b"\xff" + report[16:],  # a verdict that is not ASCII
        report[:14] + b"\xc8" + report[15:],  # a verdict of 200 bytes
        report[:-4] + b"\xc3\x28" + report[-2:],  # a reason that is not UTF-8
        segment_frame[:-1],  # a segment without data
        transfer.encode(9, transfer.CommitAck(IMAGE)),  # through connector 9: no name in CONRO
    ]


def transfer_capture(path: Path, programs: tuple[CompiledProgram, ...]) -> None:
    """Every transfer message on CAN (segmented when long) and on a serial link, then the
    broken ones on both."""
    rec = Recorder(path, programs)
    try:
        frames = [transfer.encode(BACK, m) for m in TRANSFER_MESSAGES]
        for frame in frames:
            rec.can(frame, 5, 0)
            rec.serial(encode_serial(frame), 3, 1)
        for frame in broken_transfer_frames():
            rec.can(frame, 7, 1)
            rec.serial(encode_serial(frame), 4, 0)
    finally:
        rec.writer.close()


TRANSFER_FIELDS = (*FIELDS, "dh2rt.transfer.message", "_ws.expert.message")


def test_transfer_frames_show_as_dump_does(
    tshark: str, programs: tuple[CompiledProgram, CompiledProgram], tmp_path: Path
) -> None:
    """Every transfer message, and frames broken every way the codec refuses, on CAN and on
    a serial link: the generic dissector (transfer frames name no program) shows each as
    dump does, a broken one as malformed (expert info) with dump's reason."""
    path = tmp_path / "transfer.pcapng"
    transfer_capture(path, programs)
    rows = run_tshark(tshark, COMMITTED, path, tmp_path / "home", fields=TRANSFER_FIELDS)
    hops = dump_hops(path)
    assert len(rows) == len(hops)
    shown = [hop for hop in hops if hop.kind != "segment"]
    assert [hop.kind for hop in shown].count("transfer") == 2 * len(TRANSFER_MESSAGES) + 2
    assert [hop.kind for hop in shown].count("error") == 2 * (len(broken_transfer_frames()) - 1)
    for row, hop in zip(rows, hops, strict=True):
        number, medium, link, side, kind, text, info, message, expert = row
        assert (medium, int(link), int(side), kind, text) == (hop.medium, hop.link, hop.side, hop.kind, hop.text)
        assert info == dump_line(hop, path), number
        assert message == (hop.text.split()[0] if hop.kind == "transfer" else message), number
        if hop.kind == "error":
            assert expert == hop.error, number  # malformed: expert info with dump's reason
        else:
            assert expert == "", number
    lines = [row[6] for row in rows if row[4] != "segment"]
    assert lines[0] == (
        "link    5 side 0  transfer  OFFER v2 1a2b3c4d5e6f7a8b 1843 bytes, segments of 80, held 12,"
        " path front>front back>front (reassembled) via back"
    )
    assert lines[3] == (
        "ir      3 side 1  transfer  OFFER v3 1a2b3c4d5e6f7a8b 100 bytes, segments of 50, held 2, running,"
        " path (entry point) via back"
    )
    assert lines[17] == "ir      3 side 1  transfer  COMMIT 1a2b3c4d5e6f7a8b in 105.9 ms (hops 2) via back"
    errors = [line for line in lines if " error " in line]
    assert errors[0] == "link    7 side 1  error       !! transfer frame: unknown message type 99"
    assert errors[-1] == "ir      4 side 0  error       !! transfer frame SEGMENT: 0 data bytes, outside 1..506"


def test_transfer_fields_name_what_dump_shows(
    tshark: str, programs: tuple[CompiledProgram, CompiledProgram], tmp_path: Path
) -> None:
    """Each field of a transfer message is a dh2rt.transfer.NAME field, NAME as dump's table
    names it: filter on them, add them as columns."""
    path = tmp_path / "transfer.pcapng"
    transfer_capture(path, programs)
    fields = ("dh2rt.transfer.message", "dh2rt.transfer.image", "dh2rt.transfer.version", "dh2rt.transfer.path",
              "dh2rt.transfer.running", "dh2rt.transfer.reason", "dh2rt.transfer.remaining_us")  # fmt: skip
    command = ["-Y", 'dh2rt.medium == "serial" && dh2rt.kind == "transfer"']
    rows = run_tshark(tshark, COMMITTED, path, tmp_path / "home", *command, fields=fields)
    assert len(rows) == len(TRANSFER_MESSAGES) + 1
    assert rows[0][:5] == ["OFFER", IMAGE.hex(), "2", "front>front back>front", "0"]
    assert rows[1][4] == "1"  # tshark prints a bool as 0 or 1
    assert rows[6][:3] == ["DECLINE", IMAGE.hex(), "4"] and rows[6][5] == "newer"
    assert rows[8][6] == "105900"
    assert rows[11][3:6] == ["back>front", "", "sign\u00e9 par une autre cl\u00e9"]
    names = {f.name for view in transfer_view.VIEWS for f in view.fields}
    assert {"segment_size", "held", "next", "window", "sack", "outcome", "left", "verdict", "data"} <= names


@pytest.mark.realtime  # modules run in real time
def test_a_flash_in_the_loop_shows_as_dump_does(tshark: str, tmp_path: Path) -> None:
    """A real flash (four modules in the loop, m0 rolling out an image): the dissector
    written for its capture shows every frame as dump does, every message type among them."""
    path = tmp_path / "flash.pcapng"
    assert capture_a_flash(tmp_path, path) == 0
    script = tmp_path / "dh2rt.lua"
    assert main(["--capture", str(path), "-o", str(script)]) == 0
    rows = run_tshark(tshark, script, path, tmp_path / "home", fields=TRANSFER_FIELDS)
    hops = dump_hops(path)
    assert len(rows) == len(hops)
    for row, hop in zip(rows, hops, strict=True):
        number, medium, link, side, kind, text, info, _message, expert = row
        link_and_side = ("" if hop.link is None else str(hop.link), "" if hop.side is None else str(hop.side))
        assert (medium, (link, side), kind, text) == (hop.medium, link_and_side, hop.kind, hop.text), number
        assert expert == (hop.error or ""), number
        assert info == dump_line(hop, path), number
    messages = {row[7] for row in rows if row[4] == "transfer"}
    assert messages >= {"OFFER", "REQUEST", "SEGMENT", "ACK", "COMMIT", "COMMIT_ACK", "REPORT", "REPORT_ACK"}
    assert not [hop for hop in hops if hop.kind == "error"]
    assert run_tshark(tshark, script, path, tmp_path / "home", "-2", fields=TRANSFER_FIELDS) == rows


# -- the layout check --------------------------------------------------------------------


def test_the_committed_dissector_is_what_the_codec_gives() -> None:
    assert COMMITTED.read_text(encoding="utf-8") == template()
    assert dissector(base=template()) == template()
    assert main(["--check"]) == 0


def test_a_codec_whose_layout_moved_fails_the_check(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def moved(kind: int, segment: int, seq: int, link_id: int, side: int) -> int:
        return (side << 28) | (kind << 26) | (segment << 24) | (seq << 18) | link_id

    monkeypatch.setattr(can_frames, "make_arbitration_id", moved)
    assert main(["--check"]) == 1
    assert "dh2rt.lua differs" in capsys.readouterr().err


def test_the_layout_reads_what_the_codec_writes() -> None:
    fields = layout.can_id_fields()
    for values in ((3, 2, 63, 0x3FFFF, 1), (1, 0, 5, 12345, 0), (0, 3, 0, 1, 1)):
        can_id = make_arbitration_id(*values)
        assert tuple(layout.extract(can_id, fields[n]) for n in ("kind", "segment", "seq", "link", "side")) == values
        assert tuple(parse_arbitration_id(can_id)) == values
    header = layout.header_fields()
    codec = FrameCodec(compile_source(COUNTERS).vocabulary, 4)
    for sender, frame, kind in (
        (LEFT, Hormone("LTS"), FrameKind.HORMONE),
        (RIGHT, Hormone("LTS", route=(FRONT,)), FrameKind.ROUTED),
        (FRONT, KeepAlive(3), FrameKind.KEEPALIVE),
    ):
        head = codec.encode(sender, frame)[0]
        assert [layout.extract(head, header[n]) for n in ("version", "kind", "sender")] == [WIRE_VERSION, kind, sender]


def test_a_transfer_table_the_codec_does_not_match_fails(monkeypatch: pytest.MonkeyPatch) -> None:
    """Dump's table of transfer messages is checked against the codec: fields in another
    order, or a field missing, stop the generator."""
    ack = next(v for v in transfer_view.VIEWS if v.message is transfer.Ack)
    swapped = dataclasses.replace(ack, fields=(ack.fields[1], ack.fields[0], ack.fields[2]))
    for views in (
        tuple(swapped if v is ack else v for v in transfer_view.VIEWS),
        tuple(dataclasses.replace(v, fields=v.fields[:-1]) if v is ack else v for v in transfer_view.VIEWS),
        tuple(v for v in transfer_view.VIEWS if v is not ack),
    ):
        monkeypatch.setattr(layout, "VIEWS", views)
        with pytest.raises(layout.LayoutError):
            layout.transfer_layout()


def test_bit_fields_must_be_one_run() -> None:
    assert layout.bit_field(0b0111_0000) == {"shift": 4, "width": 3}
    for mask in (0, 0b1010):
        with pytest.raises(layout.LayoutError):
            layout.bit_field(mask)


# -- the generator -----------------------------------------------------------------------


def test_lua_literals() -> None:
    assert lua_string('a"b\\c\n') == '"a\\034b\\092c\\010"'
    assert lua_string("é") == '"\\195\\169"'
    assert lua({"x": [1, True], 0: "y"}) == '{ x = { 1, true }, [0] = "y" }'
    assert lua([]) == "{}"
    with pytest.raises(TypeError):
        lua(1.5)


def test_a_program_names_the_hormones(programs: tuple[CompiledProgram, CompiledProgram], tmp_path: Path) -> None:
    source = tmp_path / "counters.dh2"
    source.write_text(COUNTERS, encoding="utf-8")
    out = tmp_path / "counters.lua"
    assert main(["--program", str(source), "-o", str(out)]) == 0
    text = out.read_text(encoding="utf-8")
    digest = program_digest(programs[1].image).hex()
    assert f'name = "counters",\n        digest = "{digest}",' in text
    assert '{ name = "phase", domain = { "A", "B" } },\n' in text and '{ name = "n" },\n' in text
    assert '[2] = { name = "LTS", params = {} },' in text
    assert text.replace(_block(text), "") == template().replace(_block(template()), "")


def _block(text: str) -> str:
    return text[text.index("-- BEGIN GENERATED") : text.index("-- END GENERATED")]


def test_bad_input_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bare = tmp_path / "bare.pcapng"
    PcapngWriter(bare).close()
    assert main(["--capture", str(bare)]) == 2
    assert "carries no program image" in capsys.readouterr().err
    broken = tmp_path / "broken.dh2"
    broken.write_text("hormone X(\n", encoding="utf-8")
    assert main(["--program", str(broken)]) == 2
    assert "broken.dh2" in capsys.readouterr().err


# -- control frames (the operator's) --------------------------------------------------------

KEY_ID = bytes.fromhex("0011223344556677")
OTHER_DIGEST = bytes.fromhex("abcdef012345")  # a program no capture here carries
STATUS = operator.ModuleStatus(OTHER_DIGEST, 1, True, 300, 70_000, (2, 0, 0, 0), (1,), (-5, 1 << 40), (1, 0, 2))
CONTROL_MESSAGES: list[operator.Message] = [
    operator.Signed(operator.Inject(OTHER_DIGEST, b"\x02\x05", ((BACK, FRONT), (LEFT, FRONT))), 1, KEY_ID, bytes(64)),
    operator.Signed(operator.Pause(), 1_764_288_000_123_456, KEY_ID, bytes(64), 3),
    operator.Signed(operator.Resume(), (1 << 64) - 1, KEY_ID, bytes(64)),
    operator.Signed(operator.StateRequest(((BACK, FRONT),)), 9, KEY_ID, bytes(64), 1),
    operator.StateReply(9, 1, ((BACK, FRONT),), STATUS),
    operator.Refused(10, 0, (), operator.RefusalReason.REPLAYED),
    operator.Signed(operator.Watch(500, 3), 11, KEY_ID, bytes(64)),
    operator.Signed(operator.Watch(65535), 12, KEY_ID, bytes(64)),
    operator.Watched(11, 1 << 40, LEFT, bytes.fromhex("c100000a")),
    operator.Watched(11, 7, 0, bytes.fromhex("c1")),
]


def broken_control_frames() -> list[bytes]:
    """Control frames the codec refuses, each for another reason."""
    pause = operator.encode(BACK, CONTROL_MESSAGES[1])
    reply = operator.encode(BACK, CONTROL_MESSAGES[4])
    refused = operator.encode(BACK, CONTROL_MESSAGES[5])
    return [
        bytes((0x22, 70)),  # the reserved docking range
        bytes((0x22, 6)),  # an unknown type
        pause + b"\x00",  # a trailing byte
        pause[:-1],  # cut short in the signature
        bytes((pause[0] ^ 0x30,)) + pause[1:],  # the class of another type
        refused[:-1] + b"\x09",  # an unknown reason
        refused[:10] + b"\x01" + refused[11:],  # a hop left of a 0-hop path
        reply[:20] + b"\x02" + reply[21:],  # unknown flags
        reply[:21] + b"\x80\x00" + reply[23:],  # LocalTimer not in its shortest form (300 = ac 02)
        operator.encode(BACK, CONTROL_MESSAGES[7])[:19] + b"\x00\x00\x00" + bytes(64),  # a watch of 0 cycles
        operator.encode(BACK, CONTROL_MESSAGES[9])[:-2] + b"\x00",  # an empty frame
        operator.encode(BACK, CONTROL_MESSAGES[8]) + b"\x01",  # a trailing byte
    ]


def control_family_as_dump(
    tshark: str,
    programs: tuple[CompiledProgram, CompiledProgram],
    tmp_path: Path,
    good: list[bytes],
    broken: list[bytes],
) -> tuple[list[list[str]], list[Hop]]:
    """Control-family frames, each on CAN (segment trains) and on a serial link, through the
    dissector and through dump: every row as dump shows it; the rows and dump's hops."""
    path = tmp_path / "control.pcapng"
    rec = Recorder(path, programs)
    try:
        for frame in good + broken:
            rec.can(frame, 5, 0)
            rec.serial(encode_serial(frame), 3, 1)
    finally:
        rec.writer.close()
    rows = run_tshark(tshark, COMMITTED, path, tmp_path / "home", fields=(*FIELDS, "_ws.expert.message"))
    hops = dump_hops(path)
    assert len(rows) == len(hops)
    shown = [hop for hop in hops if hop.kind != "segment"]
    assert [hop.kind for hop in shown].count("control") == 2 * len(good)
    assert [hop.kind for hop in shown].count("error") == 2 * len(broken)
    for row, hop in zip(rows, hops, strict=True):
        number, medium, link, side, kind, text, info, expert = row
        assert (medium, int(link), int(side), kind, text) == (hop.medium, hop.link, hop.side, hop.kind, hop.text)
        assert info == dump_line(hop, path), number
        assert expert == (hop.error if hop.kind == "error" else ""), number
    return rows, shown


def test_control_frames_show_as_dump_does(
    tshark: str, programs: tuple[CompiledProgram, CompiledProgram], tmp_path: Path
) -> None:
    """Every control message and frames broken as the codec refuses them, on CAN (signed
    commands are segment trains) and on a serial link: the dissector shows each as dump does."""
    frames = [operator.encode(BACK, m) for m in CONTROL_MESSAGES]
    rows, _shown = control_family_as_dump(tshark, programs, tmp_path, frames, broken_control_frames())
    lines = [row[6] for row in rows if row[4] == "control"]
    assert lines[1] == (
        "ir      3 side 1  control   INJECT #1 key 0011223344556677 hops 0, hormone 0205 of program abcdef012345"
        " at back>front left>front via back"
    )


# -- motion frames (the docking chain's) -----------------------------------------------------

MOTION_ROUTE = ((BACK, FRONT), (LEFT, FRONT))
MOTION_MESSAGES: list[motion.MotionMessage] = [
    motion.Ask(7, 0, MOTION_ROUTE, 1),
    motion.Angles(7, 0, MOTION_ROUTE, 3, (12.5, -40.0), (2, 0, 1, 0), 2),
    motion.Angles(7, 1, MOTION_ROUTE[:1], 65535, (327.67, -327.68, 0.01, -0.07), (), 0),
    motion.Targets(7, 65535, MOTION_ROUTE, ((0, 30.0), (1, -7.25)), 0),
    motion.Targets(7, 3, MOTION_ROUTE, ((1, 0.0), (7, 1.5)), 2),
    motion.End(65535, 4, MOTION_ROUTE, 2),
    motion.SetOff(7, 5, MOTION_ROUTE, 300, 2, (300, 12, 65535), (9,), 2),
    motion.SetOff(7, 6, MOTION_ROUTE[:1], 0, 15, (0,), (), 0),
]


def broken_motion_frames() -> list[bytes]:
    """Motion frames the codec refuses, each for another reason."""
    targets = motion.encode(BACK, MOTION_MESSAGES[3])
    angles = motion.encode(BACK, MOTION_MESSAGES[1])
    set_off = motion.encode(BACK, MOTION_MESSAGES[7])  # connector at byte 11, body 12..14, others 15
    return [
        bytes((0x22, 100)),  # a type of the range not yet defined
        bytes((0x20, 64)) + targets[2:],  # sender connector 0
        bytes((targets[0] ^ 0x30,)) + targets[1:],  # another class
        targets[:6],  # cut short in the head
        targets[:7] + b"\x00",  # an empty route
        targets[:6] + b"\x03" + targets[7:],  # hops beyond the route
        targets[:7] + b"\x01\x10",  # a route hop names connector 0
        targets[:10] + b"\x00",  # no targets
        targets[:11] + targets[14:] + targets[11:14],  # DOFs not ascending
        targets[:-1],  # cut short in the targets
        angles[:12] + b"\x09",  # too many angles
        angles[:-7],  # cut short in the angles
        angles[:-5] + b"\x10" + bytes(16),  # too many links
        angles[:-1] + b"\x10",  # a link beyond connector 15
        angles[:-1],  # cut short in the links
        angles + b"\x00",  # a trailing byte
        set_off[:11] + b"\x00" + set_off[12:],  # target connector 0
        set_off[:12] + b"\x00\x00",  # no marker in body
        set_off[:12] + b"\x21" + bytes(66) + b"\x00",  # too many markers in body
        set_off[:15] + b"\x21" + bytes(66),  # too many markers in others
        set_off[:15] + b"\x01\x00\x00",  # a marker in body and in others
        set_off[:-1],  # cut short in the markers
    ]


def test_motion_frames_show_as_dump_does(
    tshark: str, programs: tuple[CompiledProgram, CompiledProgram], tmp_path: Path
) -> None:
    """Every motion message and frames broken as the codec refuses them, on CAN (segment
    trains) and on a serial link: the dissector shows each as dump does."""
    frames = [motion.encode(BACK, m) for m in MOTION_MESSAGES]
    rows, shown = control_family_as_dump(tshark, programs, tmp_path, frames, broken_motion_frames())
    assert len({hop.error for hop in shown if hop.error}) == len(broken_motion_frames())
    lines = [row[5] for row in rows if row[4] == "control"]
    angles = "DOF1 327.67, DOF2 -327.68, DOF3 0.01, DOF4 -0.07"
    assert f"ANGLES motion 7 #1 from back>front, left 0: module 65535, {angles}, links none" in lines
    set_off = "to module 300 connector 2, body 300,12,65535, others 9"
    assert f"SET_OFF motion 7 #5 to back>front left>front, hops 2: {set_off}" in lines
