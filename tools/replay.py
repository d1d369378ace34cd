"""``dh2rt replay CAPTURE``: rebuild every module's engine cycle by cycle from a capture of a
loop run, and print each module's trace records as ``dh2rt run --trace`` writes them, or
stop at breakpoints.

The capture must have the modules' cycle marks beside it (:mod:`tools.capture_cycles`: the
launcher's ``--capture`` writes them; replay reads those of serial links); how each cycle is
rebuilt, and what replay says where the capture lacks something, is :mod:`tools.replay_rebuild`.

Breakpoints (``--break``, repeatable), checked after each rebuilt cycle, in the capture's
time order:

* ``hormone H``: a module took in (received or was injected) or sent ``H`` (a name, or a
  content ``X(A)``);
* ``receptor NAME fires``: a module ran the actions of receptor ``NAME``;
* ``type of MODULE changes``: ``MODULE`` (its name, ``m4``, or its index) now has another
  type than after its previous cycle.

At each, replay stops: it prints where (module, cycle, its clock) and the module's state
(type, LocalTimer, status, actuators, variables, sensors, receptor statuses, what it took in
and sent), then goes on to the next (``--first``: ends at the first). Without breakpoints it
prints the records (JSON Lines); ``--trace FILE`` writes them to a file in either case.
``--json`` prints one JSON summary instead: the stops, the notes, the counts.

Exit codes: 0 (whatever the notes say: a missing frame, a divergence), 2 bad input (not a
capture, no cycle marks in it, a ``--program`` whose digest no Hello of the capture names,
a breakpoint that names no hormone, receptor or module), 130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from dh2rt.cmdline import EXIT_OK, EXIT_USAGE, err
from dh2rt.errors import CaptureError, OptionError
from dh2rt.program import ACTIVE, PASSIVE, CompiledProgram
from dh2rt.wire.frame import program_digest
from tools.capture_cycles import CycleMark, marks_path, read_marks
from tools.reading import PROGRAM_HELP, Capture, interruptible, options_and_capture
from tools.replay_rebuild import Note, Rebuild, Step

_BREAK_FORMS = "'hormone H', 'receptor NAME fires' or 'type of MODULE changes'"


@dataclass(frozen=True, slots=True)
class Breakpoint:
    """``kind`` is hormone, receptor or type; ``what`` the hormone (name or content), the
    receptor's name or the module's index; ``text`` as the user wrote it."""

    kind: str
    what: str
    text: str

    def hit(self, step: Step) -> bool:
        if self.kind == "receptor":
            return self.what in step.fired
        if self.kind == "type":
            return (
                str(step.mark.module) == self.what
                and step.previous_type is not None
                and step.record["type"] != step.previous_type
            )
        hormones = [a.hormone for a in step.arrivals] + [e.hormone for e in step.sent]
        return any(self.what in (h.name, h.content()) for h in hormones)


def parse_break(text: str, capture: Capture, modules: dict[str, int]) -> Breakpoint:
    """A ``--break`` as written; OptionError naming it when it is none of the forms, or names
    what the program or the capture does not have."""
    words = text.split()
    if len(words) == 2 and words[0] == "hormone":
        return Breakpoint("hormone", capture.hormone(words[1], "--break hormone"), text)
    if len(words) == 3 and words[0] == "receptor" and words[2] == "fires":
        names = [r.name for r in capture.program.receptors]
        if words[1] not in names:
            raise OptionError(f"--break {text!r}: no receptor {words[1]} in the program (it has {', '.join(names)})")
        return Breakpoint("receptor", words[1], text)
    match = re.fullmatch(r"type of (\S+) changes", " ".join(words))
    if match:
        who = match.group(1)
        if who in modules:
            return Breakpoint("type", str(modules[who]), text)
        if who.isdigit() and int(who) in modules.values():
            return Breakpoint("type", who, text)
        known = ", ".join(sorted(modules, key=modules.__getitem__))
        raise OptionError(f"--break {text!r}: no module {who} in the capture (it has {known})")
    raise OptionError(f"--break {text!r}: a breakpoint is {_BREAK_FORMS}")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dh2rt replay",
        description="Rebuild every module's engine cycle by cycle from a capture of a loop run: its trace "
        "records, or stops at breakpoints.",
        epilog="Example: dh2rt replay robot.pcapng --break 'receptor head_a fires' --first",
    )
    p.add_argument("capture", type=Path, help="a pcapng the launcher's --capture wrote (its cycle marks beside it)")
    p.add_argument("--program", type=Path, help=PROGRAM_HELP + "; its digest must be the one the Hellos name")
    p.add_argument("--break", dest="breaks", action="append", default=[], metavar="SPEC", help=_BREAK_FORMS)
    p.add_argument("--first", action="store_true", help="end at the first breakpoint hit")
    p.add_argument("--trace", type=Path, metavar="FILE", help="write the rebuilt trace records to FILE (JSON Lines)")
    p.add_argument("--json", action="store_true", help="one JSON summary: stops, notes, counts")
    return p


def _check_digest(capture: Capture, rebuild: Rebuild, program: Path | None) -> None:
    if program is None or not rebuild.frames.digests:
        return
    mine = program_digest(capture.program.image).hex()
    if mine not in rebuild.frames.digests:
        named = ", ".join(sorted(rebuild.frames.digests))
        raise OptionError(
            f"--program {program}: digest {mine}; the capture's Hellos name {named}: not the program the robot ran"
        )


def _open(ns: argparse.Namespace, capture: Capture) -> tuple[Rebuild, list[Breakpoint]]:
    marks = list(read_marks(ns.capture))
    cycles = [m for m in marks if isinstance(m, CycleMark)]
    if not cycles:
        raise CaptureError(
            f"{ns.capture}: no cycle marks beside it ({marks_path(ns.capture).name}): it holds only the wire, and "
            "replay needs each module's cycles (which frames it took in at which cycle, its timer phase); "
            "a loop run's --capture keeps them"
        )
    rebuild = Rebuild(capture.program, marks, capture.hops())
    _check_digest(capture, rebuild, ns.program)
    modules = {m.name: m.module for m in cycles}
    breaks = [parse_break(text, capture, modules) for text in ns.breaks]
    return rebuild, breaks


@interruptible
def main(argv: Sequence[str] | None = None) -> int:
    started = options_and_capture(build_parser(), argv)
    if isinstance(started, int):
        return started
    ns, capture = started
    try:
        rebuild, breaks = _open(ns, capture)
        trace_out = ns.trace.open("w", encoding="utf-8") if ns.trace is not None else None
    except (CaptureError, OptionError) as exc:
        err(str(exc))
        return EXIT_USAGE
    except OSError as exc:
        err(f"--trace {ns.trace}: cannot be written ({exc.strerror or exc})")
        return EXIT_USAGE
    records_out = sys.stdout if not breaks and not ns.json else None
    stops: list[dict[str, Any]] = []
    count = 0
    try:
        for step in rebuild.steps():
            count += 1
            for out in (records_out, trace_out):
                if out is not None:
                    out.write(json.dumps(step.record, separators=(",", ":")) + "\n")
            hits = [b for b in breaks if b.hit(step)]
            if hits:
                stops.append(_stop(step, hits, capture.program))
                if not ns.json:
                    print(_stop_text(stops[-1]))
                if ns.first:
                    break
    except CaptureError as exc:
        err(str(exc))
        return EXIT_USAGE
    finally:
        if trace_out is not None:
            trace_out.close()
    _summary(ns, rebuild.notes, stops, count, len(rebuild.period))
    return EXIT_OK


def _summary(
    ns: argparse.Namespace, notes: Sequence[Note], stops: Sequence[dict[str, Any]], cycles: int, modules: int
) -> None:
    if ns.json:
        doc = {
            "capture": str(ns.capture),
            "modules": modules,
            "cycles": cycles,
            "stops": list(stops),
            "notes": [n.to_json() for n in notes],
        }
        print(json.dumps(doc, indent=1))
        return
    stream: IO[str] = sys.stderr
    for note in notes:
        print(f"replay: {note.kind}: {note.line()}", file=stream)
    if ns.breaks and not stops:
        print("no breakpoint was hit", file=sys.stdout)


def _stop(step: Step, hits: Sequence[Breakpoint], program: CompiledProgram) -> dict[str, Any]:
    """Where replay stopped and the module's state there (the record after the cycle)."""
    engine = step.engine
    status = {ACTIVE: "active", PASSIVE: "passive"}
    receptors = {r.name: status.get(s, "absent") for r, s in zip(program.receptors, engine.rstatus, strict=True)}
    return {
        "break": [b.text for b in hits],
        "module": step.mark.module,
        "name": step.mark.name,
        "life": step.mark.life,
        "cycle": step.mark.cycle,
        "t": step.mark.t,
        "fired": list(step.fired),
        "receptors": receptors,
        "uncertain": step.uncertain or None,
        "record": step.record,
    }


def _stop_text(stop: dict[str, Any]) -> str:
    rec = stop["record"]
    life = f", life {stop['life']}" if stop["life"] else ""
    status = ", ".join(f"{c} {r}" for c, r in rec["status"].items())
    lines = [
        f"break at {stop['name']} (module {stop['module']}) cycle {stop['cycle']}{life}, t {stop['t']:.6f}: "
        + "; ".join(stop["break"]),
        f"  type {rec['type']} (T {rec['T']}), LocalTimer {rec['timer']}, status {status}",
        f"  DOF1 {rec['actuators']['DOF1']:g}, DOF2 {rec['actuators']['DOF2']:g}",
    ]
    for key in ("variables", "sensors"):
        if rec.get(key):
            lines.append(f"  {key}: " + ", ".join(f"{k} {v}" for k, v in rec[key].items()))
    lines.append("  receptors: " + ", ".join(f"{k} {v}" for k, v in stop["receptors"].items()))
    if stop["fired"]:
        lines.append("  fired: " + ", ".join(stop["fired"]))
    took = [f"{a['hormone']} at {a['at'] or '(injected)'}" for a in rec["received"]]
    sent = [f"{s['hormone']} through {s['through']}" for s in rec["sent"]]
    lines.append("  took in: " + (", ".join(took) or "nothing") + "; sent: " + (", ".join(sent) or "nothing"))
    if stop["uncertain"]:
        lines.append(f"  uncertain: {stop['uncertain']}")
    return "\n".join(lines)
