"""Images forged for a public key of small order (issue 27): no private key, R of small order
and S = 0 (tests/dh2rt/forgery.py). Before issue 27 each of them passed ``dh2rt module
--check-config``, ``Flash.stage`` and a first boot; now a config refuses the weak key when it
loads it, naming the file, and a flash that trusts one all the same (made without a config)
refuses the image."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from dh2rt.bundled import compile_bundled
from dh2rt.errors import FlashError, ModuleConfigError
from dh2rt.signed_image import Verdict, key_id, new_private_key, pack, public_key
from firmware.config import ModuleConfig
from firmware.flash.slots import LEGACY_IMAGE, Flash
from tests.dh2rt.forgery import WEAK_KEYS, forge

ROOT = Path(__file__).resolve().parents[2]
WEAK = pytest.mark.parametrize("weak", list(WEAK_KEYS.values()), ids=list(WEAK_KEYS))


@pytest.fixture(scope="module")
def program() -> bytes:
    return compile_bundled("caterpillar.dh2").image


def _module(tmp_path: Path, weak: bytes, program: bytes) -> tuple[Path, Path]:
    """A module's folder whose flash holds the forged image and whose module.toml trusts the
    weak key: the config file and the key file."""
    (tmp_path / "flash").mkdir()
    (tmp_path / "flash" / LEGACY_IMAGE).write_bytes(forge(program, weak))
    key = tmp_path / "weak.pub"
    key.write_bytes(weak)
    config = tmp_path / "module.toml"
    config.write_text(f'name = "m"\n[program]\nflash = "flash"\ntrust = ["{key}"]\n[transport]\nkind = "inproc"\n')
    return config, key


def _run_module(config: Path, *args: str) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "dh2rt", "module", "--config", str(config), *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=ROOT)


@WEAK
def test_check_config_refuses_the_weak_key_naming_its_file(weak: bytes, program: bytes, tmp_path: Path) -> None:
    config, key = _module(tmp_path, weak, program)
    proc = _run_module(config, "--check-config")
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert f"[program] trust[0]: {key}: refused: a weak Ed25519 public key, a point of small order" in proc.stderr
    assert "Traceback" not in proc.stderr and "ok" not in proc.stdout


def test_a_module_trusting_an_all_zero_key_file_does_not_start(program: bytes, tmp_path: Path) -> None:
    config, key = _module(tmp_path, bytes(32), program)
    proc = _run_module(config)
    assert proc.returncode == 2 and f"{key}: refused: a weak Ed25519 public key" in proc.stderr, proc.stderr
    assert "all zeros" in proc.stderr and "Traceback" not in proc.stderr


@WEAK
def test_a_json_config_refuses_the_weak_key(weak: bytes) -> None:
    """The config the HIL world hands a module process: keys in hexadecimal."""
    good = public_key(new_private_key())
    with pytest.raises(ModuleConfigError, match="config trust: refused: a weak Ed25519 public key"):
        ModuleConfig.from_json({"flash": "flash", "trust": [good.hex(), weak.hex()]})
    assert ModuleConfig.from_json({"flash": "flash", "trust": [good.hex()]}).trust == (good,)


@WEAK
def test_a_flash_that_trusts_the_weak_key_refuses_to_stage_the_forgery(
    weak: bytes, program: bytes, tmp_path: Path
) -> None:
    signer = new_private_key()
    flash = Flash(tmp_path, [weak, public_key(signer)])
    assert flash.stage(pack(program, 1, signer)).accepted  # a flash that works
    files = sorted(p.name for p in tmp_path.iterdir())
    staged = flash.stage(forge(program, weak, first_version=2))
    assert not staged.accepted and staged.verdict is Verdict.TAMPERED, staged
    assert flash.refused[Verdict.TAMPERED] == 1 and f"signed for key {key_id(weak).hex()}, a weak key" in str(
        flash.last_refusal
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == files


@WEAK
def test_a_first_boot_refuses_the_forgery(weak: bytes, program: bytes, tmp_path: Path) -> None:
    """An empty flash with the forged image as program.img, the weak key trusted: nothing to
    boot, and ``peek`` (what --check-config prints) says it would be refused."""
    (tmp_path / LEGACY_IMAGE).write_bytes(forge(program, weak))
    flash = Flash(tmp_path, [weak])
    summary, image = flash.peek()
    assert image is None and "would be refused (tampered" in summary, summary
    with pytest.raises(FlashError, match=f"no program to boot: {LEGACY_IMAGE} refused"):
        flash.boot()
    assert sorted(p.name for p in tmp_path.iterdir()) == [LEGACY_IMAGE]
