"""One module process: ``python -m hil.module_process --config JSON``.

The world starts one of these per module (or runs :class:`ModuleHost` in a thread for the
in-process transports). The config (a JSON object, inline or ``@file``)::

    {"module": 3, "name": "m3", "image": "<hex>" | "image_path": "...",
     "transport": "udp" | "vcan0" | "serial" | "virtual:ch" | "inproc:ch",
     "attach": {"2": {"link_id": 7, "side": 0}, "1": {"port": "/dev/pts/9"}},
     "timer_phase": 17, "cycle_period": 0.02, "cycles": 300 | null,
     "silence_cycles": 3, "driver": "recording" | "none", "trace": false,
     "servo_port": "/dev/ttyUSB0" | null, "servo_ids": [1, 2],
     "status_every": 10, "handshake": 1.0}

Actuators: with ``servo_port`` the module drives its DOF1/DOF2 Dynamixel servos (ids
``servo_ids``) through dynamixel-sdk; without one it takes the stand-in (``driver``:
``recording`` records the commanded angles, ``none`` drives nothing). Servos that cannot be
opened (missing, wrong model, a bad bus) are reported as an actuator fault, and the module
runs its program without actuators rather than not at all.

Control channel. Commands arrive as JSON lines on stdin (``{"cmd": ...}``): ``go`` (start
cycling; with ``at``, a CLOCK_MONOTONIC reading, exchange Hellos until then and start at that
instant, as modules powered up together; with ``cycles``, run that many), ``attach``
(``connector``, ``link``), ``detach`` (``connector``), ``inject`` (``hormone`` text like
``X(A)``), ``stop``. Reports go out as JSON lines on stdout, each with
an ``event``: ``ready`` (transport open, links attached), ``status`` (every ``status_every``
cycles: type, T, DOF1/DOF2, ConnectorStatus, counters), ``trace`` (one record per cycle, when
asked), ``effect`` (a native's request of the physical world), ``log``, ``error`` and
``final`` (the last status, at exit). SIGTERM and SIGINT end the loop cleanly with a final
report. Exit 0 after a clean stop, 1 after a failure, 2 for a bad config.
"""

from __future__ import annotations

import argparse
import json
import queue
import signal
import sys
import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from types import FrameType
from typing import IO, Any

from dh2rt.compiler import load_image
from dh2rt.errors import DH2Error, ModuleConfigError
from dh2rt.events import parse_hormone
from dh2rt.runtime import SILENCE_CYCLES, ModuleRuntime
from dh2rt.transport.base import BusEnd, LinkEnd, PortEnd
from dh2rt.transport.registry import open_transport
from dh2rt.wire.frame import FrameCodec
from drivers.base import ModuleDriver
from drivers.recording import RecordingDriver

Report = Callable[[dict[str, Any]], None]



def open_driver(config: Mapping[str, Any], stand_in: str) -> tuple[ModuleDriver | None, str | None]:
    """The module's driver: Dynamixel servos when ``servo_port`` is set, else the stand-in.

    Returns (driver, fault): a servo bus that cannot be opened gives (None, why).
    """
    port = config.get("servo_port")
    if not port:
        return (RecordingDriver() if stand_in == "recording" else None), None
    from drivers.dynamixel import DynamixelDriver

    ids = list(config.get("servo_ids", [1, 2]))
    if len(ids) != 2 or not all(isinstance(i, int) for i in ids):
        raise ModuleConfigError(f"config servo_ids {ids!r}: expected two servo ids [DOF1, DOF2]")
    try:
        return DynamixelDriver(str(port), dof1_id=ids[0], dof2_id=ids[1]), None
    except DH2Error as exc:
        return None, str(exc)


def link_end(spec: Mapping[str, Any], where: str = "link") -> LinkEnd:
    """``{"link_id": L, "side": S}`` or ``{"port": path}`` as a transport link end."""
    if "port" in spec:
        return PortEnd(str(spec["port"]))
    try:
        return BusEnd(int(spec["link_id"]), int(spec["side"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise ModuleConfigError(f"{where}: expected {{'link_id', 'side'}} or {{'port'}}, got {dict(spec)!r}") from exc


class ModuleHost:
    """Runs one module from a config, reading commands from a queue and reporting through
    a callback: the body of a module process, also run in a thread for in-process buses."""

    def __init__(self, config: Mapping[str, Any], commands: queue.Queue[dict[str, Any]], report: Report) -> None:
        self.config = dict(config)
        self.commands = commands
        self.report = report
        self.stop_event = threading.Event()
        self.failed = False
        try:
            if "image" in config:
                image = bytes.fromhex(str(config["image"]))
            elif "image_path" in config:
                image = Path(str(config["image_path"])).read_bytes()
            else:
                raise ModuleConfigError("config: one of 'image' (hex) or 'image_path' is required")
            self.program = load_image(image)
            self.module = int(config.get("module", 0))
            self.status_every = max(1, int(config.get("status_every", 10)))
            self.cycles: int | None = None if config.get("cycles") is None else int(config["cycles"])
            self.handshake_timeout = float(config.get("handshake", 1.0))
            attach = {int(c): link_end(v, f"config attach[{c}]") for c, v in dict(config.get("attach", {})).items()}
            driver_name = str(config.get("driver", "recording"))
            if driver_name not in ("recording", "none"):
                raise ModuleConfigError(f"config driver {driver_name!r}: expected 'recording' or 'none'")
        except (OSError, ValueError, TypeError) as exc:
            raise ModuleConfigError(str(exc)) from exc
        self.driver, driver_fault = open_driver(config, driver_name)
        codec = FrameCodec(self.program.vocabulary, self.program.profile.connector_count)
        transport = open_transport(str(config.get("transport", "inproc")), codec)
        self.runtime = ModuleRuntime(
            self.program,
            transport,
            timer_phase=int(config.get("timer_phase", 0)),
            driver=self.driver,
            cycle_period=float(config.get("cycle_period", 0.02)),
            silence_cycles=int(config.get("silence_cycles", SILENCE_CYCLES)),
            record=bool(config.get("trace", False)),
            module=self.module,
            name=str(config.get("name", f"m{self.module}")),
        )
        if driver_fault is not None:
            self.runtime.actuator_fault = driver_fault
            self.runtime.stats.actuator_faults += 1
            self.runtime.log.append(f"actuator fault: {driver_fault}")
        self._attach = attach
        self._logged = 0

    def serve(self) -> int:
        """Attach, report ready, wait for ``go``, cycle until done or stopped; 0 or 1."""
        rt = self.runtime
        try:
            for c, end in self._attach.items():
                rt.attach(c, end)
            self.report({"event": "ready", "module": self.module})
            start_at: float | None = None
            while not self.stop_event.is_set():
                try:
                    cmd = self.commands.get(timeout=0.05)
                except queue.Empty:
                    continue
                if cmd.get("cmd") == "go":
                    start_at = None if cmd.get("at") is None else float(cmd["at"])
                    if "cycles" in cmd:
                        self.cycles = None if cmd["cycles"] is None else int(cmd["cycles"])
                    break
                self._command(cmd)
            if not self.stop_event.is_set():
                linked = rt.handshake(self.handshake_timeout, until=start_at)
                if not linked:
                    self.report({"event": "log", "module": self.module, "message": "handshake: a peer is silent"})
                rt.run(self.cycles, self.stop_event, self._on_cycle)
        except Exception as exc:  # report it to the world rather than die silently
            self.failed = True
            self.report({"event": "error", "module": self.module, "message": f"{type(exc).__name__}: {exc}"})
        finally:
            self._flush()
            final = rt.status()
            final["event"] = "final"
            final["failed"] = self.failed
            # what was last commanded: the servos themselves may be gone by now
            final["targets"] = list(self.runtime.commanded) if self.driver is not None else None
            rt.close()
            self.report(final)
        return 1 if self.failed else 0

    def _on_cycle(self, rt: ModuleRuntime) -> None:
        while True:
            try:
                cmd = self.commands.get_nowait()
            except queue.Empty:
                break
            self._command(cmd)
        if rt.cycle % self.status_every == 0:
            self._flush()
            status = rt.status()
            status["event"] = "status"
            self.report(status)

    def _flush(self) -> None:
        rt = self.runtime
        for rec in rt.records:
            self.report({"event": "trace", "record": rec})
        rt.records.clear()
        for kind, args in rt.effects:
            self.report({"event": "effect", "module": self.module, "kind": kind, "args": _jsonable(args)})
        rt.effects.clear()
        log = rt.log
        if self._logged > len(log):
            self._logged = 0
        for line in log[self._logged :]:
            self.report({"event": "log", "module": self.module, "message": line})
        self._logged = len(log)

    def _command(self, cmd: Mapping[str, Any]) -> None:
        rt = self.runtime
        kind = cmd.get("cmd")
        try:
            if kind == "stop":
                self.stop_event.set()
            elif kind == "attach":
                rt.attach(int(cmd["connector"]), link_end(cmd["link"], "attach command"))
            elif kind == "detach":
                rt.detach(int(cmd["connector"]))
            elif kind == "inject":
                rt.inject(parse_hormone(str(cmd["hormone"]), self.program.vocabulary, "inject command"))
            elif kind == "status":
                status = rt.status()
                status["event"] = "status"
                self.report(status)
            elif kind != "go":
                raise ModuleConfigError(f"unknown command {kind!r}")
        except (DH2Error, KeyError, ValueError, TypeError) as exc:
            self.report({"event": "log", "module": self.module, "message": f"command {dict(cmd)!r} refused: {exc}"})


def _jsonable(value: Any) -> Any:
    if isinstance(value, tuple | list):
        return [_jsonable(v) for v in value]
    return value


def _stdout_report(stream: IO[str]) -> Report:
    lock = threading.Lock()

    def report(obj: dict[str, Any]) -> None:
        line = json.dumps(obj, separators=(",", ":"))
        with lock:
            try:
                stream.write(line + "\n")
                stream.flush()
            except (BrokenPipeError, ValueError):
                pass  # the world has gone; nothing left to tell

    return report


def _read_commands(stream: IO[str], commands: queue.Queue[dict[str, Any]]) -> None:
    for line in stream:
        line = line.strip()
        if not line:
            continue
        try:
            obj = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(obj, dict):
            commands.put(obj)
    commands.put({"cmd": "stop"})  # the world closed the channel


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hil.module_process", description="Run one dh2rt module.")
    parser.add_argument("--config", required=True, help="module config: a JSON object, or @FILE")
    ns = parser.parse_args(argv)
    report = _stdout_report(sys.stdout)
    try:
        text = ns.config
        if text.startswith("@"):
            text = Path(text[1:]).read_text(encoding="utf-8")
        config = json.loads(text)
        if not isinstance(config, dict):
            raise ModuleConfigError("config: expected a JSON object")
        commands: queue.Queue[dict[str, Any]] = queue.Queue()
        host = ModuleHost(config, commands, report)
    except (OSError, ValueError, DH2Error) as exc:
        report({"event": "error", "message": f"bad config: {exc}"})
        print(f"module_process: bad config: {exc}", file=sys.stderr)
        return 2

    def on_signal(_sig: int, _frame: FrameType | None) -> None:
        host.stop_event.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    threading.Thread(target=_read_commands, args=(sys.stdin, commands), daemon=True).start()
    return host.serve()


if __name__ == "__main__":
    sys.exit(main())
