"""Marks that sort a sweep between `make test` and `make test-long`.

`make test` keeps at least one case of each feature and topology; the rest of a long sweep
(many seeds, many instants, whole reconfigurations) is marked ``long`` and runs in
`make test-long` (tests/conftest.py)."""

from __future__ import annotations

from collections.abc import Collection, Iterable
from typing import Any

import pytest

LONG = pytest.mark.long


def sweep(cases: Iterable[Any], keep: Collection[int] = (0,)) -> list[Any]:
    """``cases`` for ``pytest.mark.parametrize``: those at the indexes in ``keep`` as they are,
    every other marked ``long``. A case that is a tuple gives one value per argument name
    (as parametrize takes it with several names)."""
    out: list[Any] = []
    for i, case in enumerate(cases):
        if i in keep:
            out.append(case)
        elif isinstance(case, type(pytest.param(None))):
            out.append(pytest.param(*case.values, marks=[*case.marks, LONG], id=case.id))
        else:
            out.append(pytest.param(*(case if isinstance(case, tuple) else (case,)), marks=LONG))
    return out
