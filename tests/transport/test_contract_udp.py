"""The transport contract on python-can ``udp_multicast``, inside a private network namespace.

udp_multicast follows the route table and cannot pick an interface, so it never runs in the
host namespace: the whole suite runs in a subprocess under ``unshare -rn`` with only loopback
up and a multicast route on it.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from dh2rt.testing import CONTRACT_CHECKS
from hil.netns import in_namespace, namespace_problem

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = (
    "import json, sys\n"
    "from dh2rt.testing import CanHarness, run_contract\n"
    "print(json.dumps(run_contract(lambda: CanHarness('udp'))))\n"
)


@pytest.fixture(scope="module")
def udp_results() -> dict[str, str]:
    problem = namespace_problem()
    if problem is not None:
        pytest.skip(f"udp_multicast runs only in a private network namespace: {problem}")
    proc = subprocess.run(
        in_namespace([sys.executable, "-c", SCRIPT]),
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/sbin:/usr/bin:/sbin:/bin"},
    )
    assert proc.returncode == 0, proc.stderr
    results: dict[str, str] = json.loads(proc.stdout.strip().splitlines()[-1])
    return results


@pytest.mark.parametrize("check", list(CONTRACT_CHECKS))
def test_udp_multicast_contract(udp_results: dict[str, str], check: str) -> None:
    assert udp_results[check] == "ok", udp_results[check]
