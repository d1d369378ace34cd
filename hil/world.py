"""The hardware-in-the-loop world: the physical layer around module processes.

The :class:`World` plays what the in-process :class:`~dh2rt.robot.Robot` plays in one
process, but for modules that each run their own :class:`~dh2rt.runtime.ModuleRuntime` on
a real link layer. It owns the topology; it assigns each docked connector pair a CAN link id
and sides (``vcan0``/``can0``/``udp``/``virtual``/``inproc``) or a pair of pty ends through
the :class:`~hil.link_emulator.LinkEmulator` (``serial``); it starts the modules (one OS
process each over ``socketcan``, ``udp`` and ``serial``; one thread each over the
in-process buses ``virtual`` and ``inproc``); and it carries out events at world cycles:

* ``cut``: CAN: both ends are told to detach the link id; serial: the emulator undocks the
  link (the modules notice by liveness, as they would over infrared).
* ``dock``: a new link id (or emulator link) is attached at both ends.
* ``kill``: the module's process is ended by its pid (a thread is told to stop); its
  neighbours notice the silence within the liveness bound.
* ``restart``: the module starts again with a fresh state on the same links.
* ``inject``: the hormone is sent to the module over its control channel.

Effects that natives ask of the physical world arrive as reports; ``reach_and_dock`` is
carried out as the Robot does it (DOCK_DELAY world cycles later: the foot's link is cut and
the asking connector docked to it), so ``legs_to_snake`` reconfigures in the loop.

A world cycle is wall time since ``go`` divided by the cycle period: modules keep their own
clocks and cycle counts. Reports from the modules (status, trace records, logs, effects)
arrive on one queue and are read by :meth:`World.poll`.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import queue
import random
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dh2rt.docking import DOCK_DELAY, route_end
from dh2rt.errors import HilWorldError, TopologyError
from dh2rt.events import Event
from dh2rt.hormone import Hormone
from dh2rt.program import CompiledProgram
from dh2rt.runtime import SILENCE_CYCLES
from dh2rt.topology import Topology
from dh2rt.transport.registry import parse_spec as parse_transport_spec
from hil.link_emulator import LinkEmulator
from hil.module_process import ModuleHost

ROOT = Path(__file__).resolve().parents[1]
#: Transports whose modules run as threads of the world's process (their bus is in-process).
THREAD_TRANSPORTS = ("inproc", "virtual")


if TYPE_CHECKING:
    from hil.physics_stand_in import PhysicsStandIn



@dataclass(slots=True)
class ModuleView:
    """What the world last heard from one module."""

    module: int
    name: str
    alive: bool = False
    ready: bool = False
    finished: bool = False
    failed: bool = False
    killed: bool = False
    status: dict[str, Any] = field(default_factory=dict)
    frames_per_s: float = 0.0
    errors: list[str] = field(default_factory=list)
    _last: tuple[float, int] | None = None

    @property
    def state(self) -> str:
        """failed, killed, done (ran its cycles), running or stopped."""
        if self.failed:
            return "failed"
        if self.killed:
            return "killed"
        if self.finished:
            return "done"
        return "running" if self.alive else "stopped"


class _ProcessModule:
    """One module as an OS process; commands on its stdin, reports from its stdout."""

    def __init__(self, module: int, config: dict[str, Any], reports: queue.Queue[tuple[int, dict[str, Any]]]) -> None:
        self.module = module
        env = dict(os.environ)
        env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hil.module_process", "--config", json.dumps(config)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=str(ROOT),
            env=env,
        )
        self.pid = self.proc.pid
        try:
            self._reader = threading.Thread(target=self._read, args=(reports,), daemon=True)
            self._reader.start()
        except BaseException:  # interrupted before the world holds this handle: end it here
            self.proc.kill()
            self.proc.wait()
            raise

    def _read(self, reports: queue.Queue[tuple[int, dict[str, Any]]]) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with contextlib.suppress(json.JSONDecodeError):
                obj = json.loads(line)
                if isinstance(obj, dict):
                    reports.put((self.module, obj))
        reports.put((self.module, {"event": "exit"}))

    def send(self, cmd: dict[str, Any]) -> None:
        stdin = self.proc.stdin
        if stdin is None or self.proc.poll() is not None:
            return
        with contextlib.suppress(BrokenPipeError, ValueError, OSError):
            stdin.write(json.dumps(cmd) + "\n")
            stdin.flush()

    def running(self) -> bool:
        return self.proc.poll() is None

    def exit_code(self) -> int | None:
        return self.proc.poll()

    def end(self, grace: float) -> None:
        """Ask politely (SIGTERM to its pid), then SIGKILL; reap it and close its pipes."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGTERM)
            try:
                self.proc.wait(grace)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(self.pid, signal.SIGKILL)
                self.proc.wait(5)
        self._reader.join(2)
        for stream in (self.proc.stdin, self.proc.stdout):
            if stream is not None:
                with contextlib.suppress(OSError, BrokenPipeError):
                    stream.close()


class _ThreadModule:
    """One module as a thread of the world's process (in-process buses only)."""

    def __init__(self, module: int, config: dict[str, Any], reports: queue.Queue[tuple[int, dict[str, Any]]]) -> None:
        self.module = module
        self.pid = os.getpid()
        self.commands: queue.Queue[dict[str, Any]] = queue.Queue()
        self._code: int | None = None
        self.host = ModuleHost(config, self.commands, lambda obj: reports.put((module, obj)))

        def body() -> None:
            self._code = self.host.serve()
            reports.put((module, {"event": "exit"}))

        self.thread = threading.Thread(target=body, name=f"dh2rt-module-{module}", daemon=True)
        self.thread.start()

    def send(self, cmd: dict[str, Any]) -> None:
        self.commands.put(cmd)

    def running(self) -> bool:
        return self.thread.is_alive()

    def exit_code(self) -> int | None:
        return None if self.thread.is_alive() else (self._code if self._code is not None else 1)

    def end(self, grace: float) -> None:
        self.host.stop_event.set()
        self.thread.join(grace + 2)


_Handle = _ProcessModule | _ThreadModule


@dataclass(slots=True)
class _WorldLink:
    link_id: int
    a: int
    a_conn: int
    b: int
    b_conn: int


class World:
    """Modules of ``topology`` running ``program`` over ``transport`` (see module docs)."""

    def __init__(
        self,
        program: CompiledProgram,
        topology: Topology,
        transport: str,
        *,
        seed: int = 0,
        cycle_period: float = 0.02,
        cycles: int | None = None,
        trace: bool = False,
        silence_cycles: int = SILENCE_CYCLES,
        status_every: int = 10,
        frame_loss: float = 0.0,
        bit_error: float = 0.0,
        emulator_seed: int | None = None,
        handshake: float = 2.0,
        start_delay: float = 0.3,
        stand_in: str = "recording",
    ) -> None:
        self.program = program
        self.topology = topology
        self.profile = topology.profile
        self.spec = transport
        self.kind, options = parse_transport_spec(transport)
        self.seed = seed
        self.rng = random.Random(seed)
        # the same LocalTimer phases as the in-process Robot with this seed
        self.phases = [self.rng.randrange(program.clock_cycle) for _ in range(topology.size)]
        self.cycle_period = cycle_period
        self.cycles = cycles
        self.trace = trace
        self.silence_cycles = silence_cycles
        self.status_every = status_every
        self.handshake = handshake
        self.start_delay = start_delay
        self.threads = self.kind in THREAD_TRANSPORTS
        if self.threads:
            channel = options.get("channel") or f"dh2rt-hil-{os.getpid()}-{id(self):x}"
            self.transport_spec = f"{self.kind}:{channel}"
        else:
            self.transport_spec = transport
        self.emulator: LinkEmulator | None = None
        if self.kind == "serial":
            self.emulator = LinkEmulator(frame_loss=frame_loss, bit_error=bit_error, seed=emulator_seed)
        #: The modules' body: "recording" (each module records its commanded angles),
        #: "pybullet" (the full firmware path: Dynamixel servos emulated on ptys whose joints
        #: are PyBullet joints; see hil.physics_stand_in) or "none".
        self.stand_in = stand_in
        self.physics: PhysicsStandIn | None = None
        try:
            if stand_in == "pybullet":
                from hil.physics_stand_in import PhysicsStandIn

                self.physics = PhysicsStandIn(topology, seed=seed)
            elif stand_in not in ("recording", "none"):
                raise HilWorldError(f"stand-in {stand_in!r}: expected pybullet, recording or none")
        except BaseException:  # a failed or interrupted start leaves no pty or thread behind
            if self.emulator is not None:
                self.emulator.close()
            raise
        self.reports: queue.Queue[tuple[int, dict[str, Any]]] = queue.Queue()
        self.views = [ModuleView(m, topology.names[m]) for m in range(topology.size)]
        self.handles: list[_Handle | None] = [None] * topology.size
        self.records: list[dict[str, Any]] = []
        self.effects: list[dict[str, Any]] = []
        self.log: list[str] = []
        #: (event text, monotonic time it was carried out): CLOCK_MONOTONIC is system-wide,
        #: so these compare with the ``t`` of the modules' trace records.
        self.event_times: list[tuple[str, float]] = []
        self._link_ids = itertools.count()
        self.peer: dict[tuple[int, int], _WorldLink] = {}
        self.links: dict[int, _WorldLink] = {}
        self._pending: list[tuple[int, Callable[[], None]]] = []  # (world cycle, effect)
        self._go_at: float | None = None
        self._closed = False
        for lk in topology.links:
            self._new_link(lk.a, lk.a_conn, lk.b, lk.b_conn)

    # ------------------------------------------------------------ links

    def _new_link(self, a: int, a_conn: int, b: int, b_conn: int) -> _WorldLink:
        link = _WorldLink(next(self._link_ids), a, a_conn, b, b_conn)
        if self.emulator is not None:
            self.emulator.add_link(link.link_id)
        self.links[link.link_id] = link
        self.peer[(a, a_conn)] = link
        self.peer[(b, b_conn)] = link
        return link

    def _end(self, link: _WorldLink, module: int, connector: int) -> dict[str, Any]:
        """The link end ``module`` attaches at ``connector``: side 0 is the link's ``a``."""
        side = 0 if (module, connector) == (link.a, link.a_conn) else 1
        if self.emulator is not None:
            return {"port": self.emulator.link(link.link_id).paths[side]}
        return {"link_id": link.link_id, "side": side}

    def attachments(self, module: int) -> dict[str, dict[str, Any]]:
        """Connector -> link end of every docked connector of ``module``."""
        return {str(c): self._end(link, m, c) for (m, c), link in sorted(self.peer.items()) if m == module}

    # ------------------------------------------------------------ modules

    def config(self, module: int, cycles: int | None, phase: int) -> dict[str, Any]:
        return {
            "module": module,
            "name": self.topology.names[module],
            "image": self.program.image.hex(),
            "transport": self.transport_spec,
            "attach": self.attachments(module),
            "timer_phase": phase,
            "cycle_period": self.cycle_period,
            "cycles": cycles,
            "silence_cycles": self.silence_cycles,
            "driver": "none" if self.stand_in == "none" else "recording",
            "servo_port": self.physics.port(module) if self.physics is not None else None,
            "trace": self.trace,
            "status_every": self.status_every,
            "handshake": self.handshake,
        }

    def _spawn(self, module: int, cycles: int | None, phase: int) -> None:
        config = self.config(module, cycles, phase)
        handle: _Handle
        if self.threads:
            handle = _ThreadModule(module, config, self.reports)
        else:
            handle = _ProcessModule(module, config, self.reports)
        self.handles[module] = handle
        v = self.views[module]
        v.alive, v.ready, v.finished, v.failed, v.killed = True, False, False, False, False

    def start(self, ready_timeout: float = 30.0) -> None:
        """Start every module, wait until all have attached their links, then say ``go``."""
        for m in range(self.topology.size):
            self._spawn(m, self.cycles, self.phases[m])
        deadline = time.monotonic() + ready_timeout
        while not all(v.ready for v in self.views):
            self.poll(0.05)
            if any(v.failed or (not v.ready and self._exited(v.module)) for v in self.views):
                raise HilWorldError(self._failure_text("a module failed to start"))
            if time.monotonic() > deadline:
                late = [v.name for v in self.views if not v.ready]
                raise HilWorldError(f"modules {', '.join(late)} not ready after {ready_timeout:.0f} s")
        # one start instant for all (CLOCK_MONOTONIC is shared by every process here): the
        # modules exchange Hellos until then and start cycling together, like modules powered
        # up at once; afterwards each keeps its own clock
        self._go_at = time.monotonic() + self.start_delay
        for h in self.handles:
            if h is not None:
                h.send({"cmd": "go", "at": self._go_at})

    def _exited(self, module: int) -> bool:
        h = self.handles[module]
        return h is not None and not h.running()

    def _failure_text(self, what: str) -> str:
        details = [f"{v.name}: {e}" for v in self.views for e in v.errors]
        return what + (": " + "; ".join(details) if details else "")

    @property
    def cycle(self) -> int:
        """The world cycle: wall time since ``go`` over the cycle period."""
        if self._go_at is None:
            return 0
        return max(0, int((time.monotonic() - self._go_at) / self.cycle_period))

    def poll(self, timeout: float = 0.0) -> None:
        """Read the modules' reports (waiting up to ``timeout`` s for the first)."""
        try:
            item = self.reports.get(timeout=timeout) if timeout > 0 else self.reports.get_nowait()
        except queue.Empty:
            return
        while True:
            self._report(*item)
            try:
                item = self.reports.get_nowait()
            except queue.Empty:
                return

    def _report(self, module: int, obj: dict[str, Any]) -> None:
        v = self.views[module]
        event = obj.get("event")
        if event == "ready":
            v.ready = True
        elif event in ("status", "final"):
            counters = obj.get("counters", {})
            frames = int(counters.get("frames_sent", 0)) + int(counters.get("frames_received", 0))
            now = time.monotonic()
            if event == "status" and (v._last is None or now - v._last[0] >= 0.2):
                if v._last is not None:
                    v.frames_per_s = (frames - v._last[1]) / (now - v._last[0])
                v._last = (now, frames)
            v.status = obj
            if event == "final":
                v.finished = True
                if obj.get("failed"):
                    v.failed = True
        elif event == "trace":
            self.records.append(obj["record"])
        elif event == "effect":
            self.effects.append(obj)
            self.log.append(f"{v.name}: effect {obj.get('kind')} {obj.get('args')}")
            self._effect(module, str(obj.get("kind")), obj.get("args") or [])
        elif event == "log":
            self.log.append(f"{v.name}: {obj.get('message')}")
        elif event == "error":
            v.errors.append(str(obj.get("message")))
            v.failed = True
        elif event == "exit":
            h = self.handles[module]
            code = h.exit_code() if h is not None else None
            if h is not None and not v.killed and code not in (0, None):
                v.failed = True
                v.errors.append(f"exited with code {code}")
            v.alive = False

    def _effect(self, module: int, kind: str, args: list[Any]) -> None:
        """Carry out what a native asked of the physical world (as the Robot does)."""
        if kind != "reach_and_dock":
            return  # "assist" and the like only move joints, which the module did itself
        try:
            connector, route = int(args[0]), [int(c) for c in args[1]]
        except (IndexError, TypeError, ValueError):
            self.log.append(f"{self.topology.names[module]}: malformed reach_and_dock {args!r}")
            return
        self._pending.append((self.cycle + DOCK_DELAY, lambda: self.reach_and_dock(module, connector, route)))

    def _peer_of(self, end: tuple[int, int]) -> tuple[int, int] | None:
        """The module and connector docked at ``end`` (module, connector), if any."""
        link = self.peer.get(end)
        if link is None:
            return None
        return (link.b, link.b_conn) if end == (link.a, link.a_conn) else (link.a, link.a_conn)

    def reach_and_dock(self, module: int, connector: int, route: Sequence[int]) -> None:
        """Follow ``route`` from ``module`` to the module at its end, release that module's
        link at the connector the route arrives at, and dock ``module``'s ``connector`` there
        (the in-process Robot's ``reach_and_dock``, on real links)."""
        end = route_end(self._peer_of, module, route)
        if end is None:
            self.log.append(f"reach_and_dock from {self._where(module, connector)}: route broken")
            return
        here, at = end
        if here == module or not self.views[here].alive or not self.views[module].alive:
            return
        if (module, connector) in self.peer:
            self.log.append(f"reach_and_dock: {self._where(module, connector)} is not free")
            return
        if self.physics is not None and not self.physics.aligned(module, connector, here, at):
            # as sim.runner does: the motions that align the two are not modelled
            self.log.append(
                f"world cycle {self.cycle}: {self._where(module, connector)} cannot reach "
                f"{self._where(here, at)}: not aligned in the world"
            )
            return
        self.cut(here, at)
        self.dock(module, connector, here, at)
        if self.physics is not None:
            self.physics.dock(module, connector, here, at)
        self.log.append(f"world cycle {self.cycle}: {self._where(module, connector)} docked to {self._where(here, at)}")

    def tick(self) -> None:
        """Read reports; carry out due effects; notice modules that died on their own; step
        physics up to now (with the PyBullet stand-in)."""
        self.poll()
        if self.physics is not None and self._go_at is not None and time.monotonic() >= self._go_at:
            self.physics.advance()
        if self._pending:
            now = self.cycle
            due = [action for when, action in self._pending if when <= now]
            self._pending = [(when, action) for when, action in self._pending if when > now]
            for action in due:
                action()
        for m, h in enumerate(self.handles):
            v = self.views[m]
            if h is not None and v.alive and not h.running():
                code = h.exit_code()
                if code is not None and code != 0 and not v.killed:
                    if not v.failed:
                        v.errors.append(f"exited with code {code}")
                    v.failed = True

    def done(self) -> bool:
        """Every module that was not killed has finished (or died)."""
        return all(v.finished or v.killed or v.failed or not v.alive for v in self.views)

    # ------------------------------------------------------------ events

    def apply(self, event: Event) -> None:
        """Carry out an event now (see the module docs)."""
        started = time.monotonic()
        if event.kind == "cut":
            self.cut(event.module, event.connector)
        elif event.kind == "dock":
            self.dock(event.module, event.connector, event.other, event.other_connector)
        elif event.kind == "kill":
            self.kill(event.module)
        elif event.kind == "restart":
            self.restart(event.module)
        elif event.kind == "inject" and event.hormone is not None:
            self.inject(event.module, event.hormone)
        self.log.append(f"world cycle {self.cycle}: {event.text or event.kind}")
        self.event_times.append((event.text or event.kind, started))

    def _where(self, m: int, c: int) -> str:
        return f"{self.topology.names[m]}.{self.profile.connector_name(c)}"

    def cut(self, module: int, connector: int) -> None:
        link = self.peer.get((module, connector))
        if link is None:
            raise TopologyError(f"cannot cut {self._where(module, connector)}: nothing is docked there")
        del self.peer[(link.a, link.a_conn)]
        del self.peer[(link.b, link.b_conn)]
        if self.physics is not None:
            self.physics.undock(module, connector)
        if self.emulator is not None:
            self.emulator.undock(link.link_id)
        else:
            for m, c in ((link.a, link.a_conn), (link.b, link.b_conn)):
                self._send(m, {"cmd": "detach", "connector": c})

    def dock(self, a: int, a_conn: int, b: int, b_conn: int) -> None:
        if not self.profile.can_link(a_conn, b_conn):
            raise TopologyError(f"cannot dock {self._where(a, a_conn)} to {self._where(b, b_conn)}: same gender")
        for m, c in ((a, a_conn), (b, b_conn)):
            if (m, c) in self.peer:
                raise TopologyError(f"cannot dock {self._where(m, c)}: it is already docked")
        link = self._new_link(a, a_conn, b, b_conn)
        for m, c in ((a, a_conn), (b, b_conn)):
            self._send(m, {"cmd": "attach", "connector": c, "link": self._end(link, m, c)})

    def kill(self, module: int) -> None:
        h = self.handles[module]
        if h is None or not self.views[module].alive:
            return
        self.views[module].killed = True
        h.end(grace=0.0 if not self.threads else 1.0)
        if isinstance(h, _ProcessModule):
            h.proc.wait(5)
        self.views[module].alive = False

    def restart(self, module: int) -> None:
        self.kill(module)
        self._spawn(module, self.cycles, self.rng.randrange(self.program.clock_cycle))
        deadline = time.monotonic() + 30
        while not self.views[module].ready and time.monotonic() < deadline:
            self.poll(0.02)
            if self._exited(module):
                break
        # it starts on a world cycle boundary a little ahead (Hellos first) and runs the
        # cycles left from there, so it stops with the others
        base = self._go_at if self._go_at is not None else time.monotonic()
        start = self.cycle + 1 + int(self.start_delay / self.cycle_period)
        left = None if self.cycles is None else max(0, self.cycles - start)
        self._send(module, {"cmd": "go", "at": base + start * self.cycle_period, "cycles": left})

    def inject(self, module: int, hormone: Hormone) -> None:
        text = hormone.name if not hormone.args else hormone.content()
        self._send(module, {"cmd": "inject", "hormone": text})

    def _send(self, module: int, cmd: dict[str, Any]) -> None:
        h = self.handles[module]
        if h is not None and self.views[module].alive:
            h.send(cmd)

    def run_events(self, events: Iterable[Event], applied: set[int]) -> None:
        """Apply the events whose cycle has come (``applied`` holds indices already done)."""
        now = self.cycle
        for i, ev in enumerate(events):
            if i not in applied and ev.cycle <= now:
                applied.add(i)
                self.apply(ev)

    # ------------------------------------------------------------ reading, stopping

    def rows(self) -> list[dict[str, Any]]:
        """One row per module for the status table and the summary."""
        out: list[dict[str, Any]] = []
        for v in self.views:
            s = v.status
            c = s.get("counters", {})
            out.append(
                {
                    "module": v.module,
                    "name": v.name,
                    "alive": v.alive,
                    "state": v.state,
                    "cycle": s.get("cycle", 0),
                    "type": s.get("type", "-"),
                    "T": s.get("T"),
                    "DOF1": s.get("DOF1", 0.0),
                    "DOF2": s.get("DOF2", 0.0),
                    "frames_per_s": v.frames_per_s,
                    "counters": c,
                    "actuator_fault": s.get("actuator_fault"),
                    "errors": int(c.get("frames_dropped", 0))
                    + int(c.get("frames_corrupted", 0))
                    + int(c.get("refused", 0)),
                }
            )
        return out

    def sorted_records(self) -> list[dict[str, Any]]:
        """Trace records merged from the modules, by cycle then module."""
        return sorted(self.records, key=lambda r: (r["cycle"], r["module"]))

    def stop(self, grace: float = 3.0) -> None:
        """Tell every module to stop, end the stragglers by pid, close the link emulator."""
        # _closed is set only once everything is released: a stop interrupted by a second
        # Ctrl-C can be called again and finishes the job (every step below is idempotent)
        if self._closed:
            return
        for m, h in enumerate(self.handles):
            if h is not None and h.running():
                self._send(m, {"cmd": "stop"})
        deadline = time.monotonic() + grace
        while any(h is not None and h.running() for h in self.handles) and time.monotonic() < deadline:
            self.poll(0.05)
        for h in self.handles:
            if h is not None:
                h.end(grace=1.0)
        self._end_strays()
        self.poll()
        if self.emulator is not None:
            self.emulator.close()
        if self.physics is not None:
            self.physics.close()
        self._closed = True

    def _end_strays(self) -> None:
        """End module processes this world started but holds no handle for (a Ctrl-C between
        starting one and recording it): its own children running hil.module_process, by pid."""
        known = {h.pid for h in self.handles if isinstance(h, _ProcessModule)}
        for pid in _own_module_processes():
            if pid not in known:
                with contextlib.suppress(ProcessLookupError, ChildProcessError):
                    os.kill(pid, signal.SIGKILL)
                    os.waitpid(pid, 0)

    def __enter__(self) -> World:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _own_module_processes() -> list[int]:
    """Pids of this process's children that run hil.module_process (Linux /proc; else none)."""
    me = os.getpid()
    found: list[int] = []
    proc = Path("/proc")
    if not proc.is_dir():
        return found
    for entry in proc.iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == me and b"hil.module_process" in cmdline:
            found.append(int(entry.name))
    return found


def module_pids(world: World) -> Sequence[int]:
    """The pids of the world's module processes (tests check they are gone)."""
    return [h.pid for h in world.handles if isinstance(h, _ProcessModule)]
