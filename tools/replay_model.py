"""``dh2rt replay --model``: the rebuilt run against what the in-process model predicts for
the same topology and inputs, by ``dh2rt diff``'s rule (order per module, stream by stream;
:mod:`tools.diff`).

The model is the in-process :class:`~dh2rt.robot.Robot` on what the capture says of the run:

* the topology: the modules of the cycle marks, by index and name, and the links the link
  marks name before the first cycle mark (those the run started with);
* each module's LocalTimer phase: its timer at its first cycle, moved back to cycle 0;
* the hormones injected over the control channels, at the module's cycle they came in;
* as many cycles as the longest-running module ran.

What the model cannot know is said: links docked later (their marks come after the first
cycle: the model, as ``dh2rt run``, docks what the program's effects ask for by its own
rules, and nothing else), links undocked (a ``release`` or a cut: the unlink marks; the
model releases and docks by ``dh2rt run``'s rules, at once, where the loop's motion takes
its time), links that lost frames (on serial links a frame sent into an undocked link is
lost: a cut), a module's later lives (a restart). Divergences from there on are the model's
ignorance, not the robot's fault, and the comparison says so: a divergence at or after the
first of them (on the capture's clock, by the cycle marks) is said to come after it, one
before any of them is the run's own.
"""

from __future__ import annotations

import io
import json
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dh2rt.errors import DH2Error
from dh2rt.events import parse_hormone
from dh2rt.profile import Profile
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.topology import Link, Topology
from dh2rt.trace import TraceWriter
from tools import diff
from tools.capture_cycles import CycleMark, LinkMark, Mark, UnlinkMark


@dataclass(frozen=True)
class ModelResult:
    """The comparison: ``lines`` as diff prints them, ``first`` the first divergence (None:
    none), ``unknown`` what the model could not know of the run (in the order it happened),
    ``after_unknown`` whether the first divergence comes at or after the first of those."""

    lines: list[str]
    first: dict[str, Any] | None
    unknown: list[str]
    after_unknown: bool = False


@dataclass(frozen=True, order=True)
class Unknown:
    """Something of the run the model cannot know, from ``time`` on the capture's clock."""

    time: float
    text: str


def model_records(program: CompiledProgram, marks: Sequence[Mark]) -> tuple[list[dict[str, Any]], list[Unknown]]:
    """The model's trace records for the run the marks tell of, and what it cannot know."""
    cycles = [m for m in marks if isinstance(m, CycleMark)]
    first_cycle = next(i for i, m in enumerate(marks) if isinstance(m, CycleMark))
    start_links = [m for m in marks[:first_cycle] if isinstance(m, LinkMark)]
    names = {m.module: m.name for m in reversed(cycles)}
    unknown = [
        Unknown(m.time, _link_change(m, names, cycles, program.profile))
        for m in marks[first_cycle:]
        if isinstance(m, LinkMark | UnlinkMark) and m.ends[0][0] in names and m.ends[1][0] in names
    ]
    phases: dict[int, int] = {}
    restarted: set[int] = set()
    injected: dict[int, list[tuple[int, str]]] = defaultdict(list)
    last = 0
    for m in cycles:
        if m.life:
            if m.module not in restarted:
                restarted.add(m.module)
                text = f"{m.name} restarted (life {m.life}): the model runs its first life only"
                unknown.append(Unknown(m.time, text))
            continue
        phases.setdefault(m.module, (m.timer - m.cycle) % program.clock_cycle)
        injected[m.module] += [(m.cycle, text) for text in m.injected]
        last = max(last, m.cycle)
    size = max(names) + 1
    topology = Topology(
        program.profile,
        tuple(names.get(i, f"m{i}") for i in range(size)),
        tuple(Link(a, ac, b, bc) for (a, ac), (b, bc) in (m.ends for m in start_links)),
    )
    robot = Robot(program, topology, timer_phases=[phases.get(i, 0) for i in range(size)])
    stream = io.StringIO()
    writer = TraceWriter(stream, robot, owns_stream=False)
    due: dict[int, list[tuple[int, str]]] = defaultdict(list)
    for module, items in injected.items():
        for cycle, text in items:
            due[cycle].append((module, text))
    for cycle in range(last + 1):
        for module, text in due.get(cycle, ()):
            try:
                robot.inject(module, parse_hormone(text, program.vocabulary, "injected hormone"))
            except DH2Error as exc:
                text = f"{names[module]} cycle {cycle}: injected {text!r} is no hormone of the program ({exc})"
                unknown.append(Unknown(_time_of(cycles, module, cycle), text))
        robot.step()
        writer.write_cycle()
    records = [json.loads(line) for line in stream.getvalue().splitlines()]
    for record in records:
        record["life"] = 0
    return records, unknown


def _link_change(
    m: LinkMark | UnlinkMark, names: Mapping[int, str], cycles: Sequence[CycleMark], profile: Profile
) -> str:
    """A link docked or undocked after the start, with each end's cycle then."""
    at = ", ".join(
        f"{names[module]}.{profile.connector_name(conn)} in its cycle {_cycle_at(cycles, module, m.time)}"
        for module, conn in m.ends
    )
    if isinstance(m, LinkMark):
        return (
            f"link {m.link} docked later ({at}): the model docks only what the program's own effects dock, "
            "by dh2rt run's rules"
        )
    return (
        f"link {m.link} undocked ({at}; a release or a cut): the model releases and docks by dh2rt run's rules, "
        "at once, where the loop's motion takes its time"
    )


def _cycle_at(cycles: Sequence[CycleMark], module: int, when: float) -> int | None:
    """The cycle ``module`` was in at ``when`` (its last cycle begun by then)."""
    begun = [m.cycle for m in cycles if m.module == module and m.time <= when]
    return begun[-1] if begun else None


def _time_of(cycles: Sequence[CycleMark], module: int, cycle: int) -> float:
    """When ``module`` began ``cycle`` (its first life), on the capture's clock."""
    return next((m.time for m in cycles if m.module == module and m.cycle == cycle and not m.life), 0.0)


def lost_links(first_lost: Mapping[int, float]) -> list[Unknown]:
    """Links that lost frames (sent into an undocked link, or dropped by an impaired one)."""
    return [
        Unknown(t, f"link {link} lost frames from t {t:.6f} (a cut?): the model keeps it")
        for link, t in sorted(first_lost.items())
    ]


def compare_with_model(
    rebuilt: Sequence[dict[str, Any]],
    program: CompiledProgram,
    marks: Sequence[Mark],
    folder: Path,
    capture: Path,
    first_lost: Mapping[int, float] | None = None,
) -> ModelResult:
    """diff's comparison of the rebuilt records (A) with the model's (B), both written as
    traces into ``folder`` (diff reads files and names them); ``first_lost``: when each link
    that lost frames lost its first (the capture's clock)."""
    model, found = model_records(program, marks)
    unknowns = sorted(found + lost_links(first_lost or {}))
    unknown = [u.text for u in unknowns]
    a, b = folder / f"{capture.name}.replayed.jsonl", folder / "model.jsonl"
    for path, records in ((a, rebuilt), (b, model)):
        path.write_text("".join(json.dumps(r, separators=(",", ":")) + "\n" for r in records), encoding="utf-8")
    run_a, run_b = diff.trace_run(a), diff.trace_run(b)
    results, divergences = diff.compare(run_a, run_b, diff.DEFAULT_SLACK)
    after = False
    if divergences:
        lines = diff.describe(divergences[0], run_a, run_b)
        first = diff.to_json(results, divergences, every=False)["divergence"]
        lines.append(_judged(divergences[0], marks, unknowns))
        after = lines[-1].startswith("it comes after")
    else:
        lines = [f"no divergence between {a.name} and {b.name}"]
        first = None
    return ModelResult(lines + diff.summary(results, run_a, run_b), first, unknown, after)


def _judged(first: diff.Divergence, marks: Sequence[Mark], unknowns: Sequence[Unknown]) -> str:
    """Whether ``first`` comes after what the model cannot know (by the capture's clock: the
    cycle it happens in at its module, a cycle's slack for the hop that carried it) or before."""
    cycles = [m for m in marks if isinstance(m, CycleMark)]
    module, cycle = first.key.order[0], int(first.when)
    when = _time_of(cycles, module, cycle) or _time_of(cycles, module, cycle - 1)
    earlier = [u for u in unknowns if when and u.time <= when]
    if earlier:
        return f"it comes after what the model cannot know (the first: {earlier[0].text})"
    if unknowns:
        return "it comes before anything the model cannot know: the run's own"
    return "the model knew everything the capture says of this run: the divergence is the run's own"
