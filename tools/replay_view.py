"""Breakpoints of ``dh2rt replay`` and how a rebuilt cycle is shown: where it is and the
module's state after it (the command's stops and the replay prompt share them)."""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from dh2rt.errors import OptionError
from dh2rt.program import ACTIVE, PASSIVE
from tools.reading import Capture
from tools.replay_rebuild import Step

BREAK_FORMS = "'hormone H', 'receptor NAME fires' or 'type of MODULE changes'"


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
    raise OptionError(f"--break {text!r}: a breakpoint is {BREAK_FORMS}")


def view(step: Step, hits: Sequence[str]) -> dict[str, Any]:
    """Where a rebuilt cycle is and the module's state after it (its record, the receptors'
    statuses as they stand now: take it right after the step; those of the program the
    module ran then, which a flash may have switched); ``hits``: the breakpoints it stopped at."""
    engine = step.engine
    status = {ACTIVE: "active", PASSIVE: "passive"}
    receptors = {r.name: status.get(s, "absent") for r, s in zip(engine.program.receptors, engine.rstatus, strict=True)}
    return {
        "break": list(hits),
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


def view_text(stop: dict[str, Any]) -> str:
    """A :func:`view` as lines: where, then the state."""
    rec = stop["record"]
    life = f", life {stop['life']}" if stop["life"] else ""
    status = ", ".join(f"{c} {r}" for c, r in rec["status"].items())
    lines = [
        f"{'break at' if stop['break'] else 'at'} {stop['name']} (module {stop['module']}) cycle {stop['cycle']}"
        f"{life}, t {stop['t']:.6f}" + "".join(f": {'; '.join(stop['break'])}" for _ in stop["break"][:1]),
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
