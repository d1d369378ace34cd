"""The receptor index never leaves out a receptor that can match: for random states of the
example programs, the candidates it gives include every receptor whose pattern matches."""

from __future__ import annotations

import random

import pytest

from dh2rt.compiler import compile_program
from dh2rt.engine import Engine
from dh2rt.lang.parser import parse_file
from dh2rt.natives import STANDARD_NATIVES
from dh2rt.program import ACTIVE, CompiledProgram, Entry


def random_present(program: CompiledProgram, rng: random.Random) -> dict[str, list[Entry]]:
    present: dict[str, list[Entry]] = {}
    for spec in program.vocabulary.by_index:
        if rng.random() < 0.3:
            args = tuple(rng.choice(p.domain) if p.domain else rng.randrange(-3, 12) for p in spec.params)
            path = ((rng.randrange(1, 5), rng.randrange(1, 5)),)
            present.setdefault(spec.name, []).append((spec.name, args, path, None, path[0][1]))
    return present


@pytest.mark.parametrize("name", ["caterpillar.dh2", "locomotion.dh2", "legs_to_snake.dh2"])
def test_candidates_include_every_match(name: str, examples: object) -> None:
    from pathlib import Path

    ast = parse_file(Path(str(examples)) / name)
    indexed, plain = compile_program(ast), compile_program(ast, indexed=False)
    rng = random.Random(name)
    for _ in range(3000):
        t = rng.randrange(len(indexed.profile.types))
        timer = rng.randrange(indexed.clock_cycle)
        present = random_present(indexed, rng)
        cands = indexed.index.candidates(t, timer, present)
        assert list(cands) == sorted(set(cands))  # program order, no repeats
        e = Engine(plain, natives=STANDARD_NATIVES)
        e.type_index, e.timer, e.present = t, timer, present
        e.rstatus = [ACTIVE] * len(plain.receptors)
        matching = set(e.matching_receptors())
        assert matching <= set(cands), (t, timer, present)
