"""``dh2rt topo CAPTURE``: the robot's links over time, rebuilt from its traffic alone, each
module's topological type as the profile derives it, and the pieces (connected components),
printed at each change and, with ``--png-dir``, drawn one picture per change.

Nothing on the wire names a module: the modules are labelled ``M0``, ``M1``, ... by the first
frame any of their link ends sent. These labels are this tool's own, not the modules' names.
How link ends are found to be one module, and what traffic cannot show, is
:mod:`tools.topology_rebuild`'s docs; each module says what tied its ends (hormones
``forwarded`` through it, hormones it ``relayed``, the ``timing`` of its frames, or ``one
end`` when nothing tied that end to another).

``--trace TRACE`` (the JSON Lines trace of the same run, from the launcher's ``--trace``)
compares every module's own type, cycle by cycle, with the type its links on the capture
give it, and flags each stretch where they disagree for longer than the modules can lag
(the liveness bound and two cycles). The launcher's records carry the module's clock at each
cycle (``t``, monotonic) and the capture the wall clock: the two are aligned by the hormones
the trace says were sent (found in the capture just after their cycle began), or, in a run
without hormones, by the runs' ends; records without ``t`` (``dh2rt run``) are placed at
cycle x period. Trace modules are matched to the traffic's by the hormones they sent and
received, then by the status they had most of the time.

Exit codes: 0 ok (and, with --trace, no disagreement), 1 disagreements found, 2 bad input
(capture, program or trace that cannot be read, or no link traffic), 130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dh2rt.cmdline import EXIT_FAIL, EXIT_OK, EXIT_USAGE, err
from dh2rt.errors import CaptureError, DH2Error, TopologyError, TraceError
from dh2rt.liveness import SILENCE_CYCLES
from dh2rt.output_paths import check_output
from dh2rt.profile import Profile
from tools.decode import Hop
from tools.reading import PROGRAM_HELP, interruptible, options_and_capture
from tools.topology_rebuild import (
    Alignment,
    Disagreement,
    Module,
    Rebuilt,
    Snapshot,
    TraceCycle,
    Traffic,
    align,
    describe_end,
    disagreements,
    rebuild,
)
from tools.trace_reading import parse_record

HOW = {"forwarded": "hormones forwarded", "relayed": "hormones relayed", "timing": "frame timing", "alone": "one end"}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dh2rt topo",
        description="Rebuild a robot's topology over time from a capture of its traffic alone.",
        epilog="Example: dh2rt topo run.pcapng --trace run.jsonl --png-dir topo/",
    )
    p.add_argument("capture", type=Path, help="a pcapng or pcap, or a python-can log (.log .asc .blf ...)")
    p.add_argument("--program", type=Path, help=PROGRAM_HELP)
    p.add_argument("--trace", type=Path, help="the run's JSON Lines trace: flag where modules' own types disagree")
    p.add_argument("--png-dir", type=Path, help="draw each change as DIR/topo-NNN.png (needs matplotlib)")
    p.add_argument("--json", action="store_true", help="the whole rebuild as one JSON object")
    p.add_argument("--cycle-ms", type=float, help="the cycle period (default: told from the frames' intervals)")
    p.add_argument(
        "--silence-cycles",
        type=int,
        default=SILENCE_CYCLES,
        help=f"liveness bound in cycles (default: {SILENCE_CYCLES})",
    )
    p.add_argument(
        "--burst-ms", type=float, help="one module's frames of a cycle lie within this (default: 5%% of a cycle)"
    )
    p.add_argument("--settle-ms", type=float, help="changes closer than this are one (default: the liveness bound)")
    return p


@interruptible
def main(argv: Sequence[str] | None = None) -> int:
    started = options_and_capture(build_parser(), argv)
    if isinstance(started, int):
        return started
    ns, capture = started
    profile = capture.program.profile
    try:
        _check_options(ns)
        records = read_trace_cycles(ns.trace, profile) if ns.trace else None  # a bad trace fails first
        rebuilt, traffic = _rebuild(ns, capture.hops(), profile)
        compared = None if records is None else _compare(records, traffic, rebuilt)
        if ns.png_dir:
            draw_all(rebuilt, ns.png_dir, profile)
    except (CaptureError, TraceError, DH2Error, ValueError) as exc:
        err(str(exc))
        return EXIT_USAGE
    try:
        if ns.json:
            print(json.dumps(to_json(rebuilt, profile, compared)))
        else:
            print("\n".join(text_lines(ns.capture, rebuilt, profile, compared)))
    except BrokenPipeError:  # `dh2rt topo ... | head`: the reader has what it wanted
        pass
    return EXIT_FAIL if compared and compared.found else EXIT_OK


def _check_options(ns: argparse.Namespace) -> None:
    for option, value in (("--cycle-ms", ns.cycle_ms), ("--burst-ms", ns.burst_ms), ("--settle-ms", ns.settle_ms)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ValueError(f"{option} {value}: must be a positive number of milliseconds")
    if ns.silence_cycles < 1:
        raise ValueError(f"--silence-cycles {ns.silence_cycles}: must be at least 1")
    if ns.png_dir is not None:
        check_output(ns.png_dir, "--png-dir", folder=True)  # before the rebuild: the rule every output follows


def _ms(value: float | None) -> float | None:
    return None if value is None else value / 1000


def _rebuild(ns: argparse.Namespace, hops: Iterable[Hop], profile: Profile) -> tuple[Rebuilt, Traffic]:
    traffic = Traffic(profile).extend(hops)
    if traffic.stop is None:
        raise ValueError(f"{ns.capture}: no link traffic in it (no Hello, KeepAlive or hormone on a link)")
    rebuilt = rebuild(
        traffic,
        period=_ms(ns.cycle_ms),
        silence_cycles=ns.silence_cycles,
        burst=_ms(ns.burst_ms),
        settle=_ms(ns.settle_ms),
    )
    return rebuilt, traffic


# ----------------------------------------------------------------------------- the trace


def read_trace_cycles(path: Path, profile: Profile) -> list[TraceCycle]:
    """The trace's records as the comparison needs them; TraceError naming the file and the
    line for one that is not a record or names a connector or type the profile lacks."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise TraceError(f"{path}: cannot read it ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise TraceError(f"{path}: not UTF-8 text ({exc.reason})") from None
    out = [_cycle(line, path, n, profile) for n, line in enumerate(lines, 1) if line.strip()]
    if not out:
        raise TraceError(f"{path}: no records in it")
    return out


def _cycle(line: str, path: Path, line_no: int, profile: Profile) -> TraceCycle:
    rec = parse_record(line, path, line_no)  # checks the common fields, names what is wrong
    obj = json.loads(line)
    where = f"{path}:{line_no}"
    status = obj.get("status")
    if not isinstance(status, dict) or not isinstance(obj.get("type"), str):
        raise TraceError(f"{where}: fields type (a name) and status (connector -> connector) are needed")
    sent = obj.get("sent", [])
    if not isinstance(sent, list) or not all(isinstance(x, dict) for x in sent):
        raise TraceError(f"{where}: field sent: expected a list of objects")
    try:
        index = profile.connector_index
        t = obj.get("t")
        return TraceCycle(
            module=rec.module,
            life=rec.life,
            name=rec.name,
            cycle=rec.cycle,
            t=float(t) if isinstance(t, int | float) and not isinstance(t, bool) else None,
            type_name=obj["type"],
            status=tuple(0 if status.get(c, "0") == "0" else index(str(status[c])) for c in profile.connectors),
            sent=tuple((str(x["hormone"]), index(str(x["through"]))) for x in sent),
            received=tuple(
                (a.hormone, index(a.at), index(a.remote), tuple((index(x), index(y)) for x, y in a.path))
                for a in rec.received
                if a.at is not None and a.remote is not None
            ),
        )
    except KeyError as exc:
        raise TraceError(f"{where}: field sent: an entry without {exc}") from None
    except TopologyError as exc:
        raise TraceError(f"{where}: {exc}") from None


@dataclass(frozen=True)
class Comparison:
    """A trace against the rebuild: the alignment, the disagreements, and the trace's
    modules (index -> the name the trace gives it)."""

    alignment: Alignment
    found: list[Disagreement]
    names: dict[int, str]


def _compare(records: Sequence[TraceCycle], traffic: Traffic, rebuilt: Rebuilt) -> Comparison:
    alignment = align(traffic, rebuilt, records)
    names = {r.module: r.name for r in records}
    return Comparison(alignment, disagreements(traffic, rebuilt, records, alignment), names)


# ----------------------------------------------------------------------------- text


def _type_text(profile: Profile, type_name: str | None) -> str:
    """A type's name, and its T-number alias where it has one."""
    if type_name is None:
        return "illegal status"
    found = profile.type_by_name(type_name)
    return f"{type_name} (T{found.alias})" if found is not None and found.alias is not None else type_name


def _module_line(m: Module, rebuilt: Rebuilt, profile: Profile) -> str:
    ends = ", ".join(f"{profile.connector_name(rebuilt.connector[e])}: {describe_end(e)}" for e in m.ends)
    return f"  {m.label:<4} {ends}  [{HOW[m.grouped_by]}]"


def _snapshot_lines(s: Snapshot, start: float, profile: Profile) -> list[str]:
    lines = [f"+{s.time - start:.3f} s ({s.time:.6f}): " + "; ".join(s.changes)]
    types = {m.label: m for m in s.modules}
    for n, piece in enumerate(s.pieces, 1):
        shown = " ".join(f"{label}={_type_text(profile, types[label].type_name)}" for label in piece)
        lines.append(f"  piece {n} ({len(piece)}): {shown}")
    for m in s.modules:
        if m.type_name is None:
            lines.append(f"  {m.label}: status {profile.describe(m.status)} is not legal in {profile.name}")
    if s.silent:
        lines.append(f"  silent (cut off or stopped; traffic cannot tell): {' '.join(s.silent)}")
    return lines


def _trace_lines(compared: Comparison, start: float, profile: Profile) -> list[str]:
    alignment, found, names = compared.alignment, compared.found, compared.names
    by = "the hormones the trace sent" if alignment.how == "hormones" else "the runs' ends (no hormone to go by)"
    lines = [
        f"trace: {len(alignment.modules)} of {len(names)} modules matched to the traffic "
        f"({sum(v == 'hormones' for v in alignment.matched_by.values())} by hormones, "
        f"{sum(v == 'status' for v in alignment.matched_by.values())} by status); "
        f"clocks aligned by {by}, capture = trace {alignment.offset:+.6f} s"
    ]
    matched = (f"{names[tm]}={'+'.join(labels)}" for tm, labels in sorted(alignment.modules.items()))
    lines.append(f"  matched: {' '.join(matched)}")
    unmatched = sorted(set(names) - set(alignment.modules))
    if unmatched:
        lines.append(
            f"  not matched (no hormone or status of theirs on the capture): {' '.join(names[m] for m in unmatched)}"
        )
    if not found:
        lines.append("  every matched module's own type agrees with the traffic")
    return lines + [_disagreement_line(d, start, profile) for d in found]


def _disagreement_line(d: Disagreement, start: float, profile: Profile) -> str:
    cycles = f"cycle {d.first_cycle}" if d.first_cycle == d.last_cycle else f"cycles {d.first_cycle}-{d.last_cycle}"
    who = f"{'+'.join(d.labels)} ({d.name}, life {d.life})"
    when = f"+{d.start - start:.3f} to +{d.stop - start:.3f} s"
    shows = f"{_type_text(profile, d.shows)} {profile.describe(d.status)}"
    return f"  !! {who} {cycles}, {when}: says {_type_text(profile, d.says)}, the traffic shows {shows}"


def text_lines(capture: Path, rebuilt: Rebuilt, profile: Profile, compared: Comparison | None) -> list[str]:
    start = min(s.time for s in rebuilt.snapshots) if rebuilt.snapshots else 0.0
    lines = [
        f"{capture}: {len(rebuilt.modules)} modules, {len(rebuilt.spans)} links; cycle {rebuilt.period * 1000:.2f} ms, "
        f"liveness bound {rebuilt.bound * 1000:.1f} ms",
        "modules (labels are this tool's own, by first frame; nothing on the wire names a module):",
        *(_module_line(m, rebuilt, profile) for m in rebuilt.modules),
    ]
    for s in rebuilt.snapshots:
        lines += _snapshot_lines(s, start, profile)
    if compared is not None:
        lines += _trace_lines(compared, start, profile)
    return lines


# ----------------------------------------------------------------------------- JSON


def _end_json(e: tuple[str, int, int], rebuilt: Rebuilt, profile: Profile) -> dict[str, Any]:
    return {"medium": e[0], "link": e[1], "side": e[2], "connector": profile.connector_name(rebuilt.connector[e])}


def _snapshot_json(s: Snapshot, profile: Profile) -> dict[str, Any]:
    name = profile.connector_name
    return {
        "time": s.time,
        "changes": list(s.changes),
        "modules": [
            {
                "label": m.label,
                "type": m.type_name,
                "T": m.alias,
                "status": dict(zip(profile.connectors, map(name, m.status), strict=True)),
            }
            for m in s.modules
        ],
        "links": [
            {
                "medium": lk.key[0],
                "link": lk.key[1],
                "a": lk.a,
                "a_connector": name(lk.a_conn),
                "b": lk.b,
                "b_connector": name(lk.b_conn),
            }
            for lk in s.links
        ],
        "pieces": [list(p) for p in s.pieces],
        "silent": list(s.silent),
    }


def to_json(rebuilt: Rebuilt, profile: Profile, compared: Comparison | None) -> dict[str, Any]:
    out: dict[str, Any] = {
        "period": rebuilt.period,
        "liveness_bound": rebuilt.bound,
        "modules": [
            {"label": m.label, "grouped_by": m.grouped_by, "ends": [_end_json(e, rebuilt, profile) for e in m.ends]}
            for m in rebuilt.modules
        ],
        "snapshots": [_snapshot_json(s, profile) for s in rebuilt.snapshots],
    }
    if compared is not None:
        alignment, found = compared.alignment, compared.found
        out["trace"] = {
            "offset": alignment.offset,
            "aligned_by": alignment.how,
            "modules": {str(m): name for m, name in sorted(compared.names.items())},
            "matched": [
                {"module": tm, "labels": list(labels), "by": alignment.matched_by[tm]}
                for tm, labels in sorted(alignment.modules.items())
            ],
            "disagreements": [
                {
                    "labels": list(d.labels),
                    "module": d.module,
                    "life": d.life,
                    "name": d.name,
                    "first_cycle": d.first_cycle,
                    "last_cycle": d.last_cycle,
                    "start": d.start,
                    "stop": d.stop,
                    "says": d.says,
                    "shows": d.shows,
                    "status": dict(zip(profile.connectors, map(profile.connector_name, d.status), strict=True)),
                }
                for d in found
            ],
        }
    return out


# ----------------------------------------------------------------------------- pictures

#: Where a connector points, in degrees from the module's heading (its front); connectors
#: with other names are spread around the rest of the circle.
DIRECTIONS = {"front": 90.0, "back": 270.0, "left": 180.0, "right": 0.0}


def _angles(profile: Profile) -> dict[int, float]:
    named = {i + 1: DIRECTIONS[c] for i, c in enumerate(profile.connectors) if c in DIRECTIONS}
    rest = [i + 1 for i, c in enumerate(profile.connectors) if c not in DIRECTIONS]
    named |= {c: 45.0 + 360.0 * k / max(1, len(rest)) for k, c in enumerate(rest)}
    return named


def layout(s: Snapshot, profile: Profile) -> dict[str, tuple[float, float]]:
    """A position per module: each piece grown from its first module, a neighbour one unit
    away in the direction of the connector it hangs from (a snake vertical, head on top;
    legs to the sides), turned so that its own connector faces back; pieces side by side."""
    angles = _angles(profile)
    by_module: dict[str, list[tuple[int, str, int]]] = {}
    for lk in s.links:
        by_module.setdefault(lk.a, []).append((lk.a_conn, lk.b, lk.b_conn))
        by_module.setdefault(lk.b, []).append((lk.b_conn, lk.a, lk.a_conn))
    pos: dict[str, tuple[float, float]] = {}
    left = 0.0
    for piece in s.pieces:
        placed = _grow(piece[0], by_module, angles)
        xs = [x for x, _ in placed.values()]
        shift = left - min(xs)
        pos |= {label: (x + shift, y) for label, (x, y) in placed.items()}
        left += max(xs) - min(xs) + 2.0
    return pos


def _grow(
    root: str, by_module: dict[str, list[tuple[int, str, int]]], angles: dict[int, float]
) -> dict[str, tuple[float, float]]:
    placed: dict[str, tuple[float, float]] = {root: (0.0, 0.0)}
    heading = {root: 0.0}
    taken = {(0.0, 0.0)}
    todo = [root]
    while todo:
        here = todo.pop(0)
        x, y = placed[here]
        for mine, there, theirs in sorted(by_module.get(here, [])):
            if there in placed:
                continue
            way = heading[here] + angles[mine]
            spot = (round(x + math.cos(math.radians(way)), 6), round(y + math.sin(math.radians(way)), 6))
            while spot in taken:  # a ring or a crowded corner: step aside rather than overlap
                spot = (spot[0] + 0.35, spot[1] + 0.35)
            placed[there], heading[there] = spot, way + 180.0 - angles[theirs]
            taken.add(spot)
            todo.append(there)
    return placed


def draw(s: Snapshot, path: Path, profile: Profile, start: float) -> None:
    """One change as a picture: modules as labelled dots (label, type), links as lines with
    the connectors at each end, each piece in its colour."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pos = layout(s, profile)
    colours = plt.get_cmap("tab10")
    piece_of = {label: n for n, piece in enumerate(s.pieces) for label in piece}
    fig, ax = plt.subplots(figsize=(max(4.0, len(pos) * 0.6), 6.0))
    for lk in s.links:
        (xa, ya), (xb, yb) = pos[lk.a], pos[lk.b]
        ax.plot([xa, xb], [ya, yb], color="0.55", linewidth=2, zorder=1)
        for (x0, y0), (x1, y1), conn in (((xa, ya), (xb, yb), lk.a_conn), ((xb, yb), (xa, ya), lk.b_conn)):
            ax.text(x0 + 0.3 * (x1 - x0), y0 + 0.3 * (y1 - y0), profile.connector_name(conn), fontsize=7, ha="center")
    for m in s.modules:
        x, y = pos[m.label]
        ax.scatter([x], [y], s=500, color=colours(piece_of[m.label] % 10), zorder=2)
        ax.text(x, y, m.label, ha="center", va="center", fontsize=8, color="white", zorder=3)
        ax.text(x + 0.25, y + 0.12, _type_text(profile, m.type_name), fontsize=7, zorder=3)
    ax.set_title(f"+{s.time - start:.3f} s: {len(s.pieces)} piece(s); " + "; ".join(s.changes)[:90], fontsize=9)
    ax.set_aspect("equal")
    ax.margins(0.25)
    ax.axis("off")
    fig.savefig(path, dpi=100)
    plt.close(fig)


def draw_all(rebuilt: Rebuilt, folder: Path, profile: Profile) -> list[Path]:
    """Every snapshot drawn as ``folder/topo-NNN.png``; the paths written."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"--png-dir {folder}: cannot create it ({exc.strerror or exc})") from None
    try:
        import matplotlib  # noqa: F401 - only to say what is missing before any work
    except ImportError:
        raise ValueError("--png-dir needs matplotlib (pip install 'dh2rt[sim]', or matplotlib)") from None
    start = rebuilt.snapshots[0].time if rebuilt.snapshots else 0.0
    written = []
    for n, s in enumerate(rebuilt.snapshots):
        path = folder / f"topo-{n:03d}.png"
        draw(s, path, profile, start)
        written.append(path)
    return written


if __name__ == "__main__":
    sys.exit(main())
