"""The cycle marks of a loop run's capture: what replay needs beside the wire.

The frames on the links say what each module sent and, through the link emulator, what was
delivered to it; they do not say *at which of its cycles* a module took a frame in, what it
believed of its links then, nor its LocalTimer phase. A module's engine cannot be rebuilt
cycle by cycle without those. In the loop the launcher has them: every module reports each
cycle's record (the trace record of :mod:`dh2rt.records`), and the launcher's ``--capture``
keeps a small part of it beside the frames:

* a **cycle mark** per module per cycle: the module (index, name, life), its cycle number,
  ``t`` (its own clock when the cycle began), LocalTimer as the cycle began, the status it
  reported for the cycle (connector -> remote connector, as the record has it: at the
  cycle's end), how many hormones it took in at each connector
  (the count only: *which* hormones is the wire's: the next ones delivered to that
  connector, every link being first in, first out), the hormones injected over its control
  channel (not on any link) and the sensors as the cycle read them;
* a **link mark** per link: its id and the (module, connector) at each side, so that a link
  end of the capture is a module's connector (an emulated infrared link as the world made it;
  a bus link as both its modules logged they negotiated it);
* an **unlink mark** when a link marked before is undocked (a ``release``, a cut): its id and
  ends again. Frames only stop on the wire there; the mark says why and when (version 2; a
  version 1 file has none).

What a cycle mark does not hold is what replay recomputes and compares: the type (it follows
from the status, as the engine's table gives it), the actuators, the variables, the receptor
statuses, the hormones sent and which hormones came in.

A capture on a real robot has only the wire: no marks. Replay then says what it cannot know
(which cycle took what in, the timer phases) instead of guessing.

The marks are a file of their own beside the capture, ``CAPTURE.cycles.jsonl`` (JSON Lines:
a header ``{"format": "dh2rt-cycle-marks", "version": 2}``, then one mark a line, each with
``time``: the cycle's start on the capture's clock, the module's monotonic ``t`` moved to
the wall clock the link emulator stamps frames with, or when a link mark was written). The
capture file itself stays what was on the wire, as every reader of it (dump, Wireshark)
expects: the marks are the modules' reports, not frames.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dh2rt.errors import CaptureError
from dh2rt.output_paths import shown_path

SUFFIX = ".cycles.jsonl"
FORMAT = "dh2rt-cycle-marks"
VERSION = 2
#: The versions this dh2rt reads: version 1 had no unlink marks.
READS = (1, 2)


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


@dataclass(frozen=True, slots=True)
class UnlinkMark:
    """A link marked before undocked (released or cut) at ``time``; ``ends`` as its link mark's."""

    time: float
    link: int
    ends: tuple[tuple[int, int], tuple[int, int]]


Mark = LinkMark | UnlinkMark | CycleMark


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


def link_mark_json(link: int, ends: tuple[tuple[int, int], tuple[int, int]], *, docked: bool = True) -> dict[str, Any]:
    """A link mark (``docked``) or an unlink mark (not)."""
    return {"kind": "link" if docked else "unlink", "link": link, "ends": [list(ends[0]), list(ends[1])]}


def marks_path(capture: Path) -> Path:
    """Where the marks of ``capture`` are: beside it."""
    return capture.with_name(capture.name + SUFFIX)


def header() -> str:
    return json.dumps({"format": FORMAT, "version": VERSION}) + "\n"


def line(mark: Mapping[str, Any], when: float) -> str:
    """One mark as a line of the file, ``when`` its time on the capture's clock."""
    return json.dumps({"time": when, **mark}, separators=(",", ":")) + "\n"


def wall_time(monotonic_t: float) -> float:
    """A time on this machine's monotonic clock (the modules' ``t``) on the wall clock the
    link emulator stamps frames with."""
    return monotonic_t + (time.time() - time.monotonic())


def unpack(obj: Any, where: str) -> Mark:
    """One mark of the file; CaptureError naming ``where`` when it is not one."""
    try:
        when = float(obj["time"])
        if obj["kind"] in ("link", "unlink"):
            (m0, c0), (m1, c1) = obj["ends"]
            kind = LinkMark if obj["kind"] == "link" else UnlinkMark
            return kind(when, int(obj["link"]), ((int(m0), int(c0)), (int(m1), int(c1))))
        if obj["kind"] != "cycle":
            raise ValueError(f"kind {obj['kind']!r}")
        return CycleMark(
            when,
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
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise CaptureError(f"{where}: not a cycle mark ({type(exc).__name__}: {exc})") from None


def read_marks(capture: Path) -> Iterator[Mark]:
    """The marks kept beside ``capture``, in file order (none when there is no such file)."""
    path = marks_path(capture)
    try:
        fh = path.open(encoding="utf-8")
    except FileNotFoundError:
        return
    except OSError as exc:
        raise CaptureError(f"{shown_path(path)}: cannot be read ({exc.strerror or exc})") from None
    with fh:
        try:
            first = json.loads(fh.readline() or "null")
            if not isinstance(first, dict) or first.get("format") != FORMAT:
                raise ValueError(f"no {FORMAT} header")
            if first.get("version") not in READS:
                raise ValueError(f"version {first.get('version')}, this dh2rt reads {', '.join(map(str, READS))}")
        except (ValueError, UnicodeError) as exc:
            raise CaptureError(f"{path}:1: not a cycle marks file ({exc})") from None
        for number, text in enumerate(fh, start=2):
            try:
                obj = json.loads(text)
            except (ValueError, UnicodeError) as exc:
                raise CaptureError(f"{path}:{number}: not JSON ({exc})") from None
            yield unpack(obj, f"{path}:{number}")
