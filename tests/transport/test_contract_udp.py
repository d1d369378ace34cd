"""The transport contract on python-can ``udp_multicast``, inside a private network namespace.

udp_multicast follows the route table and cannot pick an interface, so it never runs in the
host namespace: the whole suite runs in a subprocess under ``unshare -rn`` with only loopback
up and a multicast route on it.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from dh2rt.testing import CONTRACT_CHECKS

ROOT = Path(__file__).resolve().parents[2]
NETNS = "ip link set lo up && ip route add 224.0.0.0/4 dev lo && "
SCRIPT = (
    "import json, sys\n"
    "from dh2rt.testing import CanHarness, run_contract\n"
    "print(json.dumps(run_contract(lambda: CanHarness('udp'))))\n"
)


def _namespace_problem() -> str | None:
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare or ip (util-linux, iproute2) is not installed"
    probe = subprocess.run(["unshare", "-rn", "sh", "-c", NETNS + "true"], capture_output=True, text=True, timeout=20)
    if probe.returncode != 0:
        return f"cannot create a private network namespace: {probe.stderr.strip()}"
    return None


@pytest.fixture(scope="module")
def udp_results() -> dict[str, str]:
    problem = _namespace_problem()
    if problem is not None:
        pytest.skip(f"udp_multicast runs only in a private network namespace: {problem}")
    cmd = NETNS + f'exec {sys.executable} -c "$DH2RT_SCRIPT"'
    proc = subprocess.run(
        ["unshare", "-rn", "sh", "-c", cmd],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
        env={
            "DH2RT_SCRIPT": SCRIPT,
            "PYTHONPATH": str(ROOT),
            "PATH": "/usr/sbin:/usr/bin:/sbin:/bin",
        },
    )
    assert proc.returncode == 0, proc.stderr
    results: dict[str, str] = json.loads(proc.stdout.strip().splitlines()[-1])
    return results


@pytest.mark.parametrize("check", list(CONTRACT_CHECKS))
def test_udp_multicast_contract(udp_results: dict[str, str], check: str) -> None:
    assert udp_results[check] == "ok", udp_results[check]
