"""``dh2rt follow CAPTURE HORMONE [--at TIME]``: one hormone's journey,
hop by hop, and where it ended.

A hormone's path grows by one (sent through, received at) pair per hop, newest first, and no
module renames it: the frame that carries it one hop further has the same content and a path
one hop longer that ends with the path it arrived with. That is what ties the hops together
here, with no module names (there are none on the wire). HORMONE is ``NAME`` or its content
``NAME(args)``; the first one sent with an empty path at or after ``--at`` (seconds, as the
capture's clock) is followed. Where it ended, per branch: forwarded on (a later hop was
seen), stopped by the hop limit (its path reached the program's ``max_hops``), or ended at a
module (bound there, or no link to go on; a CAN capture cannot tell the two apart).

Exit codes: 0 found and followed, 1 no such hormone in the capture, 2 bad input.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from dh2rt.cmdline import EXIT_FAIL, EXIT_OK, EXIT_USAGE, err
from dh2rt.errors import CaptureError
from dh2rt.hormone import Path as HormonePath
from tools.decode import Hop
from tools.reading import PROGRAM_HELP, options_and_capture


@dataclass
class Step:
    hop: Hop
    depth: int
    latency: float | None  # seconds since the hop it continues
    next: list[Step] = field(default_factory=list)


def _matches(hop: Hop, wanted: str) -> bool:
    return hop.hormone is not None and (hop.hormone.name == wanted or hop.hormone.content() == wanted)


def follow(hops: Sequence[Hop], wanted: str, at: float) -> Step | None:
    """The journey of the first ``wanted`` hormone sent fresh at or after ``at``."""
    first = next(
        (h for h in hops if h.time >= at and _matches(h, wanted) and h.hormone and not h.hormone.path), None
    )
    if first is None or first.hormone is None:
        return None
    root = Step(first, 0, None)
    frontier: dict[HormonePath, Step] = {first.hormone.path: root}
    content = first.hormone.content()
    for h in hops:
        if h.time <= first.time or h.hormone is None or h.hormone.content() != content or not h.hormone.path:
            continue
        parent = frontier.get(h.hormone.path[1:])
        if parent is None:
            continue
        step = Step(h, parent.depth + 1, h.time - parent.hop.time)
        parent.next.append(step)
        frontier[h.hormone.path] = step
    return root


def _lines(step: Step, max_hops: int, names: Sequence[str], out: list[str]) -> None:
    h = step.hop
    latency = "" if step.latency is None else f"  +{step.latency * 1000:.1f} ms"
    indent = "  " * step.depth
    out.append(f"{indent}hop {step.depth}: {h.time:.6f}  link {h.link} side {h.side}  sent via {h.sender}{latency}")
    if step.next:
        for nxt in step.next:
            _lines(nxt, max_hops, names, out)
        return
    assert h.hormone is not None
    if len(h.hormone.path) + 1 >= max_hops:
        out.append(f"{indent}  ended: stopped by the hop limit (max_hops {max_hops})")
    else:
        out.append(f"{indent}  ended: at the module it reached (bound there, or no link to go on)")


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="dh2rt follow", description="Follow one hormone through a capture, hop by hop, and say where it ended."
    )
    p.add_argument("capture", type=Path)
    p.add_argument("hormone", help="NAME or its content NAME(args), e.g. LTS or X(A)")
    p.add_argument("--program", type=Path, help=PROGRAM_HELP)
    p.add_argument("--at", type=float, default=0.0, help="follow the first one sent at or after this time (s)")
    p.add_argument("--json", action="store_true", help="the journey as JSON")
    started = options_and_capture(p, argv)
    if isinstance(started, int):
        return started
    ns, capture = started
    program = capture.program
    try:
        hops = [h for h in capture.hops() if h.hormone]
    except CaptureError as exc:
        err(str(exc))
        return EXIT_USAGE
    root = follow(hops, ns.hormone, ns.at)
    if root is None:
        err(f"{ns.capture}: no {ns.hormone} sent at or after {ns.at} s")
        return EXIT_FAIL
    if ns.json:

        def tree(step: Step) -> dict[str, object]:
            return {**step.hop.to_json(), "latency": step.latency, "next": [tree(s) for s in step.next]}

        print(json.dumps(tree(root)))
        return EXIT_OK
    assert root.hop.hormone is not None
    print(f"{root.hop.hormone.content()} from {root.hop.time:.6f} s:")
    lines: list[str] = []
    _lines(root, program.max_hops, program.profile.connectors, lines)
    print("\n".join(lines))
    return EXIT_OK
