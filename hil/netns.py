"""A private network namespace for python-can's ``udp_multicast``: the one place that makes it.

udp_multicast follows the route table and cannot pick an interface, so it never runs in the
host namespace: whatever uses it (the launcher's ``--transport udp``, benchmarks, tests) runs
again under ``unshare -rn`` with only loopback up and a multicast route on it::

    if (why := namespace_problem()) is None:
        subprocess.run(in_namespace([sys.executable, "-m", "hil.launcher", *argv]))
"""

from __future__ import annotations

import shutil
import socket
import subprocess
from collections.abc import Sequence

#: Set in the environment of a command re-executed inside its private network namespace.
NETNS_ENV = "DH2RT_HIL_NETNS"
#: What runs first inside the namespace: loopback up, and multicast routed onto it.
SETUP = "ip link set lo up && ip route add 224.0.0.0/4 dev lo"


def namespace_problem() -> str | None:
    """Why no such namespace can be made here (a missing tool, or a machine that refuses
    ``unshare -rn``), or None when it can."""
    missing = [tool for tool in ("unshare", "ip") if shutil.which(tool) is None]
    if missing:
        return f"{' and '.join(missing)} (util-linux, iproute2) is not installed"
    probe = subprocess.run(["unshare", "-rn", "sh", "-c", SETUP], capture_output=True, text=True, timeout=30)
    if probe.returncode != 0:
        why = probe.stderr.strip() or "unshare -rn failed"
        return f"this machine cannot create a private network namespace ({why})"
    return None


def in_namespace(argv: Sequence[str]) -> list[str]:
    """The command line that runs ``argv`` inside a new private network namespace."""
    return ["unshare", "-rn", "sh", "-c", SETUP + ' && exec "$@"', "sh", *argv]


def only_loopback() -> bool:
    """True inside such a namespace: loopback is this process's only network interface."""
    try:
        names = [name for _index, name in socket.if_nameindex()]
    except OSError:
        return False
    return names == ["lo"]
