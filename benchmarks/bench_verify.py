"""Verifying a signed image (issue 27): libsodium through PyNaCl, as dh2rt.ed25519 does now,
against the pure-Python cofactorless verifier it replaced, in the same run.

Run: ``python -m benchmarks.bench_verify [--quick]`` (a few seconds; ``--quick`` under one).

What is verified: the caterpillar signed as a module receives it (the signature over the
header and the compressed body, a few hundred bytes), with one trusted key. Each verifier is
timed over the same image, best of ``REPEATS`` batches (the least disturbed by the machine):

* **pynacl**: :func:`dh2rt.ed25519.verify` (``VerifyKey(key).verify(...)``, libsodium's
  ``crypto_sign_open``), a new VerifyKey each call as dh2rt makes it.
* **old**: the pure-Python verifier of dh2rt before issue 27, read from this checkout's git
  history (the parent of the commit that removed it), its key tables warm as a module's were
  after its first check; "not available" outside a git checkout.
* **openssl**: ``cryptography``'s Ed25519 (a reference: what signing needs anyway).

Also, each in a fresh interpreter: the time to import PyNaCl (paid at a module's first check)
and the resident memory it adds (VmRSS after ``import nacl.signing`` and one verification,
less VmRSS before, both after importing firmware.flash.slots as a module does). The last
line is one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
import types
from collections.abc import Callable
from pathlib import Path

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from dh2rt import ed25519
from dh2rt import signed_image as si
from dh2rt.bundled import compile_bundled

ROOT = Path(__file__).resolve().parents[1]
REPEATS = 5
#: The code the old verifier had that the new one has not: finds the commit that removed it.
OLD_MARK = "def _double_scalar_mult"

Verify = Callable[[bytes, bytes, bytes], bool]


def old_verifier() -> Verify | None:
    """The verifier dh2rt.ed25519 held before issue 27, from git history; None without it."""

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], capture_output=True, text=True, cwd=ROOT, check=True).stdout

    try:
        removed = git("log", "--format=%H", "-S", OLD_MARK, "--", "dh2rt/ed25519.py").split()
        source = git("show", f"{removed[0]}^:dh2rt/ed25519.py") if removed else ""
    except (OSError, subprocess.CalledProcessError):
        return None
    if OLD_MARK not in source:
        return None
    module = types.ModuleType("old_ed25519")
    exec(compile(source, "old dh2rt/ed25519.py", "exec"), module.__dict__)  # this checkout's own history
    verify: Verify = module.verify
    return verify


def openssl_verify(public: bytes, signature: bytes, message: bytes) -> bool:
    """cryptography's check of a signature that holds (it raises for one that does not)."""
    Ed25519PublicKey.from_public_bytes(public).verify(signature, message)
    return True


def time_per_call(verify: Verify, args: tuple[bytes, bytes, bytes], calls: int) -> float:
    """Seconds per call, best of REPEATS batches of ``calls``."""
    assert verify(*args)
    best = float("inf")
    for _ in range(REPEATS):
        started = time.perf_counter()
        for _ in range(calls):
            verify(*args)
        best = min(best, (time.perf_counter() - started) / calls)
    return best


_FRESH = """
import sys, time
import firmware.flash.slots
from dh2rt import ed25519
def rss():
    for line in open('/proc/self/status'):
        if line.startswith('VmRSS:'):
            return int(line.split()[1]) / 1024
before = rss()
started = time.perf_counter()
import nacl.signing
imported = time.perf_counter() - started
ed25519.verify(*[bytes.fromhex(h) for h in sys.argv[1:]])
print(imported, rss() - before)
"""


def fresh_interpreter(args: tuple[bytes, bytes, bytes]) -> tuple[float, float]:
    """Seconds to import PyNaCl and MB of resident memory it and one verification add."""
    cmd = [sys.executable, "-c", _FRESH, *(a.hex() for a in args)]
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, check=True).stdout.split()
    return float(out[0]), float(out[1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_verify", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer calls (a smoke test)")
    quick = parser.parse_args(argv).quick
    private = si.new_private_key()
    image = si.parse(si.pack(compile_bundled("caterpillar.dh2").image, 1, private))
    assert image.signature is not None
    args = (si.public_key(private), image.signature, image.signed_part)
    calls = 20 if quick else 200
    pynacl = time_per_call(ed25519.verify, args, calls * 10)
    openssl = time_per_call(openssl_verify, args, calls * 10)
    old = old_verifier()
    old_s = None if old is None else time_per_call(old, args, calls)
    import_s, rss_mb = fresh_interpreter(args)
    print(f"image: caterpillar, {len(image.signed_part)} signed bytes")
    print(f"pynacl (libsodium)    {pynacl * 1e6:8.1f} us per verification")
    if old_s is None:
        print("old pure Python       not available (no git history here)")
    else:
        print(f"old pure Python       {old_s * 1e6:8.1f} us per verification: {old_s / pynacl:.1f}x pynacl's")
    print(f"openssl (reference)   {openssl * 1e6:8.1f} us per verification")
    print(f"import nacl.signing   {import_s * 1e3:8.1f} ms, once, at a module's first check")
    print(f"resident memory       {rss_mb:8.1f} MB added by PyNaCl and one verification")
    result = {
        "benchmark": "verify",
        "signed_bytes": len(image.signed_part),
        "pynacl_us": round(pynacl * 1e6, 2),
        "old_us": None if old_s is None else round(old_s * 1e6, 1),
        "old_over_pynacl": None if old_s is None else round(old_s / pynacl, 1),
        "openssl_us": round(openssl * 1e6, 2),
        "nacl_import_ms": round(import_s * 1e3, 1),
        "nacl_rss_mb": round(rss_mb, 2),
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
