"""The example programs shipped inside the package (``dh2rt/programs``, the same files as the
checkout's ``examples/``), so that ``dh2rt demo`` and the launcher's default program work
from a plain ``pip install`` with no checkout around."""

from __future__ import annotations

from importlib.resources import as_file, files

from dh2rt.compiler import compile_file
from dh2rt.program import CompiledProgram

#: The programs shipped: the paper's caterpillar, legs-to-snake and one locomotion program.
BUNDLED = ("caterpillar.dh2", "legs_to_snake.dh2", "locomotion.dh2")


def compile_bundled(name: str) -> CompiledProgram:
    """Compile a shipped program from where it is installed (its ``include``s are its
    neighbours there)."""
    with as_file(files("dh2rt") / "programs") as folder:
        if name not in BUNDLED:
            raise KeyError(f"no bundled program {name!r} (bundled: {', '.join(BUNDLED)})")
        return compile_file(str(folder / name))
