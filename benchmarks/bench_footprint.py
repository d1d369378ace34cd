"""A module's footprint (issue 10): memory, CPU per cycle, cycle lateness, start-up time.

Run: ``python -m benchmarks.bench_footprint [--quick]`` (about 80 s; ``--quick`` about 30 s).

Eight ``dh2rt module --config module.toml`` processes run the caterpillar at 50 Hz
(``period_ms = 20``), each on its own, as eight module processors would, on this machine:

* ``serial``: a snake of pty links relayed by :class:`~hil.link_emulator.LinkEmulator` (run in
  this process), one UART per connector;
* ``bus``: python-can ``udp_multicast`` with static links, in a private network namespace
  (this script re-executes itself under ``unshare -rn``; udp_multicast never runs in the
  host's namespace).

Baseline, same run, same topology and rate: eight bare loops (``benchmarks/bare_loop.py``, run as
a script) that open the same kind of ports with pyserial or python-can alone and, every
20 ms, write the frames a caterpillar module writes (the same bytes: a Hello per link in the
first cycle, then per link and cycle a keep-alive, or the hormone every 10 cycles through
back), read whatever arrived, keep their own lateness, and write the same kind of status
file every ``status_every`` cycles. What a figure adds over its baseline is what dh2rt adds.

dh2rt's packages are compiled to bytecode first (:func:`compile_bytecode`), as an installed
module has them; ``--no-compile`` measures modules that compile their source at each start.
The modules' folders (flash, module.toml, status file, log) are on tmpfs (``/dev/shm``),
as a module's status file is in ``/run``. Per process (median and max over the eight):

* resident memory: ``VmRSS`` of ``/proc/PID/status`` at the end of the window (and the peak,
  ``VmHWM``);
* CPU: the run time of every thread (``/proc/PID/task/*/schedstat``, in ns) between two status writes a
  window apart (read the moment each status file is replaced, so the cycle count matches),
  per cycle and as % of one core;
* cycle lateness: the status's ``lateness_ms`` p50/p99 (the last 4,096 cycles: start-up
  included, when eight processes start at once on two cores), and the p99 of the cycles in
  the window, from the statuses' lateness histograms (``lateness_hist``, cumulative counts
  per bucket, as cyclictest keeps): the upper edge of its bucket, and that as % of the
  period, which is what the target judges (steady cycling);
* first cycle: from just before the process was spawned (``time.monotonic()``) to its
  ``first_cycle_at`` (CLOCK_MONOTONIC), (a) for the eight started at once, contending for two
  cores, and (b) for one module restarted while the other seven run (the target's case: one
  module booting on its own processor, neighbours already there).

Targets (judged on the worst module): at most 30 MB resident, at most 3 % of one core, p99
lateness at most 10 % of the period, first cycle (restart) within 1 s. The last line is one
JSON object with every figure.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import IO, Any

from benchmarks import strict_json
from dh2rt.runtime import LATENESS_EDGES_MS
from hil.netns import in_namespace, namespace_problem

ROOT = Path(__file__).resolve().parents[1]
MODULES = 8
PERIOD_MS = 20
#: Hormones the caterpillar's head starts each ClockCycle (40): one through back every 10 cycles.
HORMONE_EVERY = 10
RESTARTED = MODULES // 2
UDP_GROUP = "239.74.163.2"
#: Where the modules' folders go: tmpfs, as a module's status file goes to /run (docs/firmware.md);
#: on a disk, renaming a status file over the last one now and then takes tens of ms.
RAM_DIR = "/dev/shm"
TARGETS = {"rss_mb": 30.0, "cpu_percent": 3.0, "lateness_p99_percent": 10.0, "first_cycle_s": 1.0}
FIGURES = (
    ("rss_mb", "resident MB", "{:.1f}"),
    ("cpu_percent", "CPU % of one core", "{:.2f}"),
    ("cpu_ms_per_cycle", "CPU ms per cycle", "{:.3f}"),
    ("lateness_p50_ms", "lateness p50 ms", "{:.3f}"),
    ("lateness_p99_ms", "lateness p99 ms", "{:.3f}"),
    ("lateness_p99_window_ms", "  in the window, at most", "{:g}"),
    ("lateness_p99_percent", "  that, % period", "{:.1f}"),
    ("first_cycle_all_s", "first cycle s (8 at once)", "{:.2f}"),
    ("first_cycle_s", "first cycle s (restart)", "{:.2f}"),
)

#: The baseline: a bare loop with pyserial or python-can alone (its spec: its docstring).
BARE_LOOP = Path(__file__).with_name("bare_loop.py")


# ---------------------------------------------------------------- processes


@dataclass
class Child:
    """One process under measurement: a dh2rt module or a bare loop."""

    name: str
    cmd: list[str]
    status: Path
    log: Path
    proc: subprocess.Popen[bytes] | None = None
    spawned: float = 0.0
    samples: list[Sample] = field(default_factory=list)

    def spawn(self) -> None:
        with self.log.open("ab") as log:
            self.spawned = time.monotonic()
            self.proc = subprocess.Popen(
                self.cmd, cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=log,
                start_new_session=True,  # Ctrl-C reaches this script, which stops them in order
            )  # fmt: skip

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def read_status(self) -> dict[str, Any] | None:
        try:
            data = json.loads(self.status.read_text())
        except (OSError, ValueError):
            return None
        return data if isinstance(data, dict) else None

    def status_key(self) -> tuple[int, int] | None:
        """Changes whenever the status file is replaced (a new inode each time)."""
        try:
            st = self.status.stat()
        except OSError:
            return None
        return st.st_ino, st.st_mtime_ns

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self, timeout: float = 10.0) -> int | None:
        """SIGTERM, then SIGKILL after ``timeout``; the exit code (None if never started)."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@dataclass(frozen=True)
class Sample:
    """A process read the moment it replaced its status file."""

    t: float
    cpu_s: float
    #: of which the threads other than the main one (pyserial's reader threads)
    cpu_threads_s: float
    cycle: int
    status: dict[str, Any]
    rss_kb: int
    hwm_kb: int


def cpu_seconds(task: Path) -> float:
    """The time a task ran on a CPU, in s: the first field of ``/proc/PID/task/TID/schedstat``
    (nanoseconds; ``/proc/PID/stat``'s utime and stime count 10 ms ticks, and a bare loop's
    2 s window of a quick run could read 0 ticks)."""
    return int((task / "schedstat").read_text().split()[0]) / 1e9


def cpu_of(pid: int) -> tuple[float, float]:
    """(CPU seconds of the whole process, of its threads other than the main one): its live
    threads' run time (a thread that ended since the last sample takes its time with it)."""
    total = threads = 0.0
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError, ValueError):  # a thread that just ended
            seconds = cpu_seconds(task)
            total += seconds
            if task.name != str(pid):
                threads += seconds
    return total, threads


def memory_kb(pid: int) -> tuple[int, int]:
    """(VmRSS, VmHWM) of ``pid`` in kB."""
    values = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, rest = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            values[key] = int(rest.split()[0])
    return values["VmRSS"], values["VmHWM"]


def sample_next_status(children: list[Child], timeout: float) -> None:
    """Wait for each child's next status write and read its CPU and memory right then."""
    before = [c.status_key() for c in children]
    waiting = set(range(len(children)))
    deadline = time.monotonic() + timeout
    while waiting and time.monotonic() < deadline:
        for i in sorted(waiting):
            c = children[i]
            key = c.status_key()
            if key is None or key == before[i]:
                continue
            (cpu, threads), t = cpu_of(c.pid), time.monotonic()
            rss, hwm = memory_kb(c.pid)
            status = c.read_status()
            if status is None:
                before[i] = key
                continue
            c.samples.append(Sample(t, cpu, threads, int(status["cycle"]), status, rss, hwm))
            waiting.discard(i)
        time.sleep(0.004)
    dead = [children[i].name for i in waiting if not children[i].alive()]
    if waiting:
        raise RuntimeError(f"no status from {[children[i].name for i in sorted(waiting)]} (exited: {dead})")


def wait_first_cycle(children: list[Child], timeout: float) -> None:
    """Until each child's status names its first cycle (it writes a status after cycling a while)."""
    deadline = time.monotonic() + timeout
    pending = list(children)
    while pending and time.monotonic() < deadline:
        for c in list(pending):
            st = c.read_status()
            if st is not None and st.get("first_cycle_at") and float(st["first_cycle_at"]) > c.spawned:
                pending.remove(c)
            elif not c.alive():
                raise RuntimeError(f"{c.name} exited ({c.proc.returncode if c.proc else '?'}): {tail(c.log)}")
        time.sleep(0.02)
    if pending:
        raise RuntimeError(f"no first cycle from {[c.name for c in pending]} in {timeout:g} s: {tail(pending[0].log)}")


def tail(path: Path, chars: int = 600) -> str:
    try:
        return path.read_text(errors="replace")[-chars:]
    except OSError:
        return ""


@contextlib.contextmanager
def stopping(children: list[Child]) -> Iterator[list[Child]]:
    """Every child is stopped on the way out, killed (by its pid) if it does not stop."""
    try:
        yield children
    finally:
        for c in children:  # SIGTERM all first: one by one, the last would miss its neighbours
            if c.alive():
                assert c.proc is not None
                with contextlib.suppress(ProcessLookupError):
                    c.proc.send_signal(signal.SIGTERM)
        for c in children:
            try:
                c.stop()
            finally:
                c.kill()


# ---------------------------------------------------------------- one measurement


@dataclass
class Setup:
    """What one run needs: per module, its dh2rt config body and its bare loop's ports."""

    transport: str
    dh2rt_bodies: list[str]
    bare_ports: list[list[dict[str, Any]]]


def measure(children: list[Child], window: float, status_every: int, period: float) -> dict[str, Any]:
    """Start them all at once, sample a window of steady cycling, restart one, stop them."""
    with stopping(children):
        for c in children:
            c.spawn()
        wait_first_cycle(children, 60)
        # generous: on a loaded machine a status can come seconds late (the figures say how late)
        status_wait = 3 * status_every * period + 30
        sample_next_status(children, status_wait)
        time.sleep(max(0.0, window - status_every * period))
        sample_next_status(children, status_wait)
        first_all = [float(c.samples[0].status["first_cycle_at"]) - c.spawned for c in children]
        # one module restarted while the others run: a module booting with its neighbours there
        again = children[RESTARTED]
        again.stop()
        again.status.unlink(missing_ok=True)
        again.spawn()
        wait_first_cycle([again], 90)  # a loaded machine can take tens of seconds
        restart_st = again.read_status()
        assert restart_st is not None
        first_restart = float(restart_st["first_cycle_at"]) - again.spawned
    return summarise(children, first_all, first_restart, period)


def histogram_p99(before: dict[str, Any], after: dict[str, Any]) -> float:
    """The 99th percentile of the lateness of the cycles between two statuses, from their
    histograms (cumulative counts): the upper edge of the bucket it falls in, in ms (inf in
    the last, open bucket)."""
    edges = after["lateness_hist"]["edges_ms"]
    counts = [y - x for x, y in zip(before["lateness_hist"]["counts"], after["lateness_hist"]["counts"], strict=True)]
    need = math.ceil(0.99 * sum(counts))
    seen = 0
    for i, n in enumerate(counts):
        seen += n
        if need and seen >= need:
            return float(edges[i]) if i < len(edges) else math.inf
    return math.nan


def summarise(children: list[Child], first_all: list[float], first_restart: float, period: float) -> dict[str, Any]:
    per: dict[str, list[float]] = {k: [] for k, _, _ in FIGURES if k != "first_cycle_s"}
    per["rss_peak_mb"] = []
    per["cpu_threads_percent"] = []
    cycles = 0
    for c, first in zip(children, first_all, strict=True):
        a, b = c.samples[0], c.samples[-1]
        ran = b.cycle - a.cycle
        cpu = b.cpu_s - a.cpu_s
        cycles += ran
        lateness = b.status.get("lateness_ms") or {}
        per["rss_mb"].append(b.rss_kb / 1024)
        per["rss_peak_mb"].append(b.hwm_kb / 1024)
        per["cpu_percent"].append(100 * cpu / (b.t - a.t))
        per["cpu_threads_percent"].append(100 * (b.cpu_threads_s - a.cpu_threads_s) / (b.t - a.t))
        per["cpu_ms_per_cycle"].append(1000 * cpu / ran if ran else float("nan"))
        per["lateness_p50_ms"].append(float(lateness.get("p50", float("nan"))))
        per["lateness_p99_ms"].append(float(lateness.get("p99", float("nan"))))
        window_p99 = histogram_p99(a.status, b.status)
        per["lateness_p99_window_ms"].append(window_p99)
        per["lateness_p99_percent"].append(window_p99 / (period * 1000) * 100)
        per["first_cycle_all_s"].append(first)
    out: dict[str, Any] = {k: {"median": statistics.median(v), "max": max(v)} for k, v in per.items()}
    out["first_cycle_s"] = {"median": first_restart, "max": first_restart}
    out["cycles_in_window"] = cycles
    out["window_s"] = statistics.median(c.samples[-1].t - c.samples[0].t for c in children)
    return out


# ---------------------------------------------------------------- the two kinds of process


def module_children(tmp: Path, setup: Setup, status_every: int) -> list[Child]:
    from dh2rt.bundled import compile_bundled

    image = compile_bundled("caterpillar.dh2").image
    children = []
    for m, body in enumerate(setup.dh2rt_bodies):
        folder = tmp / f"dh2rt-{setup.transport}" / f"m{m}"
        (folder / "flash").mkdir(parents=True)
        (folder / "flash" / "program.img").write_bytes(image)
        config = folder / "module.toml"
        config.write_text(
            f'name = "m{m}"\n[program]\nflash = "flash"\nallow_unsigned = true\n'
            + body
            + f"[cycle]\nperiod_ms = {PERIOD_MS}\n"
            + f'[log]\nstatus_every = {status_every}\nstatus_file = "status.json"\n'
        )
        cmd = [sys.executable, "-m", "dh2rt", "module", "--config", str(config)]
        children.append(Child(f"m{m}", cmd, folder / "status.json", folder / "log.jsonl"))
    return children


def bare_children(tmp: Path, setup: Setup, status_every: int) -> list[Child]:
    children = []
    for m, ports in enumerate(setup.bare_ports):
        folder = tmp / f"bare-{setup.transport}" / f"b{m}"
        folder.mkdir(parents=True)
        kind = "serial" if setup.transport == "serial" else "udp"
        spec = {"kind": kind, "period": PERIOD_MS / 1000, "status": str(folder / "status.json"),
                "status_every": status_every, "group": UDP_GROUP, "ports": ports,
                "edges_ms": list(LATENESS_EDGES_MS)}  # fmt: skip
        cmd = [sys.executable, str(BARE_LOOP), json.dumps(spec)]
        children.append(Child(f"b{m}", cmd, folder / "status.json", folder / "log.txt"))
    return children


class Frames:
    """The bytes a caterpillar module writes: its Hello, a keep-alive, the hormone it passes on."""

    def __init__(self) -> None:
        from dh2rt.bundled import compile_bundled
        from dh2rt.hormone import Hormone
        from dh2rt.wire.frame import FrameCodec, Hello, KeepAlive, program_digest

        program = compile_bundled("caterpillar.dh2")
        self.profile = program.profile
        codec = FrameCodec(program.vocabulary, program.profile.connector_count)
        digest = program_digest(program.image)
        self.payloads: dict[str, Callable[[int], bytes | None]] = {
            "hello": lambda c: codec.encode(c, Hello(digest)),
            "keepalive": lambda c: codec.encode(c, KeepAlive(1)),
            # the hormone goes through back only (sent with an empty path, as the engine sends it)
            "hormone": lambda c: (
                codec.encode(c, Hormone("X", ("B",))) if self.profile.connector_name(c) == "back" else None
            ),
        }

    def connector(self, name: str) -> int:
        return self.profile.connector_index(name)


def serial_setup(links: Any, frames: Frames) -> Setup:
    """The snake's ports: module i's back and module i+1's front are the two ends of link i."""
    from dh2rt.wire.serial_framing import encode_serial

    ports: dict[tuple[int, str], str] = {}
    for i in range(MODULES - 1):
        pair = links.add_link(i)
        ports[(i, "back")], ports[(i + 1, "front")] = pair.paths
    bodies, bare = [], []
    for m in range(MODULES):
        mine = [(c, ports[(m, c)]) for c in ("front", "back") if (m, c) in ports]
        bodies.append('[transport]\nkind = "serial"\n[transport.connectors]\n'
                      + "".join(f'{c} = "{path}"\n' for c, path in mine))  # fmt: skip
        bare_ports = []
        for c, path in mine:
            port: dict[str, Any] = {"path": path}
            for what, make in frames.payloads.items():
                payload = make(frames.connector(c))
                port[what] = None if payload is None else encode_serial(payload).hex()
            bare_ports.append(port)
        bare.append(bare_ports)
    return Setup("serial", bodies, bare)


def bus_setup(frames: Frames) -> Setup:
    """Static links on one udp_multicast bus: link i+1 joins module i's back (side 0) and
    module i+1's front (side 1)."""
    from dh2rt.wire.can_frames import LINK_END_MASK, listen_filter, segment

    bodies, bare = [], []
    for m in range(MODULES):
        ends = []
        if m > 0:
            ends.append(("front", m, 1))
        if m < MODULES - 1:
            ends.append(("back", m + 1, 0))
        links = "".join(f"{c} = {{ link_id = {link}, side = {side} }}\n" for c, link, side in ends)
        bodies.append('[transport]\nkind = "udp"\n[transport.links]\n' + links)
        bare_ports = []
        for c, link, side in ends:
            flt = listen_filter(link, side)
            port: dict[str, Any] = {"filter": [flt["can_id"], LINK_END_MASK]}
            for what, make in frames.payloads.items():
                payload = make(frames.connector(c))
                port[what] = (
                    None
                    if payload is None
                    else [[f.arbitration_id, f.data.hex()] for f in segment(payload, link, side)]
                )
            bare_ports.append(port)
        bare.append(bare_ports)
    return Setup("bus", bodies, bare)


def run_transport(transport: str, window: float, status_every: int) -> dict[str, Any]:
    """The bare loops, then the dh2rt modules, on the same kind of links; figures and ratios."""
    frames = Frames()
    period = PERIOD_MS / 1000
    with tempfile.TemporaryDirectory(
        prefix="dh2rt-footprint-", dir=RAM_DIR if os.path.isdir(RAM_DIR) else None
    ) as name:
        tmp = Path(name)
        results: dict[str, dict[str, Any]] = {}
        for who in ("baseline", "dh2rt"):
            if transport == "serial":
                from hil.link_emulator import LinkEmulator

                with LinkEmulator() as links:
                    setup = serial_setup(links, frames)
                    results[who] = _run_one(who, tmp, setup, window, status_every, period)
            else:
                results[who] = _run_one(who, tmp, bus_setup(frames), window, status_every, period)
    return compare(transport, results["dh2rt"], results["baseline"])


def _run_one(who: str, tmp: Path, setup: Setup, window: float, status_every: int, period: float) -> dict[str, Any]:
    make = module_children if who == "dh2rt" else bare_children
    children = make(tmp, setup, status_every)
    load = os.getloadavg()[0]
    figures = measure(children, window, status_every, period)
    figures["checks"] = checks(who, children)
    # the machine is shared: how busy it was (1-minute load average, before and after)
    figures["loadavg"] = [round(load, 2), round(os.getloadavg()[0], 2)]
    return figures


def checks(who: str, children: list[Child]) -> dict[str, Any]:
    """That the processes really talked: frames received, and for dh2rt no link lost."""
    last = [c.samples[-1].status for c in children]
    if who == "baseline":
        return {
            "frames_received_min": min(int(s.get("received", 0)) for s in last),
            "send_failed": sum(int(s.get("send_failed", 0)) for s in last),
        }
    counters = [s.get("counters", {}) for s in last]
    return {
        "frames_received_min": min(int(c.get("frames_received", 0)) for c in counters),
        "send_failed": sum(int(c.get("frames_send_failed", 0)) for c in counters),
        # of those, the program's sends through a connector with no link (the tail passing
        # the wave on through its free back: one per hormone it gets), not lost frames
        "send_failed_unlinked": sum(int(c.get("engine_send_failed", 0)) for c in counters),
        "links_lost": sum(int(c.get("links_lost", 0)) for c in counters),
        "late_cycles": sum(int(c.get("late_cycles", 0)) for c in counters),
        "types": [s.get("type") for s in last],
    }


def compare(transport: str, dh2rt: dict[str, Any], baseline: dict[str, Any]) -> dict[str, Any]:
    ratio: dict[str, dict[str, float]] = {}
    for key, _, _ in FIGURES:
        ratio[key] = {
            stat: dh2rt[key][stat] / baseline[key][stat] if baseline[key][stat] else float("inf")
            for stat in ("median", "max")
        }
    met = {key: dh2rt[key]["max"] <= limit for key, limit in TARGETS.items()}
    return {"transport": transport, "dh2rt": dh2rt, "baseline": baseline, "ratio": ratio, "met": met}


# ---------------------------------------------------------------- the bus, in a namespace


def bus_in_namespace(argv: list[str]) -> dict[str, Any]:
    """The bus measurement in a child under ``unshare -rn``: its result or why not."""
    if (problem := namespace_problem()) is not None:
        return {"transport": "bus", "skipped": problem}
    cmd = in_namespace([sys.executable, "-m", "benchmarks.bench_footprint", "--bus-inner", *argv])
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=300)
    except BaseException:
        # it stops its own children (a SIGTERM is its Ctrl-C); kill it only if it does not
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        raise
    lines = out.strip().splitlines()
    if proc.returncode != 0 or not lines:
        return {"transport": "bus", "skipped": f"private network namespace run failed: {err.strip()[-600:]}"}
    result: dict[str, Any] = json.loads(lines[-1])
    return result


def _interrupt_once(signum: int, _frame: FrameType | None) -> None:
    """SIGTERM or SIGINT: stop (once: the clean-up that follows must not be cut short)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise KeyboardInterrupt(f"signal {signum}")


# ---------------------------------------------------------------- report


def table(result: dict[str, Any], out: IO[str]) -> None:
    name = result["transport"]
    if "skipped" in result:
        print(f"{name}: skipped: {result['skipped']}", file=out)
        return
    d, b, r, met = result["dh2rt"], result["baseline"], result["ratio"], result["met"]
    print(f"\n{name}: {MODULES} modules at {1000 // PERIOD_MS} Hz, window {d['window_s']:.1f} s "
          f"({d['cycles_in_window']} dh2rt cycles)", file=out)  # fmt: skip
    print(f"  {'figure':<27}{'dh2rt med / max':>20}{'bare loop med / max':>24}{'ratio med':>11}  target", file=out)
    for key, label, fmt in FIGURES:
        cells = [f"{fmt.format(x[key]['median'])} / {fmt.format(x[key]['max'])}" for x in (d, b)]
        if key == "first_cycle_s":
            cells = [fmt.format(x[key]["median"]) for x in (d, b)]
        target = ""
        if key in TARGETS:
            target = f"<= {TARGETS[key]:g}: {'met' if met[key] else 'MISSED'}"
        print(f"  {label:<27}{cells[0]:>20}{cells[1]:>24}{r[key]['median']:>10.2f}x  {target}", file=out)
    threads = [f"{x['cpu_threads_percent']['median']:.2f} / {x['cpu_threads_percent']['max']:.2f}" for x in (d, b)]
    print(f"  {'  of which other threads':<27}{threads[0]:>20}{threads[1]:>24}", file=out)
    print(f"  load average (before, after): dh2rt {d['loadavg']}, bare loop {b['loadavg']}", file=out)
    print(f"  checks: dh2rt {d['checks']}, bare loop {b['checks']}", file=out)


def compile_bytecode() -> bool:
    """Compile dh2rt's packages to bytecode (``__pycache__``), as ``pip install`` does on a
    module processor and python-can in the bare loop have them. Without it (a source
    checkout run with PYTHONDONTWRITEBYTECODE, as here) every module compiles its imports'
    source at each start: no more resident on a bus module today (29.6 MB), but 3.5 MB while the
    2,000-line rollout was imported at boot (2026-11-25), which the comparison then hid."""
    import compileall

    return all(compileall.compile_dir(ROOT / package, quiet=1) for package in ("dh2rt", "drivers", "hil"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="A module's footprint: memory, CPU, lateness, start-up")
    parser.add_argument("--quick", action="store_true", help="a few seconds per run, for smoke tests")
    parser.add_argument("--window", type=float, help="seconds of steady cycling measured (default 13, quick 2)")
    parser.add_argument("--only", choices=("serial", "bus"), help="one transport only")
    parser.add_argument(
        "--no-compile", action="store_true", help="no bytecode for dh2rt: modules compile their source at each start"
    )
    parser.add_argument("--bus-inner", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    window = args.window if args.window is not None else (2.0 if args.quick else 13.0)
    status_every = 25 if args.quick else 50
    signal.signal(signal.SIGTERM, _interrupt_once)
    signal.signal(signal.SIGINT, _interrupt_once)
    if args.bus_inner:
        if [n for _i, n in socket.if_nameindex()] != ["lo"]:
            print(json.dumps({"transport": "bus", "skipped": "not in a loopback-only namespace"}))
            return 2
        print(json.dumps(run_transport("bus", window, status_every)))
        return 0
    bytecode = not args.no_compile and compile_bytecode()
    results = []
    try:
        if args.only in (None, "serial"):
            results.append(run_transport("serial", window, status_every))
        if args.only in (None, "bus"):
            inner = [*(["--quick"] if args.quick else []), "--window", str(window)]
            results.append(bus_in_namespace(inner))
    except KeyboardInterrupt:
        print("interrupted: every process it started is stopped", file=sys.stderr)
        return 130
    for r in results:
        table(r, sys.stdout)
    met = {r["transport"]: r["met"] for r in results if "met" in r}
    print(json.dumps(strict_json({"bench": "footprint", "quick": args.quick, "modules": MODULES,
                                  "period_ms": PERIOD_MS, "status_every": status_every, "bytecode": bytecode,
                                  "targets": TARGETS, "met": met, "transports": results})))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
