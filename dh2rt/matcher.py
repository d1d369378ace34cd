"""The receptor index: which receptors are worth matching in a module's state.

From each receptor's pattern the compiler derives a necessary condition, its :class:`Guard`
(:func:`derive_guard`): the topological types it can match, the LocalTimer values, the
hormones that must be present and, when a pattern names a hormone's whole content, that
content. :func:`build_index` files every receptor by type, then by hormone content, else by
hormone name, else by timer value, else as "always a candidate". An engine looks up only the
buckets of its current type, timer and present hormones (:meth:`ReceptorIndex.candidates`),
so receptors that cannot match the current state cost nothing. Matching the candidates is
the compiled closures' job; the index only has to never leave out one that could match.

This module knows patterns and indices only: no engine, no compiled program.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from dh2rt.errors import SourceSpan
from dh2rt.hormone import HormoneSpec
from dh2rt.lang import ast

Content = tuple[str, tuple[Any, ...]]


@dataclass(frozen=True, slots=True)
class Guard:
    """A necessary condition of a pattern; None means "any"."""

    types: frozenset[int] | None = None
    timers: frozenset[int] | None = None
    hormones: frozenset[str] | None = None
    #: When every way to match needs a hormone of exactly known content: (name, args) pairs.
    contents: frozenset[Content] | None = None


class PatternFacts(Protocol):
    """What deriving a guard needs of the compiler's tables."""

    @property
    def type_count(self) -> int: ...

    def type_index(self, name: str, span: SourceSpan | None) -> int: ...

    def fold(self, e: ast.Expr, binds: Mapping[str, Any]) -> int | None: ...

    def hormone_spec(self, name: str, span: SourceSpan | None) -> HormoneSpec: ...


def derive_guard(p: ast.Pattern, facts: PatternFacts) -> Guard:
    """The guard of pattern ``p``: a condition every state it matches meets."""
    if isinstance(p, ast.TypeIs):
        s = frozenset(facts.type_index(t, p.span) for t in p.types)
        if p.negate:
            s = frozenset(range(facts.type_count)) - s
        return Guard(types=s)
    if isinstance(p, ast.TimerIs) and p.op == "==":
        k = facts.fold(p.value, {})  # bound names cannot appear here with a constant result
        return Guard(timers=frozenset({k})) if k is not None else Guard()
    if isinstance(p, ast.HormoneIs) and not p.negate:
        return Guard(hormones=frozenset({p.name}), contents=exact_content(p, facts))
    if isinstance(p, ast.And):
        a, b = derive_guard(p.left, facts), derive_guard(p.right, facts)
        need = a if a.hormones is not None else b  # either side's hormone is necessary
        return Guard(
            types=_meet(a.types, b.types),
            timers=_meet(a.timers, b.timers),
            hormones=need.hormones,
            contents=need.contents,
        )
    if isinstance(p, ast.Or):
        a, b = derive_guard(p.left, facts), derive_guard(p.right, facts)
        return Guard(
            types=_join(a.types, b.types),
            timers=_join(a.timers, b.timers),
            hormones=_join(a.hormones, b.hormones),
            contents=_join(a.contents, b.contents),
        )
    return Guard()


def exact_content(p: ast.HormoneIs, facts: PatternFacts) -> frozenset[Content] | None:
    """``{(name, args)}`` when every argument of the pattern is a constant, else None."""
    spec = facts.hormone_spec(p.name, p.span)
    args: list[Any] = []
    for a, param in zip(p.args, spec.params, strict=True):
        if isinstance(a, ast.Wildcard | ast.Bind):
            return None
        if param.domain is not None and isinstance(a, ast.Name):
            args.append(a.name)
        else:
            v = facts.fold(a, {})
            if v is None:
                return None
            args.append(v)
    return frozenset({(p.name, tuple(args))})


def without_type_tests(p: ast.Pattern) -> ast.Pattern:
    """``p`` less the TypeIs conjuncts of its top-level 'and': the index files a receptor only
    under the types its pattern allows, so its compiled match need not test them again."""
    if isinstance(p, ast.TypeIs):
        return ast.TruePattern(p.span)
    if isinstance(p, ast.And):
        left, right = without_type_tests(p.left), without_type_tests(p.right)
        if isinstance(left, ast.TruePattern):
            return right
        if isinstance(right, ast.TruePattern):
            return left
        return ast.And(left, right, p.span)
    return p


def _meet(a: frozenset[Any] | None, b: frozenset[Any] | None) -> frozenset[Any] | None:
    if a is None:
        return b
    return a if b is None else a & b


def _join(a: frozenset[Any] | None, b: frozenset[Any] | None) -> frozenset[Any] | None:
    return None if a is None or b is None else a | b


@dataclass(frozen=True, slots=True)
class ReceptorIndex:
    """Receptor numbers filed by type (the outer lists are indexed by type)."""

    #: per type: the receptors filed under no timer value and no hormone
    always: list[tuple[int, ...]]
    #: per type, per LocalTimer value: the receptors filed under it
    by_timer: list[dict[int, tuple[int, ...]]]
    #: per type, per hormone name: the receptors that need it (content unknown)
    by_hormone: list[dict[str, tuple[int, ...]]]
    #: per type, per (name, args): the receptors that need exactly that hormone
    by_content: list[dict[Content, tuple[int, ...]]]
    #: base[type][timer]: the candidates when no hormone is present ("always" ones merged
    #: with that timer value's), in program order
    base: list[list[tuple[int, ...]]]
    #: quiet[type][timer]: how many cycles from this timer value on have no candidate
    #: without a hormone (None: never one for this type). A module with no mail and no
    #: periodic hormone can skip that many cycles: they would only advance LocalTimer.
    quiet: list[list[int | None]]

    def candidates(
        self, type_index: int, timer: int, present: Mapping[str, Sequence[Sequence[Any]]]
    ) -> tuple[int, ...]:
        """The receptors worth matching in this state, in declaration order.

        ``present`` maps each hormone name present to its entries (``entry[1]`` is the args).
        """
        base = self.base[type_index][timer]
        by_name, by_content = self.by_hormone[type_index], self.by_content[type_index]
        if not present or not (by_name or by_content):
            return base
        # The usual case is one bucket: return it as it is (already in program order).
        found: tuple[int, ...] = ()
        sources = 1 if base else 0
        for name, entries in present.items():
            if by_name:
                h = by_name.get(name)
                if h:
                    found += h
                    sources += 1
            if by_content:
                for entry in entries:
                    c = by_content.get((name, entry[1]))
                    if c:
                        found += c
                        sources += 1
        if sources <= 1:
            return found or base
        return tuple(sorted({*base, *found}))


def build_index(guards: Sequence[Guard], type_count: int, clock_cycle: int) -> ReceptorIndex:
    """File receptor ``i`` (whose guard is ``guards[i]``) in every bucket it may match in."""
    always: list[list[int]] = [[] for _ in range(type_count)]
    by_timer: list[dict[int, list[int]]] = [{} for _ in range(type_count)]
    by_hormone: list[dict[str, list[int]]] = [{} for _ in range(type_count)]
    by_content: list[dict[Content, list[int]]] = [{} for _ in range(type_count)]
    for i, g in enumerate(guards):
        types = sorted(g.types) if g.types is not None else range(type_count)
        for t in types:
            if g.contents is not None:
                for key in g.contents:
                    by_content[t].setdefault(key, []).append(i)
            elif g.hormones is not None:
                for h in g.hormones:
                    by_hormone[t].setdefault(h, []).append(i)
            elif g.timers is not None:
                for k in g.timers:
                    by_timer[t].setdefault(k, []).append(i)
            else:
                always[t].append(i)
    base = [
        [tuple(sorted({*always[t], *by_timer[t].get(k, ())})) for k in range(clock_cycle)] for t in range(type_count)
    ]
    return ReceptorIndex(
        always=[tuple(x) for x in always],
        by_timer=[{k: tuple(v) for k, v in d.items()} for d in by_timer],
        by_hormone=[{k: tuple(v) for k, v in d.items()} for d in by_hormone],
        by_content=[{k: tuple(v) for k, v in d.items()} for d in by_content],
        base=base,
        quiet=[_quiet_runs(row) for row in base],
    )


def _quiet_runs(row: list[tuple[int, ...]]) -> list[int | None]:
    """For each timer value, the number of consecutive values (cyclically) with no
    candidate: one pass backwards over the row twice (linear in ClockCycle)."""
    n = len(row)
    if not any(row):
        return [None] * n
    out: list[int | None] = [0] * n
    run = 0
    for k in range(2 * n - 1, -1, -1):  # the second lap carries runs across the wrap-around
        run = 0 if row[k % n] else run + 1
        if k < n:
            out[k] = run
    return out
