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
rules, and nothing else), links that lost frames (on serial links a frame sent into an undocked link is lost:
a cut), a module's later lives (a restart). Divergences from there on are the model's
ignorance, not the robot's fault.
"""

from __future__ import annotations

import io
import json
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dh2rt.errors import DH2Error
from dh2rt.events import parse_hormone
from dh2rt.program import CompiledProgram
from dh2rt.robot import Robot
from dh2rt.topology import Link, Topology
from dh2rt.trace import TraceWriter
from tools import diff
from tools.capture_cycles import CycleMark, LinkMark, Mark


@dataclass(frozen=True)
class ModelResult:
    """The comparison: ``lines`` as diff prints them, ``first`` the first divergence (None:
    none), ``unknown`` what the model could not know of the run."""

    lines: list[str]
    first: dict[str, Any] | None
    unknown: list[str]


def model_records(program: CompiledProgram, marks: Sequence[Mark]) -> tuple[list[dict[str, Any]], list[str]]:
    """The model's trace records for the run the marks tell of, and what it cannot know."""
    cycles = [m for m in marks if isinstance(m, CycleMark)]
    first_cycle = next(i for i, m in enumerate(marks) if isinstance(m, CycleMark))
    start_links = [m for m in marks[:first_cycle] if isinstance(m, LinkMark)]
    names = {m.module: m.name for m in reversed(cycles)}
    unknown = [
        f"link {m.link} ({names[m.ends[0][0]]} to {names[m.ends[1][0]]}) came later: the model docks only what "
        "the program's own effects dock, by dh2rt run's rules"
        for m in marks[first_cycle:]
        if isinstance(m, LinkMark) and m.ends[0][0] in names and m.ends[1][0] in names
    ]
    phases: dict[int, int] = {}
    restarted: set[int] = set()
    injected: dict[int, list[tuple[int, str]]] = defaultdict(list)
    last = 0
    for m in cycles:
        if m.life:
            if m.module not in restarted:
                restarted.add(m.module)
                unknown.append(f"{m.name} restarted (life {m.life}): the model runs its first life only")
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
                unknown.append(f"{names[module]} cycle {cycle}: injected {text!r} is no hormone of the program ({exc})")
        robot.step()
        writer.write_cycle()
    records = [json.loads(line) for line in stream.getvalue().splitlines()]
    for record in records:
        record["life"] = 0
    return records, unknown


def lost_links(first_lost: dict[int, float]) -> list[str]:
    """Links that lost frames (sent into an undocked link, or dropped by an impaired one)."""
    return [
        f"link {link} lost frames from t {t:.6f} (a cut?): the model keeps it" for link, t in sorted(first_lost.items())
    ]


def compare_with_model(
    rebuilt: Sequence[dict[str, Any]], program: CompiledProgram, marks: Sequence[Mark], folder: Path, capture: Path
) -> ModelResult:
    """diff's comparison of the rebuilt records (A) with the model's (B), both written as
    traces into ``folder`` (diff reads files and names them)."""
    model, unknown = model_records(program, marks)
    a, b = folder / f"{capture.name}.replayed.jsonl", folder / "model.jsonl"
    for path, records in ((a, rebuilt), (b, model)):
        path.write_text("".join(json.dumps(r, separators=(",", ":")) + "\n" for r in records), encoding="utf-8")
    run_a, run_b = diff.trace_run(a), diff.trace_run(b)
    results, divergences = diff.compare(run_a, run_b, diff.DEFAULT_SLACK)
    if divergences:
        lines = diff.describe(divergences[0], run_a, run_b)
        first = diff.to_json(results, divergences, every=False)["divergence"]
    else:
        lines = [f"no divergence between {a.name} and {b.name}"]
        first = None
    return ModelResult(lines + diff.summary(results, run_a, run_b), first, unknown)
