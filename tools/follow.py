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

Where a branch ends at a module, that module may answer with a hormone of its own (the
caterpillar's module takes X(A) and sends X(B) on through its back, Table I's wave): with
``--chain`` (the default) the journey goes on through the hormone that module sent first
within ANSWER_CYCLES cycles after the arrival, through another of its link ends (a module
answers in its next cycle, at most a period later, plus however late that cycle began). Which link
ends are one module comes from the traffic alone (:mod:`tools.topology_rebuild`: hormones
forwarded, frames sent in one burst, hormones answered), so this is what the capture shows,
not a module's name; each module is visited once.

Exit codes: 0 found and followed, 1 the program's hormone is not in the capture (none sent
there, on that link, at or after that time), 2 bad input (HORMONE malformed or not one of the
program's, named with the reason), 130 Ctrl-C.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from dh2rt.cmdline import EXIT_FAIL, EXIT_OK, EXIT_USAGE, err
from dh2rt.errors import CaptureError, OptionError
from dh2rt.hormone import Path as HormonePath
from tools.decode import Hop
from tools.reading import PROGRAM_HELP, interruptible, options_and_capture
from tools.topology_rebuild import Rebuilt, Traffic, rebuild

#: How long after a hormone reached a module its answer may come, in the robot's periods: the
#: module reads it at its next cycle start (up to a period later) and answers in that cycle; a
#: loaded machine starts cycles late (1.5 missed answers from a module held half a period).
ANSWER_CYCLES = 2.0


@dataclass
class Step:
    hop: Hop
    depth: int
    latency: float | None  # seconds since the hop it continues
    next: list[Step] = field(default_factory=list)
    #: where the branch ended at a module: the module (the rebuild's label) and the journey
    #: of the hormone it sent in answer
    module: str | None = None
    answer: Step | None = None


def _matches(hop: Hop, wanted: str) -> bool:
    return hop.hormone is not None and (hop.hormone.name == wanted or hop.hormone.content() == wanted)


def follow(hops: Sequence[Hop], wanted: str, at: float, link: int | None = None) -> Step | None:
    """The journey of the first ``wanted`` hormone sent fresh at or after ``at`` (on ``link``
    when given)."""
    first = next(
        (
            h for h in hops
            if h.time >= at and _matches(h, wanted) and h.hormone and not h.hormone.path
            and (link is None or h.link == link)
        ),
        None,
    )  # fmt: skip
    if first is None or first.hormone is None:
        return None
    return journey(hops, first)


def journey(hops: Sequence[Hop], first: Hop) -> Step:
    """The journey of the hormone ``first`` carries, hop by hop by its growing path."""
    assert first.hormone is not None
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


def chain(hops: Sequence[Hop], root: Step, rebuilt: Rebuilt, window: float, visited: set[str] | None = None) -> None:
    """Where a branch of ``root`` ends at a module, the hormone that module sent first within
    ``window`` s of the arrival through another of its link ends, followed in turn (see the
    module docs). Each module is answered for once."""
    visited = set() if visited is None else visited
    for leaf in _leaves(root):
        h = leaf.hop
        arrived = (h.medium, h.link, 1 - h.side) if h.link is not None and h.side is not None else None
        module = rebuilt.owner.get(arrived) if arrived is not None else None
        if module is None or module in visited:
            continue
        visited.add(module)
        leaf.module = module
        ends = {e for m in rebuilt.modules if m.label == module for e in m.ends} - {arrived}
        answer = next(
            (
                x for x in hops
                if h.time < x.time <= h.time + window and x.hormone is not None and not x.hormone.path
                and (x.medium, x.link, x.side) in ends
            ),
            None,
        )  # fmt: skip
        if answer is not None:
            leaf.answer = journey(hops, answer)
            leaf.answer.latency = answer.time - h.time
            chain(hops, leaf.answer, rebuilt, window, visited)


def _leaves(step: Step) -> list[Step]:
    if not step.next:
        return [step]
    return [leaf for nxt in step.next for leaf in _leaves(nxt)]


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
    elif step.answer is not None and step.answer.hop.hormone is not None:
        answer = step.answer
        assert answer.latency is not None and answer.hop.hormone is not None
        out.append(
            f"{indent}  reached {step.module}, which answered {answer.hop.hormone.content()} "
            f"+{answer.latency * 1000:.1f} ms later:"
        )
        _lines(answer, max_hops, names, out)
    else:
        out.append(f"{indent}  ended: at the module it reached (bound there, or no link to go on)")


@interruptible
def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="dh2rt follow", description="Follow one hormone through a capture, hop by hop, and say where it ended."
    )
    p.add_argument("capture", type=Path)
    p.add_argument("hormone", help="NAME or its content NAME(args), e.g. LTS or X(A)")
    p.add_argument("--program", type=Path, help=PROGRAM_HELP)
    p.add_argument("--at", type=float, default=0.0, help="follow the first one sent at or after this time (s)")
    p.add_argument("--link", type=int, help="follow the first one sent on this link")
    p.add_argument("--json", action="store_true", help="the journey as JSON")
    p.add_argument(
        "--no-chain",
        dest="chain",
        action="store_false",
        help="stop where the hormone stops (do not go on through the hormone each module it reached sent in answer)",
    )
    started = options_and_capture(p, argv)
    if isinstance(started, int):
        return started
    ns, capture = started
    program = capture.program
    try:
        wanted = capture.hormone(ns.hormone, "HORMONE")
        hops = [h for h in capture.hops() if h.hormone]
    except (CaptureError, OptionError) as exc:
        err(str(exc))
        return EXIT_USAGE
    root = follow(hops, wanted, ns.at, ns.link)
    if root is None:
        where = "" if ns.link is None else f" on link {ns.link}"
        err(f"{ns.capture}: no {ns.hormone} sent{where} at or after {ns.at} s")
        return EXIT_FAIL
    if ns.chain:
        try:
            rebuilt = rebuild(Traffic(program.profile).extend(capture.hops()))
        except (CaptureError, ValueError) as exc:
            err(f"{ns.capture}: cannot tell which link ends are one module ({exc}); try --no-chain")
            return EXIT_USAGE
        chain(hops, root, rebuilt, ANSWER_CYCLES * rebuilt.period)
    if ns.json:

        def tree(step: Step) -> dict[str, object]:
            out = {**step.hop.to_json(), "latency": step.latency, "next": [tree(s) for s in step.next]}
            if step.answer is not None:
                out["module"] = step.module
                out["answer"] = tree(step.answer)
            return out

        print(json.dumps(tree(root)))
        return EXIT_OK
    assert root.hop.hormone is not None
    print(f"{root.hop.hormone.content()} from {root.hop.time:.6f} s:")
    lines: list[str] = []
    _lines(root, program.max_hops, program.profile.connectors, lines)
    print("\n".join(lines))
    return EXIT_OK
