"""A robot's topology rebuilt from its traffic alone (sans-IO: hops in, a timeline out).

Nothing on the wire names a module. What a capture does show, per frame: the link and the
side that sent it (a *link end*), the connector it was sent through, and for hormones their
content, path and route. :class:`Traffic` keeps what the rebuild needs of each
:class:`~tools.decode.Hop`; :func:`rebuild` then works in three steps:

1. **Links over time.** Every linked connector sends one frame a cycle (a hormone, or else a
   Hello or a KeepAlive), so the cycle period is the typical interval between one end's
   frames, and a link is *up* while both its ends keep sending: a gap longer than the
   liveness bound (``silence_cycles`` + 1/2 periods) in either end's frames is a break (a
   cut, a module gone), as the modules themselves would judge it. Frames that stop within
   one bound of the capture's end are the end of the capture, not a break.
2. **Which link ends are one module** (union-find, see :func:`group_ends`), from three kinds
   of evidence, taken in this order:

   * *forwarded*: a hormone that arrived at the end R (the side opposite its sender) and
     left again from the end S with the same content, its path one hop longer and ending
     with the path it arrived with, the new hop naming R's connector as where it arrived
     (and, for a routed hormone, S's as the first of the route it arrived with): R and S
     are one module (as ``dh2rt follow`` ties hops). Certain, up to look-alike hormones in
     flight at once (a vote is then shared among the candidates);
   * *timing*: a module sends all its frames of a cycle at once, so the frames of its ends
     come in bursts: ends whose frames are (90 % of the time) within ``burst`` of each
     other's are one module's;
   * *relayed*: a hormone sent from S in the cycle after one arrived at R (the latest
     arrival at another link within the period before the send, not counting hormones
     S's own module sent: a module that sends several at once would seem to answer
     itself). Programs that answer a hormone with another (the caterpillar) show this;
     it is a correlation, so it counts only when it holds for half of S's sends or more.

   A merge never puts two ends of one connector, or both ends of one link, in one module;
   one on timing or relays never closes a ring of modules (rings are told only by hormone
   paths).
3. **Types over time.** A module's ConnectorStatus at a moment is, for each of its ends
   whose link is up, the connector at the link's other end; the profile gives its
   topological type (:meth:`~dh2rt.profile.Profile.type_of`). Each change (link up or down,
   changes closer than ``settle`` taken together) is a :class:`Snapshot`: the links, every
   module's status and type, and the pieces (connected components).

Modules are labelled ``M0``, ``M1``, ... by the first frame of any of their ends: the tool's
own labels, not the modules' names (there are none on the wire). Each says the weakest
evidence that put its ends together (``alone``: one end that nothing tied to another).

What traffic cannot show: a module with no live link (cut off and dead are both silence);
which module a re-docked connector or a restarted module belongs to when its new link ends
carried no evidence tying them to its old ones (on CAN every docking negotiates a new link:
the module then appears anew); ends that carried too little evidence (near a capture's end:
each is then a module of its own); a ring closed by timing or relays alone; a link refused
for running another program (it still looks up). On a serial capture the timestamps are the
link emulator's, which blurs the timing evidence.

**Against a trace** (:func:`align`, :func:`disagreements`): the trace's clock is mapped to the
capture's by the hormones it says were sent, each trace module to the traffic's modules by the
hormones it sent and received (then by status), and every cycle in which a module's own type
is none of those the traffic showed it within the liveness bound before is a disagreement.
"""

from __future__ import annotations

import bisect
import math
from array import array
from collections import Counter, defaultdict, deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from dh2rt.errors import TopologyError
from dh2rt.hormone import Hormone, Path
from dh2rt.liveness import SILENCE_CYCLES
from dh2rt.profile import NONE, Profile
from tools.decode import Hop

#: A link end: medium (``can`` or ``serial``), link id, side (0 or 1).
End = tuple[str, int, int]
#: A link: medium and link id.
LinkKey = tuple[str, int]
#: Frames that show a link end alive (and name its connector).
ALIVE_KINDS = frozenset({"hello", "keepalive", "hormone", "routed"})
#: Fraction of a module's sends a *relayed* tie must explain, and the fewest sends it needs.
RELAY_RATIO = 0.5
RELAY_MIN = 3
#: Frames of an end the *timing* evidence looks at (the first ones of each pair's overlap).
TIMING_SAMPLES = 4000
#: Fewest paired frames for *timing* evidence.
TIMING_MIN = 10
#: Default burst bound, as a fraction of the cycle period.
BURST_FRACTION = 0.05
#: A moment after another on a capture's clock (wall-clock seconds: a float resolves ~0.2 us).
JUST_AFTER = 1e-6


def other_end(end: End) -> End:
    medium, link, side = end
    return (medium, link, 1 - side)


def describe_end(end: End) -> str:
    medium, link, side = end
    return f"{'ir' if medium == 'serial' else 'link'} {link} side {side}"


class HormoneFrame(NamedTuple):
    """A hormone on the wire: when, from which end, and the hormone with its path."""

    time: float
    end: End
    hormone: Hormone


class Traffic:
    """What the rebuild keeps of a capture: each link end's connector and frame times (8
    bytes a frame), and every hormone frame. Feed it hops (:meth:`add`), then read it."""

    def __init__(self, profile: Profile) -> None:
        self.profile = profile
        self._index = {name: i + 1 for i, name in enumerate(profile.connectors)}
        self.connector: dict[End, int] = {}
        self._times: dict[End, array[float]] = {}
        self._hormones: list[HormoneFrame] = []
        self._ordered: tuple[dict[End, np.ndarray], list[HormoneFrame]] | None = None
        self.start: float | None = None
        self.stop: float | None = None

    def add(self, hop: Hop) -> None:
        if hop.link is None or hop.side is None or hop.kind not in ALIVE_KINDS or hop.sender is None:
            return
        connector = self._index.get(hop.sender)
        if connector is None:
            return
        end: End = (hop.medium, hop.link, hop.side)
        times = self._times.get(end)
        if times is None:
            times = self._times[end] = array("d")
            self.connector[end] = connector
        times.append(hop.time)
        self.start = hop.time if self.start is None else min(self.start, hop.time)
        self.stop = hop.time if self.stop is None else max(self.stop, hop.time)
        if hop.hormone is not None and not hop.lost:  # a lost frame never arrived anywhere
            self._hormones.append(HormoneFrame(hop.time, end, hop.hormone))
        self._ordered = None

    def extend(self, hops: Iterable[Hop]) -> Traffic:
        for hop in hops:
            self.add(hop)
        return self

    def _order(self) -> tuple[dict[End, np.ndarray], list[HormoneFrame]]:
        """Frames in time order (a capture written by several taps may be a little out of it)."""
        if self._ordered is None:
            times = {e: np.sort(np.frombuffer(t, dtype=np.float64)) for e, t in self._times.items()}
            self._ordered = (times, sorted(self._hormones, key=lambda f: f.time))
        return self._ordered

    @property
    def times(self) -> dict[End, np.ndarray]:
        """Each link end's frame times, in order."""
        return self._order()[0]

    @property
    def hormones(self) -> list[HormoneFrame]:
        """The hormone frames, in time order."""
        return self._order()[1]


# ----------------------------------------------------------------------------- the period


def estimate_period(traffic: Traffic) -> float:
    """The cycle period: the median interval between consecutive frames of one end (every
    linked connector sends one frame a cycle). ValueError when no end sent twice."""
    gaps = [np.diff(t) for t in traffic.times.values() if t.size > 1]
    if not gaps:
        raise ValueError("too few frames to tell the cycle period (no link end sent twice)")
    joined = np.concatenate(gaps)
    positive = joined[joined > 0]
    if positive.size == 0:
        raise ValueError("too few frames to tell the cycle period (all at one instant)")
    return float(np.median(positive))


# ----------------------------------------------------------------------------- links over time


def _runs(times: np.ndarray, bound: float, stop: float) -> list[tuple[float, float]]:
    """Spans of frames (in time order) with no gap longer than ``bound``; a span that ends
    within ``bound`` of ``stop`` (the capture's last frame) lasts to ``stop``."""
    if times.size == 0:
        return []
    ordered = times
    breaks = np.nonzero(np.diff(ordered) > bound)[0]
    starts = [float(ordered[0]), *(float(ordered[i + 1]) for i in breaks)]
    ends = [*(float(ordered[i]) for i in breaks), float(ordered[-1])]
    if stop - ends[-1] <= bound:
        ends[-1] = stop
    return list(zip(starts, ends, strict=True))


def _intersect(a: Sequence[tuple[float, float]], b: Sequence[tuple[float, float]]) -> list[tuple[float, float]]:
    out: list[tuple[float, float]] = []
    i = j = 0
    while i < len(a) and j < len(b):
        lo, hi = max(a[i][0], b[j][0]), min(a[i][1], b[j][1])
        if lo <= hi:
            out.append((lo, hi))
        if a[i][1] < b[j][1]:
            i += 1
        else:
            j += 1
    return out


def link_spans(traffic: Traffic, bound: float) -> dict[LinkKey, list[tuple[float, float]]]:
    """When each link was up: both its ends sending, no gap longer than ``bound``."""
    assert traffic.stop is not None
    runs = {end: _runs(t, bound, traffic.stop) for end, t in traffic.times.items()}
    spans: dict[LinkKey, list[tuple[float, float]]] = {}
    for (medium, link, side), mine in runs.items():
        if side == 0 and (medium, link, 1) in runs:
            up = _intersect(mine, runs[(medium, link, 1)])
            if up:
                spans[(medium, link)] = up
    return spans


# ----------------------------------------------------------------------------- evidence


def _pair(a: End, b: End) -> tuple[End, End]:
    return (a, b) if a <= b else (b, a)


@dataclass
class Evidence:
    """Why link ends would be one module, per pair of ends (see the module docs)."""

    forwarded: dict[tuple[End, End], float] = field(default_factory=dict)
    #: share of the sender's sends; :func:`group_ends` fills it once the bursts are known
    relayed: dict[tuple[End, End], float] = field(default_factory=dict)
    timing: dict[tuple[End, End], float] = field(default_factory=dict)  # p90 gap between bursts, s


def _may_share(traffic: Traffic, a: End, b: End) -> bool:
    """Whether ends ``a`` and ``b`` could be one module's: other links, other connectors."""
    return a[:2] != b[:2] and traffic.connector[a] != traffic.connector[b]


def _carried_on(traffic: Traffic, earlier: HormoneFrame, frame: HormoneFrame) -> bool:
    """Whether ``frame`` can be ``earlier``'s hormone carried one hop further (their
    contents and paths already match): the new hop names the connector ``earlier`` was sent
    through and the one it arrived at, and a routed hormone goes on through the first
    connector of its route, with the rest of the route."""
    sent_through, received_at = frame.hormone.path[0]
    arrived = other_end(earlier.end)
    if traffic.connector[earlier.end] != sent_through or traffic.connector.get(arrived) != received_at:
        return False
    route = earlier.hormone.route
    if route is not None and (
        not route or route[0] != traffic.connector[frame.end] or frame.hormone.route != route[1:]
    ):
        return False
    return _may_share(traffic, arrived, frame.end)


def forwarded_ties(traffic: Traffic, window: float) -> dict[tuple[End, End], float]:
    """Votes for (arrival end, sending end) pairs from hormones carried on hop by hop: the
    frame that carries a hormone on has the same content and the path it arrived with one
    hop longer, within ``window`` of its arrival. Each such frame gives one vote, shared
    among the arrivals it could continue."""
    recent: dict[tuple[str, Path], deque[HormoneFrame]] = defaultdict(deque)
    votes: dict[tuple[End, End], float] = defaultdict(float)
    for frame in traffic.hormones:
        content, path = frame.hormone.content(), frame.hormone.path
        if path:
            candidates = recent.get((content, path[1:]), ())
            arrivals = {
                other_end(e.end)
                for e in candidates
                if frame.time - window <= e.time <= frame.time and _carried_on(traffic, e, frame)
            }
            for arrived in arrivals:
                votes[_pair(arrived, frame.end)] += 1 / len(arrivals)
        bucket = recent[(content, path)]
        bucket.append(frame)
        while bucket[0].time < frame.time - window:
            bucket.popleft()
    return dict(votes)


def relayed_ties(
    traffic: Traffic, period: float, same: Callable[[End, End], bool] = lambda a, b: False
) -> dict[tuple[End, End], float]:
    """For each sending end, the share of its hormones sent within a period after a hormone
    arrived at one given end (the latest arrival elsewhere before the send). An arrival
    whose frame ``same`` says came from the sender's own module (``same(sent by, sender)``)
    is no cause: a module that sends several hormones at once would seem to answer itself."""
    frames = traffic.hormones
    times = [f.time for f in frames]
    sends: Counter[End] = Counter(f.end for f in frames)
    votes: Counter[tuple[End, End]] = Counter()
    for i, frame in enumerate(frames):
        first = bisect.bisect_left(times, frame.time - period)
        for j in range(i - 1, first - 1, -1):
            arrived = other_end(frames[j].end)
            if same(frames[j].end, frame.end):
                continue
            if arrived in traffic.connector and _may_share(traffic, arrived, frame.end):
                votes[(arrived, frame.end)] += 1
                break
    shares: dict[tuple[End, End], float] = {}
    for (arrived, sender), n in votes.items():
        if n >= RELAY_MIN and n / sends[sender] >= RELAY_RATIO:
            key = _pair(arrived, sender)
            shares[key] = max(shares.get(key, 0.0), n / sends[sender])
    return shares


def timing_ties(traffic: Traffic, burst: float) -> dict[tuple[End, End], float]:
    """For pairs of ends whose frames overlap in time, the 90th percentile of the gap from
    each frame of one to the nearest frame of the other; kept when within ``burst``."""
    arrays = traffic.times
    ends = sorted(arrays)
    out: dict[tuple[End, End], float] = {}
    for i, a in enumerate(ends):
        for b in ends[i + 1 :]:
            if not _may_share(traffic, a, b):
                continue
            ta, tb = arrays[a], arrays[b]
            lo, hi = max(ta[0], tb[0]), min(ta[-1], tb[-1])
            sample = ta[(ta >= lo) & (ta <= hi)][:TIMING_SAMPLES]
            if sample.size < TIMING_MIN or tb.size < 2:
                continue
            k = np.searchsorted(tb, sample).clip(1, tb.size - 1)
            gaps = np.minimum(np.abs(tb[k] - sample), np.abs(tb[k - 1] - sample))
            p90 = float(np.percentile(gaps, 90))
            if p90 <= burst:
                out[_pair(a, b)] = p90
    return out


# ----------------------------------------------------------------------------- grouping


@dataclass(frozen=True)
class Module:
    """A module as the traffic shows it: its label (the tool's own), its link ends, and the
    weakest evidence that put them together (``alone`` for a module of one end)."""

    label: str
    ends: tuple[End, ...]
    grouped_by: str


class _Groups:
    """Union-find over link ends, refusing merges a module cannot have. ``epochs``: the sets
    of links up together, one per change."""

    def __init__(self, traffic: Traffic, epochs: Iterable[frozenset[LinkKey]], slack: float) -> None:
        self.traffic = traffic
        self.parent: dict[End, End] = {e: e for e in traffic.connector}
        self.members: dict[End, set[End]] = {e: {e} for e in traffic.connector}
        self.how: dict[End, str] = {e: "alone" for e in traffic.connector}
        self.life = {e: (float(t[0]) - slack, float(t[-1]) + slack) for e, t in traffic.times.items()}
        self.epochs = [ep for ep in set(epochs) if ep]

    def root(self, e: End) -> End:
        while self.parent[e] != e:
            self.parent[e] = self.parent[self.parent[e]]
            e = self.parent[e]
        return e

    def _clash(self, a: End, b: End) -> bool:
        """Two ends one module cannot have: both ends of a link, or two ends of one connector
        in use at the same time (one after the other is a re-docked connector)."""
        if a[:2] == b[:2]:
            return True
        (a0, a1), (b0, b1) = self.life[a], self.life[b]
        return self.traffic.connector[a] == self.traffic.connector[b] and a0 < b1 and b0 < a1

    def _linked(self, ra: End, rb: End) -> bool:
        """Whether the modules rooted at ``ra`` and ``rb`` are joined by links up together."""
        for epoch in self.epochs:
            graph: dict[End, set[End]] = defaultdict(set)
            for medium, link in epoch:
                x, y = self.root((medium, link, 0)), self.root((medium, link, 1))
                graph[x].add(y)
                graph[y].add(x)
            seen, todo = {ra}, [ra]
            while todo:
                for nxt in graph[todo.pop()]:
                    if nxt == rb:
                        return True
                    if nxt not in seen:
                        seen.add(nxt)
                        todo.append(nxt)
        return False

    def merge(self, a: End, b: End, how: str) -> bool:
        ra, rb = self.root(a), self.root(b)
        if ra == rb:
            return False
        ma, mb = self.members[ra], self.members[rb]
        if any(self._clash(x, y) for x in ma for y in mb):
            return False
        if how != "forwarded" and self._linked(ra, rb):
            return False
        self.parent[rb] = ra
        ma |= self.members.pop(rb)
        # a module is as sure as the weakest evidence that put it together
        used = [h for h in (self.how[ra], self.how.pop(rb), how) if h != "alone"]
        self.how[ra] = max(used, key=EVIDENCE.index)
        return True


#: The kinds of evidence, strongest first.
EVIDENCE = ("forwarded", "relayed", "timing")


def group_ends(
    traffic: Traffic, evidence: Evidence, spans: Mapping[LinkKey, Sequence[tuple[float, float]]], period: float
) -> list[Module]:
    """Link ends grouped into modules (see the module docs), labelled by first frame.
    Forwarded hormones first, then frames in one burst, then relays (counted once the
    bursts are known, so that a module's own hormones are not taken for causes)."""
    assert traffic.stop is not None
    stop = traffic.stop
    epochs = (frozenset(k for k, up in spans.items() if _up(up, t, stop)) for t in _change_times(spans, stop))
    groups = _Groups(traffic, epochs, period)
    for pair, weight in sorted(evidence.forwarded.items(), key=lambda kv: -kv[1]):
        if weight >= 1:
            groups.merge(*pair, "forwarded")
    for pair in sorted(evidence.timing, key=evidence.timing.__getitem__):
        groups.merge(*pair, "timing")
    evidence.relayed = relayed_ties(traffic, period, lambda a, b: groups.root(a) == groups.root(b))
    for pair in sorted(evidence.relayed, key=lambda p: -evidence.relayed[p]):
        groups.merge(*pair, "relayed")
    first = {e: t[0] for e, t in traffic.times.items()}
    roots = sorted(groups.members, key=lambda r: min(first[e] for e in groups.members[r]))
    return [
        Module(f"M{i}", tuple(sorted(groups.members[r], key=lambda e: traffic.connector[e])), groups.how[r])
        for i, r in enumerate(roots)
    ]


# ----------------------------------------------------------------------------- snapshots


@dataclass(frozen=True)
class ModuleState:
    """A module at one moment: its ConnectorStatus (index 0 is connector 1) and its type
    (None when the status is not legal in the profile)."""

    label: str
    status: tuple[int, ...]
    type_name: str | None
    alias: int | None


@dataclass(frozen=True)
class LinkState:
    """An up link between connector ``a_conn`` of module ``a`` and ``b_conn`` of ``b``."""

    key: LinkKey
    a: str
    a_conn: int
    b: str
    b_conn: int


@dataclass(frozen=True)
class Snapshot:
    """The topology after one change (or a burst of changes closer than ``settle``)."""

    time: float
    changes: tuple[str, ...]
    modules: tuple[ModuleState, ...]  # modules with at least one link up
    links: tuple[LinkState, ...]
    pieces: tuple[tuple[str, ...], ...]  # connected components, largest first
    silent: tuple[str, ...]  # modules seen before, with no link up now


@dataclass(frozen=True)
class Rebuilt:
    """The rebuild of one capture."""

    period: float
    bound: float
    modules: tuple[Module, ...]
    spans: Mapping[LinkKey, Sequence[tuple[float, float]]]
    snapshots: tuple[Snapshot, ...]
    connector: Mapping[End, int]
    owner: Mapping[End, str]
    profile: Profile

    def ends_of(self, labels: Iterable[str]) -> tuple[End, ...]:
        wanted = set(labels)
        return tuple(e for m in self.modules if m.label in wanted for e in m.ends)

    def status_at(self, ends: Iterable[End], t: float) -> tuple[int, ...]:
        """The ConnectorStatus the traffic shows at ``t`` for a module with these link ends
        (one module's, or its incarnations': where two ends of one connector are up at
        once, the later link counts)."""
        status = [NONE] * self.profile.connector_count
        since = [-math.inf] * self.profile.connector_count
        for end in ends:
            for lo, hi in self.spans.get(end[:2], ()):
                i = self.connector[end] - 1
                if lo <= t <= hi and lo >= since[i]:
                    status[i], since[i] = self.connector[other_end(end)], lo
        return tuple(status)

    def type_at(self, ends: Iterable[End], t: float) -> str | None:
        return type_name(self.profile, self.status_at(ends, t))


def type_name(profile: Profile, status: Sequence[int]) -> str | None:
    try:
        return profile.type_of(status).name
    except TopologyError:
        return None


def _state(profile: Profile, label: str, status: tuple[int, ...]) -> ModuleState:
    try:
        t = profile.type_of(status)
    except TopologyError:
        return ModuleState(label, status, None, None)
    return ModuleState(label, status, t.name, t.alias)


def _pieces(labels: Iterable[str], links: Sequence[LinkState]) -> tuple[tuple[str, ...], ...]:
    parent = {label: label for label in labels}

    def root(x: str) -> str:
        while parent[x] != x:
            x = parent[x]
        return x

    for link in links:
        parent[root(link.a)] = root(link.b)
    pieces: dict[str, list[str]] = defaultdict(list)
    for label in parent:
        pieces[root(label)].append(label)
    ordered = sorted(pieces.values(), key=lambda p: (-len(p), _label_key(p[0])))
    return tuple(tuple(sorted(p, key=_label_key)) for p in ordered)


def _label_key(label: str) -> int:
    return int(label[1:])


def _change_times(spans: Mapping[LinkKey, Sequence[tuple[float, float]]], stop: float) -> list[float]:
    """Every moment a link comes up or goes down (a span lasting to ``stop`` does not end)."""
    moments = {lo for up in spans.values() for lo, _ in up}
    moments |= {hi for up in spans.values() for _, hi in up if hi < stop}
    return sorted(moments)


def _settled(moments: Sequence[float], settle: float) -> list[list[float]]:
    """Moments closer than ``settle`` to the previous one, taken together."""
    bursts: list[list[float]] = []
    for t in moments:
        if bursts and t - bursts[-1][-1] < settle:
            bursts[-1].append(t)
        else:
            bursts.append([t])
    return bursts


def _up(spans: Sequence[tuple[float, float]], t: float, stop: float) -> bool:
    """Up just after ``t`` (a span ending at ``t`` is down after it, unless it lasts to the end)."""
    return any(lo <= t and (t < hi or hi >= stop) for lo, hi in spans)


def snapshots(
    traffic: Traffic, modules: Sequence[Module], spans: Mapping[LinkKey, Sequence[tuple[float, float]]], settle: float
) -> tuple[Snapshot, ...]:
    """The topology after each (settled) change."""
    assert traffic.stop is not None
    stop = traffic.stop
    owner = {e: m.label for m in modules for e in m.ends}
    profile, connector = traffic.profile, traffic.connector
    out: list[Snapshot] = []
    before: set[LinkKey] = set()
    seen: set[str] = set()
    for burst in _settled(_change_times(spans, stop), settle):
        t = burst[-1]
        now = {key for key, up in spans.items() if _up(up, t, stop)}
        links = tuple(
            sorted(
                (
                    LinkState(key, owner[(*key, 0)], connector[(*key, 0)], owner[(*key, 1)], connector[(*key, 1)])
                    for key in now
                ),
                key=lambda lk: sorted((_label_key(lk.a), _label_key(lk.b))),
            )
        )
        status: dict[str, list[int]] = {}
        for link in links:
            status.setdefault(link.a, [NONE] * profile.connector_count)[link.a_conn - 1] = link.b_conn
            status.setdefault(link.b, [NONE] * profile.connector_count)[link.b_conn - 1] = link.a_conn
        seen |= status.keys()
        changes = tuple(
            sorted(f"{_link_text(key, owner, connector, profile)} up" for key in now - before)
            + sorted(f"{_link_text(key, owner, connector, profile)} down" for key in before - now)
        )
        before = now
        if not changes:
            continue
        labels = sorted(status, key=_label_key)
        out.append(
            Snapshot(
                time=burst[0],
                changes=changes,
                modules=tuple(_state(profile, label, tuple(status[label])) for label in labels),
                links=links,
                pieces=_pieces(labels, links),
                silent=tuple(sorted(seen - status.keys(), key=_label_key)),
            )
        )
    return tuple(out)


def _link_text(key: LinkKey, owner: Mapping[End, str], connector: Mapping[End, int], profile: Profile) -> str:
    a, b = sorted(((*key, 0), (*key, 1)), key=lambda e: _label_key(owner[e]))
    name = profile.connector_name
    return f"{owner[a]}.{name(connector[a])}-{owner[b]}.{name(connector[b])}"


# ----------------------------------------------------------------------------- the whole


def rebuild(
    traffic: Traffic,
    *,
    period: float | None = None,
    silence_cycles: int = SILENCE_CYCLES,
    burst: float | None = None,
    settle: float | None = None,
) -> Rebuilt:
    """The rebuild of ``traffic`` (see the module docs). ``period`` (s) is estimated from
    the beacons unless given; ``burst`` defaults to 5 % of it and ``settle`` to the
    liveness bound. ValueError when the capture has no link traffic to rebuild from."""
    if traffic.stop is None:
        raise ValueError("no link traffic in the capture (no Hello, KeepAlive or hormone on a link)")
    period = period or estimate_period(traffic)
    bound = (silence_cycles + 0.5) * period
    spans = link_spans(traffic, bound)
    evidence = Evidence(
        forwarded=forwarded_ties(traffic, 1.5 * period),
        timing=timing_ties(traffic, BURST_FRACTION * period if burst is None else burst),
    )
    modules = tuple(group_ends(traffic, evidence, spans, period))
    owner = {e: m.label for m in modules for e in m.ends}
    snaps = snapshots(traffic, modules, spans, bound if settle is None else settle)
    return Rebuilt(period, bound, modules, spans, snaps, dict(traffic.connector), owner, traffic.profile)


# ----------------------------------------------------------------------------- against a trace


@dataclass(frozen=True, slots=True)
class TraceCycle:
    """One module's cycle as its own trace tells it: what the comparison needs. ``t`` is the
    module's clock at the cycle's start (the launcher's records), None when the record has
    none (``dh2rt run``); connectors are indices, paths as :data:`dh2rt.hormone.Path`."""

    module: int
    life: int
    name: str
    cycle: int
    t: float | None
    type_name: str
    status: tuple[int, ...]
    sent: tuple[tuple[str, int], ...]  # (content, through)
    received: tuple[tuple[str, int, int, Path], ...]  # (content, at, sent through, path it arrived with)


#: A module of the trace: its index (all its lives: a restarted module is the same module).
TraceModule = int


@dataclass(frozen=True)
class Alignment:
    """How the trace's times map to the capture's (``capture = trace + offset``), how that
    was found, and which modules of the traffic each module of the trace is: one, or several
    one after another (a module that re-docks a connector gets a new link there, and unless
    hormones tied its old link end to the new one, the traffic shows a new module)."""

    offset: float
    how: str  # "hormones" (the trace's sends found in the capture) or "end" (the runs' last moments)
    modules: Mapping[TraceModule, tuple[str, ...]]
    matched_by: Mapping[TraceModule, str]  # "hormones" or "status"


@dataclass(frozen=True)
class Disagreement:
    """Consecutive cycles in which a module's own type was not what the traffic showed, at
    any moment within the liveness bound before (the module may lag that much)."""

    labels: tuple[str, ...]
    module: TraceModule
    life: int
    name: str
    first_cycle: int
    last_cycle: int
    start: float  # capture time
    stop: float
    says: str
    shows: str | None
    status: tuple[int, ...]  # what the traffic showed at ``start``


class _FrameIndex:
    """The capture's hormone frames by (content, connector sent through), in time order."""

    def __init__(self, traffic: Traffic) -> None:
        by_key: dict[tuple[str, int], list[HormoneFrame]] = defaultdict(list)
        for f in traffic.hormones:
            by_key[(f.hormone.content(), traffic.connector[f.end])].append(f)
        self.frames = dict(by_key)
        self.times = {k: [f.time for f in v] for k, v in by_key.items()}

    def between(self, key: tuple[str, int], lo: float, hi: float) -> list[HormoneFrame]:
        times = self.times.get(key)
        if not times:
            return []
        return self.frames[key][bisect.bisect_left(times, lo) : bisect.bisect_right(times, hi)]

    def nearest(self, key: tuple[str, int], at: float, within: float) -> HormoneFrame | None:
        """The frame of ``key`` nearest to ``at``, if one is ``within`` of it."""
        found = self.between(key, at - within, at + within)
        return min(found, key=lambda f: abs(f.time - at)) if found else None


def trace_time(rec: TraceCycle, period: float) -> float:
    """A record's time on the trace's clock: its ``t``, or else its cycle times the period."""
    return rec.t if rec.t is not None else rec.cycle * period


#: How far from where the trace puts it a hormone's frame may be, in cycles, once aligned.
NEAR = 0.1


def _matched(
    index: _FrameIndex, sends: Sequence[tuple[float, tuple[str, int]]], offset: float, within: float
) -> list[float]:
    """For each send the trace tells of that has a frame of its hormone and connector within
    ``within`` of its time (shifted by ``offset``), how far off that frame is."""
    out = []
    for t, key in sends:
        frame = index.nearest(key, t + offset, within)
        if frame is not None:
            out.append(frame.time - t - offset)
    return out


def align_offset(traffic: Traffic, records: Sequence[TraceCycle], period: float) -> tuple[float, str]:
    """``capture time = trace time + offset``: the offset under which the most hormones the
    trace says were sent are on the capture next to their cycle's start (the candidates are
    the commonest time differences between a send and a frame of its hormone and connector);
    without any, the offset that ends both together."""
    assert traffic.stop is not None
    index = _FrameIndex(traffic)
    sends = [(trace_time(r, period), key) for r in records for key in r.sent if key in index.times]
    end = traffic.stop - max(trace_time(r, period) for r in records)
    if not sends:
        return end, "end"
    step = max(1, len(sends) // 200)
    diffs = np.array([f - t for t, key in sends[::step] for f in index.times[key]])
    bins = np.round(diffs / (NEAR * period))
    values, counts = np.unique(bins, return_counts=True)
    candidates = [float(np.median(diffs[bins == v])) for v in values[np.argsort(-counts, kind="stable")[:10]]]
    within = NEAR * period
    best = max(candidates, key=lambda c: (len(_matched(index, sends, c, within)), -abs(c - end)))
    off = _matched(index, sends, best, within)
    if not off:
        return end, "end"
    return best + float(np.median(off)), "hormones"


def _hormone_votes(
    traffic: Traffic, rebuilt: Rebuilt, records: Sequence[TraceCycle], offset: float
) -> dict[TraceModule, Counter[str]]:
    """Per trace module, the traffic modules whose ends sent the hormones it says it sent
    (the frame nearest to when it says so) and received those it says it received (the
    latest such frame, same path, at that connector, in the cycle before)."""
    index, period = _FrameIndex(traffic), rebuilt.period
    votes: dict[TraceModule, Counter[str]] = defaultdict(Counter)
    for rec in records:
        x = trace_time(rec, period) + offset
        who: set[str] = set()
        for key in rec.sent:
            frame = index.nearest(key, x, NEAR * period)
            if frame is not None:
                who.add(rebuilt.owner[frame.end])
        for content, at, remote, path in rec.received:
            arrivals = [
                other_end(f.end)
                for f in index.between((content, remote), x - (1 + NEAR) * period, x + NEAR * period)
                if f.hormone.path == path and traffic.connector.get(other_end(f.end)) == at
            ]
            if arrivals and arrivals[-1] in rebuilt.owner:
                who.add(rebuilt.owner[arrivals[-1]])
        for label in who:
            votes[rec.module][label] += 1
    return votes


def _status_votes(rebuilt: Rebuilt, records: Sequence[TraceCycle], offset: float) -> dict[TraceModule, Counter[str]]:
    """Per trace module, in how many of its cycles each traffic module had its status."""
    votes: dict[TraceModule, Counter[str]] = defaultdict(Counter)
    for rec in records:
        x = trace_time(rec, rebuilt.period) + offset
        for m in rebuilt.modules:
            if rebuilt.status_at(m.ends, x) == rec.status:
                votes[rec.module][m.label] += 1
    return votes


def _ranked(votes: Mapping[TraceModule, Counter[str]]) -> list[tuple[TraceModule, str]]:
    ranked = sorted(((n, tm, label) for tm, c in votes.items() for label, n in c.items()), key=lambda v: -v[0])
    return [(tm, label) for _, tm, label in ranked]


def _lifetimes(traffic: Traffic, rebuilt: Rebuilt) -> dict[End, tuple[float, float]]:
    return {e: (float(traffic.times[e][0]), float(traffic.times[e][-1])) for m in rebuilt.modules for e in m.ends}


def _fits(rebuilt: Rebuilt, life: Mapping[End, tuple[float, float]], mine: Sequence[str], label: str) -> bool:
    """Whether module ``label`` can be a later (or earlier) part of the module whose parts
    are ``mine``: none of its ends uses a connector one of theirs uses at the same time."""
    slack = rebuilt.bound
    for e in rebuilt.ends_of([label]):
        for f in rebuilt.ends_of(mine):
            overlap = min(life[e][1], life[f][1]) - max(life[e][0], life[f][0])
            if rebuilt.connector[e] == rebuilt.connector[f] and overlap > slack:
                return False
    return True


def align(traffic: Traffic, rebuilt: Rebuilt, records: Sequence[TraceCycle]) -> Alignment:
    """The offset between the trace's clock and the capture's, and which traffic modules
    each trace module is: one by one, most votes first, by the hormones it sent and received
    where the capture has them; then the traffic modules left over go to the trace module
    most of their hormones pointed to, when they fit (another time, or other connectors);
    then trace modules still unmatched by the status they had in most of their cycles (a
    module whose status is wrong most of the time stays unmatched)."""
    offset, how = align_offset(traffic, records, rebuilt.period)
    votes = _hormone_votes(traffic, rebuilt, records, offset)
    out: dict[TraceModule, list[str]] = {}
    taken: set[str] = set()
    for tm, label in _ranked(votes):
        if tm not in out and label not in taken:
            out[tm] = [label]
            taken.add(label)
    life = _lifetimes(traffic, rebuilt)
    for tm, label in _ranked(votes):
        if tm in out and label not in taken and _fits(rebuilt, life, out[tm], label):
            out[tm].append(label)
            taken.add(label)
    matched_by = dict.fromkeys(out, "hormones")
    _complete(rebuilt, life, records, offset, out, taken)
    cycles = Counter(r.module for r in records)
    rest = [r for r in records if r.module not in out]
    status = {
        tm: Counter({k: n for k, n in c.items() if 2 * n >= cycles[tm]})
        for tm, c in _status_votes(rebuilt, rest, offset).items()
    }
    for tm, label in _ranked(status):
        if tm not in out and label not in taken:
            out[tm] = [label]
            taken.add(label)
            matched_by[tm] = "status"
    ordered = {tm: tuple(sorted(labels, key=_label_key)) for tm, labels in out.items()}
    return Alignment(offset, how, ordered, matched_by)


def _complete(
    rebuilt: Rebuilt,
    life: Mapping[End, tuple[float, float]],
    records: Sequence[TraceCycle],
    offset: float,
    out: dict[TraceModule, list[str]],
    taken: set[str],
) -> None:
    """Traffic modules no hormone pointed to (ends the rebuild could not tie, such as links
    that came up just before the capture ended) go to the matched trace module whose own
    status they complete in the most of its cycles, if any."""
    by_module: dict[TraceModule, list[TraceCycle]] = defaultdict(list)
    for rec in records:
        by_module[rec.module].append(rec)
    for m in rebuilt.modules:
        if m.label in taken:
            continue
        lo, hi = min(life[e][0] for e in m.ends), max(life[e][1] for e in m.ends)
        best: tuple[int, TraceModule] | None = None
        for tm, labels in out.items():
            if not _fits(rebuilt, life, labels, m.label):
                continue
            mine = rebuilt.ends_of(labels)
            gain = 0
            for rec in by_module[tm]:
                x = trace_time(rec, rebuilt.period) + offset
                if lo - rebuilt.period <= x <= hi:  # a link may come up within the cycle
                    x = min(max(x, lo), hi)
                    gain += (rebuilt.status_at((*mine, *m.ends), x) == rec.status) - (
                        rebuilt.status_at(mine, x) == rec.status
                    )
            if gain > 0 and (best is None or gain > best[0]):
                best = (gain, tm)
        if best is not None:
            out[best[1]].append(m.label)
            taken.add(m.label)


def _types_between(rebuilt: Rebuilt, ends: Sequence[End], lo: float, hi: float) -> set[str | None]:
    """Every type the traffic showed for a module with these ends from ``lo`` to ``hi``."""
    moments = {lo}
    for end in ends:
        for a, b in rebuilt.spans.get(end[:2], ()):
            moments |= {t for t in (a, b + JUST_AFTER) if lo < t <= hi}
    return {rebuilt.type_at(ends, t) for t in moments}


def disagreements(
    traffic: Traffic, rebuilt: Rebuilt, records: Sequence[TraceCycle], alignment: Alignment
) -> list[Disagreement]:
    """Every stretch of cycles in which a matched module's own type was none of the types
    the traffic showed it from the liveness bound (plus two cycles) before its cycle to half
    a cycle after. Cycles before the module's first frame on the capture are not judged."""
    period, grace = rebuilt.period, rebuilt.bound + 2 * rebuilt.period
    open_: dict[TraceModule, Disagreement] = {}
    out: list[Disagreement] = []
    for rec in sorted(records, key=lambda r: (r.module, r.life, r.cycle)):
        tm = rec.module
        labels = alignment.modules.get(tm)
        if labels is None:
            continue
        ends = rebuilt.ends_of(labels)
        x = trace_time(rec, period) + alignment.offset
        if x < min(traffic.times[e][0] for e in ends) + grace or x > (traffic.stop or x):
            continue
        if rec.type_name in _types_between(rebuilt, ends, x - grace, x + period / 2):
            if tm in open_:
                out.append(open_.pop(tm))
            continue
        seen = open_.get(tm)
        if seen is not None and seen.says == rec.type_name and seen.life == rec.life:
            open_[tm] = replace(seen, last_cycle=rec.cycle, stop=x)
            continue
        if seen is not None:
            out.append(open_.pop(tm))
        status = rebuilt.status_at(ends, x)
        shows = type_name(rebuilt.profile, status)
        open_[tm] = Disagreement(
            labels, tm, rec.life, rec.name, rec.cycle, rec.cycle, x, x, rec.type_name, shows, status
        )
    out.extend(open_.values())
    return sorted(out, key=lambda d: (d.start, d.module))
