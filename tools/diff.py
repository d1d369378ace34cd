"""``dh2rt diff A B``: compare two runs of the same program, topology, seed and events (the
in-process robot and a run in the loop, say) hop by hop, and print the first divergence, or
that there is none.

What is compared. Cycle numbers are not: each module in the loop counts its own cycles from
its own start, and a hormone crosses a link in the loop within the cycle it was sent or in a
later one, where the in-process robot always takes exactly one cycle. So which cycle takes
in what, and so which arrivals share a cycle, is the loop's timing. What must agree is the
*order* of what happens at each module, in these streams, each compared on its own:

* **arrivals by route**: at each connector, from each path (the connector it was sent
  through and the path it came with: ``arrivals at front from back, path front>left``),
  the hormones the module took in, in order, by content. Along one route the order is
  fixed: every link is first in, first out, and both hosts hand a cycle's arrivals to the
  engine sorted by connector, keeping that order (it matters: the engine binds the first
  matching entry). Between routes it is not compared: hormones from two neighbours, or from
  two origins through one neighbour that forwards them, fall into the same cycle in one run
  and into two in the other, and the module forwards them in the order it took them in.
* **injected hormones** (``--event CYCLE:inject:...``), in order.
* **actuator changes**: each new (DOF1, DOF2) pair, in order, from the engine's (0, 0); a
  cycle that changes nothing adds nothing. Its place between arrivals is not compared (it
  follows from them, and their grouping into cycles is the loop's).
* **faults**: each receptor fault message, in order.

Each stream is compared up to the shorter of the two: a run stops at a cycle count per
module (or at an instant), so its tail may be cut at a different point in each file. Events
left over in the longer stream are *cut by the end of the run* when the other file's module
had stopped (within ``--slack`` cycles) before they would have come there; when that is, is
read from the last event the two files agreed on before them at that module (its cycle in
each file gives the offset between the two runs there). Left-over events that should have
come while the other run was still going are a divergence (a hormone lost, say), as is a
module in one file only. The first divergence is the earliest in A's run.

What is legitimately different and still reported: a program whose outcome is a race (in
``legs_to_snake`` the tail answers the first RCT it takes in, and which foot's comes first
in the loop is its timing) diverges wherever the race goes another way.

Captures (pcapng, pcap, python-can logs, as ``dh2rt dump`` reads them) are compared per link
end (link id and side, the end that sent) and path: the hormones sent, in order, as content,
the connector sent through and the route. Link ids are the launcher's, the same for the same
topology. Beacons (Hello, KeepAlive) are not compared: they are timing. Left-over frames
count as cut by the end when the other capture had ended (within ``--slack`` cycles of
``--cycle-ms``) before they would have come.

Exit codes: 0 no divergence, 1 a divergence (printed), 2 bad input (a file that is not a
trace or capture: the message names the file and the line and column, field or offset).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dh2rt.cmdline import EXIT_FAIL, EXIT_OK, EXIT_USAGE, TRACE_SUFFIXES, add_cycle_argument, err
from dh2rt.errors import CaptureError, IncomparableInputs, ProgramError, TraceError
from dh2rt.profile import Profile
from dh2rt.runtime import ms_to_s
from tools.decode import Hop
from tools.reading import PROGRAM_HELP, interruptible, open_capture
from tools.trace_reading import TraceRecord, read_trace

#: Cycles of leeway at the end of a run (see the module docs), by default.
DEFAULT_SLACK = 3


@dataclass(frozen=True, slots=True)
class Event:
    """One thing that happened, as compared (``text``), and where in its run: ``at`` is the
    module's cycle count so far (a trace) or the frame's time in seconds (a capture), used
    only to tell a cut tail from a lost event; ``where`` orients the reader."""

    text: str
    at: float
    where: str


@dataclass(frozen=True, slots=True, order=True)
class StreamKey:
    """A stream of events: ``owner`` (a module, or a link end) and what it holds."""

    order: tuple[int, ...]  # sorts owners: the module number, or (link, side)
    owner: str  # m3 (module 3), or link 2 side 0
    what: str  # arrivals at front, actuator changes, ...


@dataclass
class Run:
    """A file read into streams: ``starts`` and ``ends`` are where each owner's run began
    and how far it went (in ``at`` units)."""

    path: Path
    streams: dict[StreamKey, list[Event]] = field(default_factory=dict)
    starts: dict[str, float] = field(default_factory=dict)
    ends: dict[str, float] = field(default_factory=dict)
    owners: dict[str, tuple[int, ...]] = field(default_factory=dict)
    unit: str = "cycles"

    def add(self, key: StreamKey, event: Event) -> None:
        self.streams.setdefault(key, []).append(event)


@dataclass(frozen=True, slots=True)
class Divergence:
    """The first place where a stream differs; ``a`` or ``b`` is None where that file has
    nothing more; ``index`` counts from 1; ``when`` is where it is in ``a``'s run (for an
    event ``a`` lacks, where it would have been), to find the first of several."""

    key: StreamKey
    index: int
    a: Event | None
    b: Event | None
    when: float
    note: str = ""


@dataclass(frozen=True, slots=True)
class StreamResult:
    key: StreamKey
    compared: int
    a_count: int
    b_count: int
    divergence: Divergence | None
    cut: str = ""  # what was left over and not compared, cut by the end of the run


# ------------------------------------------------------------------ traces into streams


def _module_key(module: int, name: str, what: str) -> StreamKey:
    return StreamKey((module,), f"{name} (module {module})", what)


def _num(x: float) -> str:
    return str(int(x)) if x.is_integer() else repr(x)


def _path_text(path: Sequence[tuple[str, str]]) -> str:
    return " ".join(f"{s}>{r}" for s, r in path) if path else "(none)"


def trace_run(path: Path) -> Run:
    """Read a trace into per-module streams (see the module docs for what they hold)."""
    by_module: dict[int, list[TraceRecord]] = {}
    names: dict[int, str] = {}
    for rec in read_trace(path):
        if names.setdefault(rec.module, rec.name) != rec.name:
            raise TraceError(f"{path}:{rec.line}: module {rec.module} is named {rec.name}, earlier {names[rec.module]}")
        by_module.setdefault(rec.module, []).append(rec)
    if not by_module:
        raise TraceError(f"{path}: no trace records in it")
    run = Run(path)
    for module, records in sorted(by_module.items()):
        records.sort(key=lambda r: (r.life, r.cycle))  # the launcher merges by cycle, then module
        _check_unique(path, records)
        _module_streams(run, module, names[module], records)
    return run


def _check_unique(path: Path, records: Sequence[TraceRecord]) -> None:
    for before, rec in itertools.pairwise(records):
        if (before.life, before.cycle) == (rec.life, rec.cycle):
            raise TraceError(
                f"{path}:{rec.line}: module {rec.module}'s cycle {rec.cycle} again (line {before.line}); "
                "two runs in one file?"
            )


def _module_streams(run: Run, module: int, name: str, records: Sequence[TraceRecord]) -> None:
    """One module's records, in its order, into its streams."""
    dof = (0.0, 0.0)  # the engine's actuators at power-up
    for ordinal, rec in enumerate(records):
        life = f", life {rec.life}" if rec.life else ""
        where = f"cycle {rec.cycle}{life}, line {rec.line}"
        for a in rec.received:
            if a.at is None:
                what = "injected hormones"
            else:  # one route: the link it came over and the path before it
                what = f"arrivals at {a.at} from {a.remote}, path {_path_text(a.path)}"
            text = a.hormone
            run.add(_module_key(module, name, what), Event(text, ordinal, where))
        if rec.dof != dof:
            dof = rec.dof
            text = f"DOF1 {_num(dof[0])}, DOF2 {_num(dof[1])}"
            run.add(_module_key(module, name, "actuator changes"), Event(text, ordinal, where))
        for fault in rec.faults:
            run.add(_module_key(module, name, "faults"), Event(fault, ordinal, where))
    owner = f"{name} (module {module})"
    run.owners[owner] = (module,)
    run.starts[owner] = 0
    run.ends[owner] = len(records) - 1


# ------------------------------------------------------------------ captures into streams


def _hop_event(hop: Hop, profile: Profile) -> tuple[str, Event]:
    """A hormone frame as (its stream, the event): the stream is the path it was sent with."""
    h = hop.hormone
    assert h is not None
    name = profile.connector_name
    text = f"{h.content()} via {hop.sender}"
    if h.route is not None:
        text += f", route {' '.join(name(c) for c in h.route)}"
    text += " (lost on the link)" if hop.lost else ""
    what = f"hormones sent, path {_path_text([(name(s), name(r)) for s, r in h.path])}"
    return what, Event(text, hop.time, f"t {hop.time:.6f} s")


def capture_run(path: Path, program: Path | None) -> Run:
    """Read a capture into per-link-end streams of the hormones sent there, one per path."""
    capture = open_capture(path, program)
    profile = capture.program.profile
    run = Run(path, unit="s")
    for hop in capture.hops():
        if hop.link is None or hop.side is None:
            continue  # not a dh2rt frame: dump shows it; nothing to compare
        owner = f"link {hop.link} side {hop.side}"
        run.owners[owner] = (hop.link, hop.side)
        run.starts.setdefault(owner, hop.time)
        run.ends[owner] = max(run.ends.get(owner, hop.time), hop.time)
        if hop.hormone is not None and hop.kind in ("hormone", "routed"):
            what, event = _hop_event(hop, profile)
            run.add(StreamKey((hop.link, hop.side), owner, what), event)
    if not run.owners:
        raise CaptureError(f"{path}: no dh2rt frames in it")
    return run


# ------------------------------------------------------------------ comparing


def compare(a: Run, b: Run, slack: float) -> tuple[list[StreamResult], list[Divergence]]:
    """Compare every stream of ``a`` and ``b``; returns the per-stream results and the
    divergences, earliest first (by where they are in ``a``, else in ``b``)."""
    if a.unit != b.unit:
        raise IncomparableInputs(f"{a.path} and {b.path}: a trace and a capture; compare two traces or two captures")
    _check_same_robot(a, b)
    divergences = [
        Divergence(StreamKey(order, owner, "module"), 0, *_presence(owner, a, b), when=0.0)
        for owner, order in sorted({**a.owners, **b.owners}.items(), key=lambda kv: kv[1])
        if owner not in a.owners or owner not in b.owners
    ]
    results: list[StreamResult] = []
    for owner in sorted(set(a.owners) & set(b.owners), key=lambda o: a.owners[o]):
        results += _compare_owner(owner, a, b, slack)
    divergences += [r.divergence for r in results if r.divergence is not None]
    divergences.sort(key=lambda d: (d.when, d.key))
    return results, divergences


def _check_same_robot(a: Run, b: Run) -> None:
    """Module numbers must name the same modules in both (the same topology)."""
    if a.unit != "cycles":
        return
    numbers_a = {order: owner for owner, order in a.owners.items()}
    for owner, order in b.owners.items():
        other = numbers_a.get(order)
        if other is not None and other != owner:
            raise IncomparableInputs(
                f"{a.path} and {b.path} are not runs of the same robot: "
                f"module {order[0]} is {other.split()[0]} in one, {owner.split()[0]} in the other"
            )


def _presence(owner: str, a: Run, b: Run) -> tuple[Event | None, Event | None]:
    def seen(run: Run) -> Event | None:
        return Event(f"{owner} is here", 0, "") if owner in run.owners else None

    return seen(a), seen(b)


@dataclass(frozen=True, slots=True)
class _Side:
    """One file's view of a stream: its events, and where its owner's run ended."""

    run: Run
    events: Sequence[Event]
    end: float


def _compare_owner(owner: str, a: Run, b: Run, slack: float) -> list[StreamResult]:
    keys = sorted({k for k in (*a.streams, *b.streams) if k.owner == owner})
    prefixes = {k: _common_prefix(a.streams.get(k, []), b.streams.get(k, [])) for k in keys}
    # where each event the files agree on is in each: how far apart the runs are there
    agreed = [
        (x.at, y.at) for k, n in prefixes.items() if n for x, y in zip(a.streams[k][:n], b.streams[k][:n], strict=True)
    ]
    agreed.append((a.starts[owner], b.starts[owner]))
    results = []
    for key, n in prefixes.items():
        xs, ys = a.streams.get(key, []), b.streams.get(key, [])
        results.append(_stream_result(key, n, _Side(a, xs, a.ends[owner]), _Side(b, ys, b.ends[owner]), agreed, slack))
    return results


def _common_prefix(xs: Sequence[Event], ys: Sequence[Event]) -> int:
    n = 0
    for x, y in zip(xs, ys, strict=False):
        if x.text != y.text:
            break
        n += 1
    return n


def _stream_result(
    key: StreamKey, n: int, a: _Side, b: _Side, agreed: Sequence[tuple[float, float]], slack: float
) -> StreamResult:
    """One stream's outcome, its first ``n`` events agreeing: a divergence, a tail cut by
    the end of a run, or neither."""
    counts = (key, n, len(a.events), len(b.events))
    if n < len(a.events) and n < len(b.events):
        return StreamResult(*counts, Divergence(key, n + 1, a.events[n], b.events[n], a.events[n].at))
    if len(a.events) == len(b.events):
        return StreamResult(*counts, None)
    in_a = len(a.events) > len(b.events)
    longer, shorter = (a, b) if in_a else (b, a)
    extra = longer.events[n]
    expected = _translate(extra.at, agreed, from_a=in_a)
    if expected > shorter.end - slack:
        left = len(longer.events) - n
        cut = f"{longer.run.path.name} has {left} more (from {extra.where}), after {shorter.run.path.name}'s end"
        return StreamResult(*counts, None, cut)
    unit = shorter.run.unit
    note = (
        f"nothing here; it would have come about {_at_text(expected, unit)}, "
        f"and this run went on to {_at_text(shorter.end, unit)}"
    )
    if in_a:
        return StreamResult(*counts, Divergence(key, n + 1, extra, None, extra.at, note))
    return StreamResult(*counts, Divergence(key, n + 1, None, extra, expected, note))


def _translate(at: float, agreed: Sequence[tuple[float, float]], *, from_a: bool) -> float:
    """Where ``at`` in one run (``a`` if ``from_a``) is in the other: the runs are as far
    apart there as at the last event they agreed on before it (or at their starts)."""
    mine, theirs = (0, 1) if from_a else (1, 0)
    before = [p for p in agreed if p[mine] <= at] or [min(agreed, key=lambda p: p[mine])]
    anchor = max(before, key=lambda p: p[mine])
    return at - anchor[mine] + anchor[theirs]


def _at_text(at: float, unit: str) -> str:
    return f"t {at:.3f} s" if unit == "s" else f"its {_nth(int(at) + 1)} cycle"


# ------------------------------------------------------------------ output


def _nth(n: int) -> str:
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def _noun(what: str) -> str:
    """``arrivals at front`` -> ``arrival at front``: one event of the stream."""
    head, _, rest = what.partition(" ")
    singular = {"arrivals": "arrival", "changes": "change", "faults": "fault", "hormones": "hormone"}
    words = [singular.get(w, w) for w in (head, *rest.split())]
    return " ".join(words)


def describe(d: Divergence, a: Run, b: Run) -> list[str]:
    """A divergence in words: where, and what each file had there."""
    if d.key.what == "module":
        only = a if d.a is not None else b
        return [f"{d.key.owner} is in {only.path.name} only"]
    lines = [f"{a.path.name} and {b.path.name} diverge at {d.key.owner}, {_nth(d.index)} {_noun(d.key.what)}:"]
    width = max(len(a.path.name), len(b.path.name))
    for run, event in ((a, d.a), (b, d.b)):
        shown = f"{event.text}  [{event.where}]" if event is not None else d.note
        lines.append(f"  {run.path.name:<{width}}  {shown}")
    if d.index == 2:
        lines.append("  (the one before it agrees)")
    elif d.index > 2:
        lines.append(f"  (the {d.index - 1} before it agree)")
    return lines


def summary(results: Sequence[StreamResult], a: Run, b: Run) -> list[str]:
    """What was compared, and what was left over at the ends of the runs."""
    counts: dict[str, int] = {}
    for r in results:
        kind = r.key.what.split(" at ")[0].split(",")[0]  # arrivals, hormones sent, ...
        counts[kind] = counts.get(kind, 0) + r.compared
    owners = len(set(a.owners) & set(b.owners))
    what = ", ".join(f"{n} {kind}" for kind, n in counts.items()) or "no events"
    unit = "modules" if a.unit == "cycles" else "link ends"
    lines = [f"compared {owners} {unit} in order, stream by stream: {what}"]
    lines += [f"  {r.key.owner}, {r.key.what}: {r.cut}; compared {r.compared}" for r in results if r.cut]
    return lines


def to_json(results: Sequence[StreamResult], divergences: Sequence[Divergence], every: bool) -> dict[str, Any]:
    def event(e: Event | None) -> dict[str, Any] | None:
        return None if e is None else {"event": e.text, "at": e.at, "where": e.where}

    def div(d: Divergence) -> dict[str, Any]:
        return {
            "owner": d.key.owner,
            "stream": d.key.what,
            "index": d.index,
            "a": event(d.a),
            "b": event(d.b),
            "note": d.note or None,
        }

    out: dict[str, Any] = {
        "divergence": div(divergences[0]) if divergences else None,
        "streams": [
            {
                "owner": r.key.owner,
                "stream": r.key.what,
                "compared": r.compared,
                "a": r.a_count,
                "b": r.b_count,
                "cut": r.cut or None,
            }
            for r in results
        ],
    }
    if every:
        out["divergences"] = [div(d) for d in divergences]
    return out


# ------------------------------------------------------------------ the command


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dh2rt diff",
        description="Compare two traces (or two captures) of the same program, topology and seed hop by hop,\n"
        "and print the first divergence in per-hop order or angle, or that there is none.\n"
        "Cycle numbers are not compared: each stream's order is (see docs/capture.md).",
        epilog="Example, the in-process robot against a run in the loop:\n"
        "  dh2rt run examples/caterpillar.dh2 --cycles 150 --seed 1 --trace robot.jsonl\n"
        "  dh2rt --transport virtual --cycles 150 --seed 1 --stand-in none --trace loop.jsonl\n"
        "  dh2rt diff robot.jsonl loop.jsonl",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("a", type=Path, help="a JSON Lines trace (.jsonl), or a capture (.pcapng, .pcap, .log, ...)")
    p.add_argument("b", type=Path, help="the other run, of the same kind")
    p.add_argument(
        "--slack",
        type=float,
        default=DEFAULT_SLACK,
        metavar="CYCLES",
        help=f"cycles of leeway for tails cut by the end of a run (default: {DEFAULT_SLACK})",
    )
    add_cycle_argument(p, "captures: the cycle period")
    p.add_argument("--program", type=Path, help="captures: " + PROGRAM_HELP)
    p.add_argument("--all", action="store_true", help="every stream's first divergence, not only the first")
    p.add_argument("--json", action="store_true", help="the result as one JSON object")
    return p


def read_run(path: Path, program: Path | None) -> Run:
    """A trace by its name (.jsonl, .ndjson), else a capture."""
    if path.suffix.lower() in TRACE_SUFFIXES:
        return trace_run(path)
    try:
        return capture_run(path, program)
    except CaptureError as exc:
        names = " or ".join(TRACE_SUFFIXES)
        raise CaptureError(f"{exc} (read as a capture: a trace's name ends in {names})") from None


@interruptible
def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        ns = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code) if isinstance(exc.code, int) else EXIT_USAGE
    if ns.slack < 0 or ns.cycle_ms <= 0:
        err("--slack must be 0 or more and --cycle-ms more than 0")
        return EXIT_USAGE
    try:
        a, b = read_run(ns.a, ns.program), read_run(ns.b, ns.program)
        slack = ns.slack if a.unit == "cycles" else ns.slack * ms_to_s(ns.cycle_ms)
        results, divergences = compare(a, b, slack)
    except ProgramError as exc:
        print(exc.render(), file=sys.stderr)
        return EXIT_USAGE
    except (TraceError, CaptureError, IncomparableInputs) as exc:
        err(str(exc))
        return EXIT_USAGE
    _print(ns, results, divergences, a, b)
    return EXIT_FAIL if divergences else EXIT_OK


def _print(
    ns: argparse.Namespace, results: Sequence[StreamResult], divergences: Sequence[Divergence], a: Run, b: Run
) -> None:
    if ns.json:
        print(json.dumps(to_json(results, divergences, ns.all)))
        return
    lines: list[str] = []
    if not divergences:
        lines.append(f"no divergence between {a.path.name} and {b.path.name}")
    for d in divergences if ns.all else divergences[:1]:
        lines += describe(d, a, b)
    lines += summary(results, a, b)
    print("\n".join(lines))
