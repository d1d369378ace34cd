"""The six packages come from this checkout, and the core imports nothing heavy."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("package", ["dh2rt", "drivers", "firmware", "sim", "tools", "hil"])
def test_packages_import_from_the_checkout(package: str) -> None:
    mod = importlib.import_module(package)
    assert mod.__file__ is not None
    assert Path(mod.__file__).resolve().parent == ROOT / package


def test_core_imports_no_hardware_or_simulation_library() -> None:
    code = (
        "import sys\n"
        "import dh2rt.cli, dh2rt.robot, dh2rt.engine, dh2rt.compiler, dh2rt.lang.api, dh2rt.demo, drivers.base\n"
        "heavy = [m for m in ('pybullet', 'numpy', 'can', 'serial', 'dynamixel_sdk', 'matplotlib', 'PIL', 'isotp')"
        " if m in sys.modules]\n"
        "print(','.join(heavy))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ""
