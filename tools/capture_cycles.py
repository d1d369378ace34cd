"""The cycle marks of a loop run's capture: what replay needs beside the wire.

The frames on the links say what each module sent and, through the link emulator, what was
delivered to it; they do not say *at which of its cycles* a module took a frame in, what it
believed of its links then, nor its LocalTimer phase. A module's engine cannot be rebuilt
cycle by cycle without those. In the loop the launcher has them: every module reports each
cycle's record (the trace record of :mod:`dh2rt.records`), and the launcher writes a small
part of it into the capture, beside the frames:

* a **cycle mark** per module per cycle: the module (index, name, life), its cycle number,
  ``t`` (its own clock when the cycle began), LocalTimer as the cycle began, the status it
  reported (connector -> remote connector), how many hormones it took in at each connector
  (the count only: *which* hormones is the wire's: the next ones delivered to that
  connector, every link being first in, first out), the hormones injected over its control
  channel (not on any link) and the sensors as the cycle read them;
* a **link mark** per emulated infrared link: its id and the (module, connector) at each
  side, so that a link end of the capture is a module's connector.

What a cycle mark does not hold is what replay recomputes and compares: the type (it follows
from the status, as the engine's table gives it), the actuators, the variables, the receptor
statuses, the hormones sent and which hormones came in.

A capture on a real robot has only the wire: no marks. Replay then says what it cannot know
(which cycle took what in, the timer phases) instead of guessing.

Marks are packets on a third pcapng interface, link type 148 (``LINKTYPE_USER1``, a link
type for private use, as 147 is for the serial links' frames): ``D2CY``, a version byte (1)
and the mark as compact JSON (ASCII). The packet's time is the cycle's start on the capture's
clock (the module's monotonic ``t`` moved to the wall clock the serial frames are stamped
with), or the moment the link mark was written. Readers of frames skip them
(:func:`tools.capture_reader.read_records`); :func:`read_marks` reads them. Only pcapng holds
marks (the other formats hold CAN frames only).
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dh2rt.errors import CaptureError
from tools.pcapng import LINKTYPE_USER1, PcapngReader

MAGIC = b"D2CY"
VERSION = 1


@dataclass(frozen=True, slots=True)
class LinkMark:
    """An emulated link: ``ends[side]`` is the (module, connector) at that side."""

    time: float
    link: int
    ends: tuple[tuple[int, int], tuple[int, int]]


@dataclass(frozen=True, slots=True)
class CycleMark:
    """One module's cycle as the capture keeps it (see the module docs); connectors are the
    profile's names, as in the trace, ``took`` only those that took something in."""

    time: float  # the cycle's start on the capture's clock
    module: int
    name: str
    life: int
    cycle: int
    t: float  # the module's own clock when the cycle began
    timer: int  # LocalTimer as the cycle began
    status: Mapping[str, str]
    took: Mapping[str, int]
    injected: tuple[str, ...]
    sensors: Mapping[str, int]


Mark = LinkMark | CycleMark


def cycle_mark_json(record: Mapping[str, Any]) -> dict[str, Any]:
    """The mark of one trace record (a module's cycle as it reported it)."""
    took: dict[str, int] = {}
    injected: list[str] = []
    for arrival in record.get("received", ()):
        if arrival.get("at") is None:
            injected.append(str(arrival["hormone"]))
        else:
            took[str(arrival["at"])] = took.get(str(arrival["at"]), 0) + 1
    mark: dict[str, Any] = {
        "kind": "cycle",
        "module": record["module"],
        "name": record["name"],
        "life": record.get("life", 0),
        "cycle": record["cycle"],
        "t": record["t"],
        "timer": record["timer"],
        "status": record["status"],
        "took": took,
    }
    if injected:
        mark["injected"] = injected
    if record.get("sensors"):
        mark["sensors"] = record["sensors"]
    return mark


def link_mark_json(link: int, ends: tuple[tuple[int, int], tuple[int, int]]) -> dict[str, Any]:
    return {"kind": "link", "link": link, "ends": [list(ends[0]), list(ends[1])]}


def pack(mark: Mapping[str, Any]) -> bytes:
    return MAGIC + bytes([VERSION]) + json.dumps(mark, separators=(",", ":")).encode("ascii")


def wall_time(monotonic_t: float) -> float:
    """A time on this machine's monotonic clock (the modules' ``t``) on the wall clock the
    link emulator stamps frames with."""
    return monotonic_t + (time.time() - time.monotonic())


def unpack(timestamp: float, data: bytes, where: str) -> Mark:
    """One mark packet; CaptureError naming ``where`` when it is not one."""
    if not data.startswith(MAGIC) or len(data) < 5:
        raise CaptureError(f"{where}: a packet of link type {LINKTYPE_USER1} that is not a dh2rt cycle mark")
    if data[4] != VERSION:
        raise CaptureError(f"{where}: cycle mark version {data[4]}, this dh2rt reads {VERSION}")
    try:
        obj = json.loads(data[5:].decode("ascii"))
        if obj["kind"] == "link":
            (m0, c0), (m1, c1) = obj["ends"]
            return LinkMark(timestamp, int(obj["link"]), ((int(m0), int(c0)), (int(m1), int(c1))))
        if obj["kind"] != "cycle":
            raise ValueError(f"kind {obj['kind']!r}")
        return CycleMark(
            timestamp,
            int(obj["module"]),
            str(obj["name"]),
            int(obj["life"]),
            int(obj["cycle"]),
            float(obj["t"]),
            int(obj["timer"]),
            {str(k): str(v) for k, v in obj["status"].items()},
            {str(k): int(v) for k, v in obj["took"].items()},
            tuple(str(h) for h in obj.get("injected", ())),
            {str(k): int(v) for k, v in obj.get("sensors", {}).items()},
        )
    except (ValueError, KeyError, TypeError, AttributeError, UnicodeError) as exc:
        raise CaptureError(f"{where}: a damaged cycle mark ({type(exc).__name__}: {exc})") from None


def read_marks(path: Path) -> Iterator[Mark]:
    """The marks of a capture, in file order (none in a file other than pcapng)."""
    from tools.capture_reader import open_capture_file

    if path.suffix.lower() != ".pcapng":
        return
    with open_capture_file(path) as fh:
        reader = PcapngReader(fh, path)
        reader.read_header()
        for packet in reader:
            if packet.linktype == LINKTYPE_USER1:
                yield unpack(packet.timestamp, packet.data, f"{path}: offset {packet.offset}")
