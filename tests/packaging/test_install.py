"""A plain, non-editable install (a wheel into a fresh venv, run away from the checkout)
carries what its commands need: `dh2rt demo` and the launcher's default program."""

from __future__ import annotations

import subprocess
import sys
import venv
from pathlib import Path

import pytest

from hil.pace import PACE

ROOT = Path(__file__).resolve().parents[2]


#: modules run in real time here: make test runs these in a group of their own (tests/conftest.py)
pytestmark = pytest.mark.realtime


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The bin/ folder of a fresh venv holding dh2rt's wheel (no extras: the core alone)."""
    work = tmp_path_factory.mktemp("install")
    wheels = work / "wheels"
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(wheels), str(ROOT)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    if build.returncode != 0:
        pytest.fail(f"building the wheel failed:\n{build.stderr[-2000:]}")
    env_dir = work / "venv"
    venv.EnvBuilder(with_pip=True).create(env_dir)
    pip = subprocess.run(
        [str(env_dir / "bin" / "python"), "-m", "pip", "install", "-q", "--no-deps", *map(str, wheels.glob("*.whl"))],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert pip.returncode == 0, pip.stderr
    return env_dir / "bin"


def test_installed_demo_runs_away_from_the_checkout(installed: Path, tmp_path: Path) -> None:
    proc = subprocess.run([str(installed / "dh2rt"), "demo"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-1000:] + proc.stderr[-1000:]
    assert proc.stdout.rstrip().endswith("demo ok")
    assert "site-packages" not in proc.stderr


def test_installed_launcher_runs_its_default_program(installed: Path, tmp_path: Path) -> None:
    """The launcher's default program ships in the package: no checkout, no --program."""
    proc = PACE.run(
        [str(installed / "dh2rt"), "--transport", "inproc", "--module-count", "3", "--cycles", "20",
         "--stand-in", "recording", "--log", str(tmp_path / "run.log")],
        text=True, timeout=120, cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-1000:] + proc.stderr[-1000:]
    assert "caterpillar on snake:3 over inproc" in proc.stdout
    assert "every frame accounted for" in proc.stdout
