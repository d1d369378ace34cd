"""Matching cost does not grow with receptors that cannot match the current state."""

from __future__ import annotations

from dh2rt.compiler import compile_source
from dh2rt.engine import Engine
from dh2rt.hormone import Arrival, Hormone
from dh2rt.profile import CONRO


def program_with_noise(noise: int) -> str:
    lines = ["const ClockCycle = 40", "hormone X(phase: A | B)", "var n = 0"]
    for i in range(noise):
        lines.append(f"hormone N{i}")
        # receptors for other types, other hormones, other timer values
        lines.append(f"receptor t{i} when T == {{T5, T6}} and H == N{i} {{ DOF1(1); keep_alive() }}")
        lines.append(f"receptor h{i} when H == N{i} {{ DOF1(2); keep_alive() }}")
        lines.append(f"receptor c{i} when T == head and LocalTimer == {1 + i % 39} {{ DOF1(3); keep_alive() }}")
    lines.append("receptor body_a when T == body and H == X(A) { V.n = V.n + 1; keep_alive() }")
    return "\n".join(lines)


def test_candidates_ignore_receptors_that_cannot_match() -> None:
    small, big = compile_source(program_with_noise(1)), compile_source(program_with_noise(300))
    body = CONRO.type_by_name("body")
    assert body is not None
    for cp in (small, big):
        cands = cp.index.candidates(body.index, 0, {"X": [["X", ("A",), (), None, 1]]})
        assert [cp.receptors[i].name for i in cands] == ["body_a"]
        assert cp.index.candidates(body.index, 0, {"X": [["X", ("B",), (), None, 1]]}) == ()  # by content
        assert cp.index.candidates(body.index, 5, {}) == ()
    head = CONRO.type_by_name("head")
    assert head is not None
    assert len(big.index.candidates(head.index, 1, {})) <= 8  # only that timer value's receptors


def test_engine_evaluates_only_candidates() -> None:
    cp = compile_source(program_with_noise(300))
    calls = 0
    receptors = list(cp.receptors)
    for i, r in enumerate(receptors):
        orig = r.match

        def counting(e, b, orig=orig):  # type: ignore[no-untyped-def]
            nonlocal calls
            calls += 1
            return orig(e, b)

        object.__setattr__(receptors[i], "match", counting)
    e = Engine(cp)
    e.link_up(1, 2)
    e.link_up(2, 1)  # a body module
    assert e.topo_type.name == "body"
    for _ in range(100):
        e.step([Arrival(1, 2, Hormone("X", ("A",)))])
    assert e.var("n") == 100
    assert calls == 100  # one evaluation per step out of 901 receptors
