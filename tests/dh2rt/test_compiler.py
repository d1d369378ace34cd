"""The compiler proper: what it makes of a program (statuses, guards, natives, constants)."""

from __future__ import annotations

import pytest

from dh2rt.compiler import compile_program, compile_source
from dh2rt.errors import ProgramCompileError
from dh2rt.lang.parser import parse
from dh2rt.matcher import Guard
from dh2rt.profile import CONRO
from dh2rt.program import ReceptorStatus

SOURCE = """program c
const ClockCycle = 12
const Quarter = ClockCycle / 4
hormone X(p: A | B)
hormone N(n: int)
receptor a when T == T1 and LocalTimer == Quarter { DOF1(1) }
receptor b passive when H == X(A) { DOF1(2) }
receptor c absent when T == {body, tail} and H == X(?p) { DOF1(3) }
receptor d when H == N(7) or H == N(8) { DOF1(4) }
receptor e when T != T1 { DOF1(5) }
"""


def test_statuses_are_an_intenum() -> None:
    cp = compile_source(SOURCE)
    assert [r.initial for r in cp.receptors] == [
        ReceptorStatus.ACTIVE,
        ReceptorStatus.PASSIVE,
        ReceptorStatus.ABSENT,
        ReceptorStatus.ACTIVE,
        ReceptorStatus.ACTIVE,
    ]
    assert [int(s) for s in ReceptorStatus] == [-1, 0, 1]


def test_guards_are_necessary_conditions() -> None:
    cp = compile_source(SOURCE)
    g = {r.name: r.guard for r in cp.receptors}
    head = CONRO.type_by_name("head")
    body, tail = CONRO.type_by_name("body"), CONRO.type_by_name("tail")
    assert head is not None and body is not None and tail is not None
    assert g["a"] == Guard(types=frozenset({head.index}), timers=frozenset({3}))  # Quarter folded
    assert g["b"] == Guard(hormones=frozenset({"X"}), contents=frozenset({("X", ("A",))}))
    assert g["c"] == Guard(types=frozenset({body.index, tail.index}), hormones=frozenset({"X"}))
    assert g["d"].contents == frozenset({("N", (7,)), ("N", (8,))})
    assert g["e"].types == frozenset(range(len(CONRO.types))) - {head.index}


def test_unindexed_compilation_files_every_receptor_everywhere() -> None:
    cp = compile_program(parse(SOURCE), indexed=False)
    assert all(r.guard == Guard() for r in cp.receptors)
    assert all(cp.index.base[t][k] == (0, 1, 2, 3, 4) for t in range(len(CONRO.types)) for k in range(12))


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        ("receptor f when LocalTimer == 12 { DOF1(1) }", "LocalTimer never equals 12"),
        ("receptor f { V.nope = 1 }", "undefined variable V.nope"),
        ("receptor f { DOF1(Nope) }", "undefined name 'Nope'"),
        ("receptor f when H == X(C) { DOF1(1) }", "'C' is not a value of X.p"),
        ("receptor f { inhibit zz }", "unknown receptor 'zz'"),
        ("receptor a { DOF1(1) }", "receptor 'a' is declared twice"),
    ],
)
def test_semantic_errors_name_the_culprit(extra: str, words: str) -> None:
    with pytest.raises(ProgramCompileError, match=words) as info:
        compile_source(SOURCE + extra + "\n", "c.dh2")
    assert str(info.value).startswith("c.dh2:11:")
