"""Time-skewed stepping for the in-process robot: the same lockstep cycles, in cache order.

A lockstep robot is a stencil over its link graph: module m's step at cycle c needs only
what its neighbours sent at cycle c-1. Stepping every module once per cycle, in module
order, touches the whole robot's state every few cycles; with thousands of modules that
state (about 2 KB a module) no longer fits in the processor's caches, and each step then
waits on memory. This is the classic stencil problem, and the classic cure applies: time
skewing (Wolf & Lam's loop skewing; Wonnacott's time-skewed tiling of stencils).

A :class:`SkewPlan` cuts the modules into blocks of neighbouring modules (runs of a
breadth-first order over the links) and gives each module its distance to the outside of
its block, ``d`` (the number of links to the nearest module not in the block; a piece of the
robot that lies wholly inside a block never depends on anything outside it). Over a window
of W cycles starting at t0:

    phase 1   block by block, for i = 0 .. W-1: step cycle t0+i of each module with d > i.
              A module with d > i has neighbours with d >= i, all of which have done cycle
              t0+i-1 already (in this block's round i-1, or at t0 if i = 0), so its mail is
              complete; each block's state is reused W times while it is in cache.
    phase 2   for i = 1 .. W-1: step cycle t0+i of each module with d <= i, the lagging
              band near block borders, in plain lockstep.

After both phases every module has done cycles t0 .. t0+W-1 exactly once, each with
exactly the mail lockstep would have given it: neighbours' cycles never differ by more
than one, so no mail is ever consumed early or late. The robot checks the equivalence
(``tests/dh2rt/test_skew.py`` runs both ways and compares every module's state). A window
needs the world to hold still: no events, no scheduled actions and no native actions (their
effects act on the world at one given cycle); :meth:`dh2rt.robot.Robot.advance` falls back
to plain steps otherwise.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

#: Modules per block: a block's engines (about 2 KB each) stay within a core's L2 cache.
DEFAULT_BLOCK = 256
#: Cycles per window: each block's state is reused this many times per visit.
DEFAULT_DEPTH = 16


@dataclass(frozen=True, slots=True)
class SkewPlan:
    """Which modules step in which round of a skewed window (see the module docs)."""

    block: int
    depth: int
    #: per block, per round i (0 .. depth-1): the block's modules with d > i, in index order
    rounds: tuple[tuple[tuple[int, ...], ...], ...]
    #: per round i (0 .. depth-1): the modules with d <= i, in index order (empty for i = 0)
    band: tuple[tuple[int, ...], ...]


def breadth_first_order(neighbours: Sequence[Sequence[int]]) -> list[int]:
    """Every module once, each connected piece breadth-first from its lowest index."""
    seen = [False] * len(neighbours)
    order: list[int] = []
    for start in range(len(neighbours)):
        if seen[start]:
            continue
        seen[start] = True
        queue = deque([start])
        while queue:
            m = queue.popleft()
            order.append(m)
            for k in neighbours[m]:
                if not seen[k]:
                    seen[k] = True
                    queue.append(k)
    return order


def make_plan(
    neighbours: Sequence[Sequence[int]], *, block: int = DEFAULT_BLOCK, depth: int = DEFAULT_DEPTH
) -> SkewPlan:
    """Plan windows of up to ``depth`` cycles over modules linked as ``neighbours``
    (``neighbours[m]``: the modules docked to m)."""
    if block < 1 or depth < 1:
        raise ValueError("block and depth must be at least 1")
    order = breadth_first_order(neighbours)
    in_block = [0] * len(neighbours)
    blocks = [order[i : i + block] for i in range(0, len(order), block)]
    for b, members in enumerate(blocks):
        for m in members:
            in_block[m] = b
    dist = [depth] * len(neighbours)  # d capped at depth: rounds beyond it do not exist
    rounds: list[tuple[tuple[int, ...], ...]] = []
    for b, members in enumerate(blocks):
        # multi-source breadth-first search inside the block from its border (d = 1)
        queue: deque[int] = deque()
        for m in members:
            if any(in_block[k] != b for k in neighbours[m]):
                dist[m] = 1
                queue.append(m)
        reached = set(queue)
        while queue:
            m = queue.popleft()
            if dist[m] >= depth:
                continue
            for k in neighbours[m]:
                if k not in reached and in_block[k] == b:
                    reached.add(k)
                    dist[k] = dist[m] + 1
                    queue.append(k)
        ordered = sorted(members)
        rounds.append(tuple(tuple(m for m in ordered if dist[m] > i) for i in range(depth)))
    everyone = range(len(neighbours))
    band = tuple(tuple(m for m in everyone if dist[m] <= i) for i in range(depth))
    return SkewPlan(block, depth, tuple(rounds), band)
