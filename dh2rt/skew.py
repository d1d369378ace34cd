"""Time-skewed stepping for the in-process robot: the same lockstep cycles, in cache order.

A lockstep robot is a stencil over its link graph: module m's step at cycle c needs only
what its neighbours sent at cycle c-1. Stepping every module once per cycle, in module
order, touches the whole robot's state every few cycles; with thousands of modules that
state (about 1.5 KB a module) no longer fits in the processor's caches, and each step then
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
              band near block borders, in plain lockstep. The band falls apart into pieces
              around each border; each piece runs as soon as the blocks it lies in are done,
              while they are still in cache.

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
from collections.abc import Callable, Sequence
from dataclasses import dataclass

#: Modules per block: a block's state (about 1.5 KB a module) stays in a core's L2 cache.
#: Chosen with benchmarks/bench_caterpillar.py; 64 to 256 measure about the same.
DEFAULT_BLOCK = 128
#: Cycles per window: each module's state comes from memory once per window. 16 left
#: snake:10000 1.2-1.3x slower per module than snake:100; 64 brings it to about 1.1x.
DEFAULT_DEPTH = 64


@dataclass(frozen=True, slots=True)
class Sweep:
    """Rounds ``first, first+1, ...``: round ``first+k`` steps ``modules[:counts[k]]``."""

    first: int
    modules: tuple[int, ...]
    counts: tuple[int, ...]

    def rounds(self, window: int) -> list[tuple[int, tuple[int, ...]]]:
        """(i, modules stepping cycle t0+i) for the rounds with i < ``window``."""
        out = []
        for k, count in enumerate(self.counts[: max(0, window - self.first)]):
            out.append((self.first + k, self.modules if count == len(self.modules) else self.modules[:count]))
        return out


@dataclass(frozen=True, slots=True)
class SkewPlan:
    """Which modules step in which round of a skewed window (see the module docs)."""

    block: int
    #: the depth asked for, and the depth planned: less where blocks are too round for it
    requested: int
    depth: int
    #: in order: each block's phase 1, then the pieces of the band whose blocks are all done
    sweeps: tuple[Sweep, ...]


def connected_pieces(neighbours: Sequence[Sequence[int]], keep: Callable[[int], bool] | None = None) -> list[list[int]]:
    """The connected pieces of the modules ``keep`` accepts (all by default), linked as
    ``neighbours``: each piece breadth-first from its lowest index, pieces by lowest index."""
    seen = [False] * len(neighbours)
    pieces: list[list[int]] = []
    for start in range(len(neighbours)):
        if seen[start] or (keep is not None and not keep(start)):
            continue
        seen[start] = True
        piece, queue = [], deque([start])
        while queue:
            m = queue.popleft()
            piece.append(m)
            for k in neighbours[m]:
                if not seen[k] and (keep is None or keep(k)):
                    seen[k] = True
                    queue.append(k)
        pieces.append(piece)
    return pieces


def breadth_first_order(neighbours: Sequence[Sequence[int]]) -> list[int]:
    """Every module once, each connected piece breadth-first from its lowest index."""
    return [m for piece in connected_pieces(neighbours) for m in piece]


def make_plan(
    neighbours: Sequence[Sequence[int]], *, block: int = DEFAULT_BLOCK, depth: int = DEFAULT_DEPTH
) -> SkewPlan:
    """Plan windows of up to ``depth`` cycles over modules linked as ``neighbours``
    (``neighbours[m]``: the modules docked to m)."""
    if block < 1 or depth < 1:
        raise ValueError("block and depth must be at least 1")
    order = breadth_first_order(neighbours)
    blocks = [sorted(order[i : i + block]) for i in range(0, len(order), block)]
    in_block = [0] * len(neighbours)
    for b, members in enumerate(blocks):
        for m in members:
            in_block[m] = b
    requested = depth
    while True:
        dist = _distances_to_block_border(neighbours, blocks, in_block, depth)
        band = _band_pieces(neighbours, dist, depth)
        # Skewing needs blocks wider than the window is deep: where they are not (a block
        # of a lattice is round, a block of a snake long), the band joins into pieces as
        # big as the robot, and phase 2 would be plain lockstep. Plan shallower windows.
        if depth <= 2 or max(map(len, band), default=0) <= 2 * block:
            break
        depth //= 2
    # a piece of the band depends only on its own modules' blocks: run it right after the
    # last of them, while they are still in cache
    after: dict[int, list[list[int]]] = {}
    for piece in band:
        after.setdefault(max(in_block[m] for m in piece), []).append(piece)
    sweeps: list[Sweep] = []
    for b, members in enumerate(blocks):
        # phase 1, round i: d > i; farthest from the border first, so each round is a prefix
        inner = tuple(sorted(members, key=lambda m: -dist[m]))
        at_most = _at_most(inner, dist, depth)
        sweeps.append(Sweep(0, inner, tuple(len(inner) - at_most[i] for i in range(depth))))
        for piece in after.get(b, ()):
            # phase 2, round i: d <= i; nearest to the border first
            outer = tuple(sorted(piece, key=lambda m: (dist[m], m)))
            at_most = _at_most(outer, dist, depth)
            sweeps.append(Sweep(1, outer, tuple(at_most[i] for i in range(1, depth))))
    return SkewPlan(block, requested, depth, tuple(sweeps))


def _at_most(modules: Sequence[int], dist: Sequence[int], depth: int) -> list[int]:
    """``out[i]``: how many of ``modules`` have d <= i, for i in 0 .. depth."""
    out = [0] * (depth + 1)
    for m in modules:
        out[dist[m]] += 1
    for i in range(1, depth + 1):
        out[i] += out[i - 1]
    return out


def _distances_to_block_border(
    neighbours: Sequence[Sequence[int]], blocks: Sequence[Sequence[int]], in_block: Sequence[int], depth: int
) -> list[int]:
    """d of each module (capped at ``depth``): links to the nearest module of another block.

    A shortest way out of the block leaves it from a border module (one with a neighbour in
    another block, d = 1), so a breadth-first search inside each block from its border gives d.
    """
    dist = [depth] * len(neighbours)
    for b, members in enumerate(blocks):
        queue: deque[int] = deque()
        for m in members:
            if any(in_block[k] != b for k in neighbours[m]):
                dist[m] = 1
                queue.append(m)
        reached = set(queue)
        while queue:
            m = queue.popleft()
            if dist[m] + 1 >= depth:
                continue
            for k in neighbours[m]:
                if k not in reached and in_block[k] == b:
                    reached.add(k)
                    dist[k] = dist[m] + 1
                    queue.append(k)
    return dist


def _band_pieces(neighbours: Sequence[Sequence[int]], dist: Sequence[int], depth: int) -> list[list[int]]:
    """The connected pieces of the band (modules with d < depth).

    Phase 2 steps a band module at round i only after its band neighbours' round i-1, and
    its neighbours outside the band are done with the whole window already, so pieces with
    no link between them can be run one after the other.
    """
    return connected_pieces(neighbours, lambda m: dist[m] < depth)
