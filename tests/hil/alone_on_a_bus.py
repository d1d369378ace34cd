"""Run inside a private network namespace by tests/hil/test_negotiated_links.py: eight
`dh2rt module` processes on python-can udp_multicast, each started with nothing but its
module.toml, the contact emulator playing the infrared pairs of a snake. Prints one JSON
object: each module's exit code and final status, their log lines, and every hormone frame
a listener on the bus saw."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import can

from dh2rt.bundled import compile_bundled
from dh2rt.signed_image import pack, public_key_path, read_private_key, write_key_pair
from hil.contact_emulator import ContactEmulator
from tools.capture_reader import CanRecord
from tools.decode import Decoder

MODULES = 8
CONNECTORS = ("front", "back", "left", "right")


def main(folder: Path) -> int:
    program = compile_bundled("caterpillar.dh2")
    key = folder / "signer.key"
    write_key_pair(key)  # each module trusts it, and boots the image it signed
    image = pack(program.image, 1, read_private_key(key))
    procs: list[subprocess.Popen[str]] = []
    tap = can.Bus(interface="udp_multicast", channel="239.74.163.2")
    frames: list[CanRecord] = []
    with ContactEmulator() as contacts:
        for m in range(MODULES):
            for c in range(1, 5):
                contacts.add_connector(m, c)
        for m in range(MODULES - 1):  # module m's back touches module m+1's front
            contacts.make_contact((m, 2), (m + 1, 1))
        try:
            for m in range(MODULES):
                procs.append(start(folder / f"m{m}", m, image, public_key_path(key), contacts))
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and not settled(folder):
                listen(tap, frames, 0.2)
            for p in procs:
                p.send_signal(signal.SIGTERM)
            results = [p.communicate(timeout=20) for p in procs]
            listen(tap, frames, 0.1)
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
                    p.wait()
            tap.shutdown()
    lines = [[json.loads(x) for x in err.splitlines() if x.startswith("{")] for _out, err in results]
    log = [f"m{m}: {x['message']}" for m, mine in enumerate(lines) for x in mine if x["event"] == "log"]
    hops = Decoder([program]).hops(frames)
    hormones = [[h.time, h.link, h.side, h.text] for h in hops if h.kind == "hormone"]
    out: dict[str, Any] = {
        "codes": [p.returncode for p in procs],
        "finals": [mine[-1] for mine in lines],
        "log": log,
        "hormones": hormones,
    }
    sys.stdout.write(json.dumps(out) + "\n")
    return 0


def start(folder: Path, m: int, image: bytes, trust: Path, contacts: ContactEmulator) -> subprocess.Popen[str]:
    (folder / "flash").mkdir(parents=True)
    (folder / "flash" / "program.img").write_bytes(image)
    channels = "".join(f'{name} = "{contacts.path((m, c))}"\n' for c, name in enumerate(CONNECTORS, 1))
    (folder / "module.toml").write_text(
        f'name = "m{m}"\n[program]\nflash = "flash"\ntrust = ["{trust}"]\n'
        f'[transport]\nkind = "udp"\n[connectors]\n{channels}'
        '[cycle]\nperiod_ms = 30\nsilence_cycles = 6\n[log]\nstatus_every = 10\nstatus_file = "status.json"\n'
    )
    cmd = [sys.executable, "-m", "dh2rt", "module", "--config", str(folder / "module.toml")]
    return subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)


#: What a snake makes each module, front to back.
SHAPE = ["head"] + ["body"] * (MODULES - 2) + ["tail"]


def settled(folder: Path) -> bool:
    """Every module has run 200 cycles and its last status says it is what the snake makes it.
    A module the machine stalls past its silence bound costs its neighbours the link for a
    while (they link again, as the liveness rules say): stopping the modules in the middle of
    that would judge the stall, not what they found. The test still judges the final statuses."""
    statuses = [status(folder / f"m{m}") for m in range(MODULES)]
    return all(int(s.get("cycle", 0)) >= 200 for s in statuses) and [s.get("type") for s in statuses] == SHAPE


def status(folder: Path) -> dict[str, Any]:
    try:
        got = json.loads((folder / "status.json").read_text())
    except (OSError, ValueError):
        return {}
    return got if isinstance(got, dict) else {}


def listen(bus: Any, frames: list[CanRecord], seconds: float) -> None:
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        msg = bus.recv(left)
        if msg is not None:
            frames.append(CanRecord(msg.timestamp, msg.arbitration_id, bytes(msg.data), msg.is_extended_id))


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1])))
