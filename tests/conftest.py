"""Shared fixtures: the examples folder and compiled example programs."""

from __future__ import annotations

from pathlib import Path

import pytest

from dh2rt.compiler import CompiledProgram, compile_file

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


@pytest.fixture(scope="session")
def examples() -> Path:
    return EXAMPLES


@pytest.fixture(scope="session")
def caterpillar() -> CompiledProgram:
    return compile_file(str(EXAMPLES / "caterpillar.dh2"))


@pytest.fixture(scope="session")
def locomotion() -> CompiledProgram:
    return compile_file(str(EXAMPLES / "locomotion.dh2"))


@pytest.fixture(scope="session")
def legs_to_snake() -> CompiledProgram:
    return compile_file(str(EXAMPLES / "legs_to_snake.dh2"))
