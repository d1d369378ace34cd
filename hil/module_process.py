"""One module process: ``python -m hil.module_process --config JSON``.

The world starts one of these per module (or runs :class:`ModuleHost` in a thread for the
in-process transports). The config is a :class:`~hil.config.ModuleConfig` as JSON (inline or
``@file``); every field, its type and its default are there.

Actuators: with ``servo_port`` the module drives its DOF1/DOF2 Dynamixel servos (ids
``servo_ids``) through dynamixel-sdk; without one it takes the stand-in (``driver``:
``recording`` records the commanded angles, ``none`` drives nothing). Servos that cannot be
opened (missing, wrong model, a bad bus) are reported as an actuator fault, and the module
runs its program without actuators rather than not at all.

Control channel: the typed commands of :mod:`hil.control` arrive as JSON lines on stdin
(``go``: start cycling, at a CLOCK_MONOTONIC instant after exchanging Hellos until then, for
a number of cycles; ``attach``, ``detach``, ``inject``, ``status``, ``stop``); reports go out
as JSON lines on stdout (``ready``, ``status`` every ``status_every`` cycles, ``trace``,
``effect``, ``log``, ``error``, and ``final`` at exit). A malformed command is refused with
a log report naming the field. SIGTERM and SIGINT end the loop cleanly with a final report.
Exit 0 after a clean stop, 1 after a failure, 2 for a bad config.
"""

from __future__ import annotations

import argparse
import json
import queue
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from types import FrameType
from typing import IO

from dh2rt.compiler import load_image
from dh2rt.errors import ControlProtocolError, DH2Error
from dh2rt.events import parse_hormone
from dh2rt.runtime import HEALTH_EVERY, ModuleRuntime
from dh2rt.transport.registry import open_transport
from dh2rt.wire.frame import FrameCodec
from drivers.base import ModuleDriver
from drivers.recording import RecordingDriver
from hil.config import ModuleConfig
from hil.control import (
    Attach,
    Command,
    Detach,
    Effect,
    Failure,
    Go,
    Inject,
    Log,
    Ready,
    Report,
    Status,
    StatusRequest,
    Stop,
    TraceRecord,
    command_from_json,
    report_to_json,
)

Reporter = Callable[[Report], None]
#: Cycle periods a module keeps reading after its last cycle (see ModuleRuntime.drain).
DRAIN_PERIODS = 3


def open_driver(config: ModuleConfig) -> tuple[ModuleDriver | None, str | None]:
    """The module's driver: Dynamixel servos when ``servo_port`` is set, else the stand-in.

    Returns (driver, fault): a servo bus that cannot be opened gives (None, why).
    """
    if not config.servo_port:
        return (RecordingDriver() if config.driver == "recording" else None), None
    from drivers.dynamixel import DynamixelDriver

    dof1, dof2 = config.servo_ids
    try:
        return DynamixelDriver(config.servo_port, dof1_id=dof1, dof2_id=dof2), None
    except DH2Error as exc:
        return None, str(exc)


class ModuleHost:
    """Runs one module from a config, reading commands from a queue and reporting through
    a callback: the body of a module process, also run in a thread for in-process buses."""

    def __init__(self, config: ModuleConfig, commands: queue.Queue[Command], report: Reporter) -> None:
        self.config = config
        self.commands = commands
        self.report = report
        self.stop_event = threading.Event()
        self.failed = False
        self.program = load_image(config.image)
        self.module = config.module
        self.cycles = config.cycles
        self.driver, driver_fault = open_driver(config)
        codec = FrameCodec(self.program.vocabulary, self.program.profile.connector_count)
        transport = open_transport(config.transport, codec)
        self.runtime = ModuleRuntime(
            self.program,
            transport,
            timer_phase=config.timer_phase,
            driver=self.driver,
            cycle_period=config.cycle_period,
            silence_cycles=config.silence_cycles,
            record=config.trace,
            module=self.module,
            name=config.label,
        )
        if driver_fault is not None:
            self.runtime.actuator_fault = driver_fault
            self.runtime.stats.actuator_faults += 1
            self.runtime.log.append(f"actuator fault: {driver_fault}")
        self._logged = 0

    def serve(self) -> int:
        """Attach, report ready, wait for ``go``, cycle until done or stopped; 0 or 1."""
        rt = self.runtime
        try:
            for c, end in self.config.attach.items():
                rt.attach(c, end)
            self.report(Ready())
            start_at: float | None = None
            while not self.stop_event.is_set():
                try:
                    cmd = self.commands.get(timeout=0.05)
                except queue.Empty:
                    continue
                if isinstance(cmd, Go):
                    start_at = cmd.at
                    if cmd.cycles is not ...:
                        self.cycles = cmd.cycles
                    break
                self._command(cmd)
            if not self.stop_event.is_set():
                linked = rt.handshake(self.config.handshake, until=start_at)
                if not linked:
                    self.report(Log("handshake: a peer is silent"))
                if start_at is not None and self.cycles is not None:
                    # started at an agreed instant: stop at one too, so that no module runs on
                    # after its neighbours stopped and takes their silence for a lost link
                    until = start_at + self.cycles * self.config.cycle_period
                    rt.run(None, self.stop_event, self._on_cycle, until=until)
                    # what the neighbours sent in their last cycles is counted, not lost
                    rt.drain(DRAIN_PERIODS * self.config.cycle_period)
                else:
                    rt.run(self.cycles, self.stop_event, self._on_cycle)
        except Exception as exc:  # report it to the world rather than die silently
            self.failed = True
            self.report(Failure(f"{type(exc).__name__}: {exc}"))
        finally:
            self._flush()
            # what was last commanded: the servos themselves may be gone by now
            targets = self.runtime.commanded if self.driver is not None else None
            final = Status(rt.status(), final=True, failed=self.failed, targets=targets)
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
        if self.driver is None and self.config.servo_port and rt.cycle % HEALTH_EVERY == rt.health_offset:
            self._reopen_servos(rt)
        if rt.cycle % self.config.status_every == 0:
            self._flush()
            self.report(Status(rt.status()))

    def _reopen_servos(self, rt: ModuleRuntime) -> None:
        """Servos that could not be opened are tried again (a bus that was busy or
        unpowered at boot); the module says so when its body comes back."""
        driver, fault = open_driver(self.config)
        if driver is None:
            rt.actuator_fault = fault
            return
        self.driver = driver
        rt.attach_driver(driver, f"servos opened on {self.config.servo_port}")

    def _flush(self) -> None:
        rt = self.runtime
        for rec in rt.records:
            rec["life"] = self.config.life
            self.report(TraceRecord(rec))
        rt.records.clear()
        for kind, args in rt.effects:
            self.report(Effect(kind, list(args)))
        rt.effects.clear()
        log = rt.log
        if self._logged > len(log):
            self._logged = 0
        for line in log[self._logged :]:
            self.report(Log(line))
        self._logged = len(log)

    def _command(self, cmd: Command) -> None:
        rt = self.runtime
        try:
            if isinstance(cmd, Stop):
                self.stop_event.set()
            elif isinstance(cmd, Attach):
                rt.attach(cmd.connector, cmd.end)
            elif isinstance(cmd, Detach):
                rt.detach(cmd.connector)
            elif isinstance(cmd, Inject):
                rt.inject(parse_hormone(cmd.hormone, self.program.vocabulary, "inject command"))
            elif isinstance(cmd, StatusRequest):
                self.report(Status(rt.status()))
        except DH2Error as exc:
            self.report(Log(f"command {cmd!r} refused: {exc}"))


def _stdout_report(stream: IO[str]) -> Reporter:
    lock = threading.Lock()

    def report(rep: Report) -> None:
        line = json.dumps(report_to_json(rep), separators=(",", ":"))
        with lock:
            try:
                stream.write(line + "\n")
                stream.flush()
            except (BrokenPipeError, ValueError):
                pass  # the world has gone; nothing left to tell

    return report


def _read_commands(stream: IO[str], commands: queue.Queue[Command], report: Reporter) -> None:
    for line in stream:
        line = line.strip()
        if not line:
            continue
        try:
            commands.put(command_from_json(json.loads(line)))
        except (json.JSONDecodeError, ControlProtocolError) as exc:
            report(Log(f"command refused ({exc}): {line[:200]!r}"))
    commands.put(Stop())  # the world closed the channel


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hil.module_process", description="Run one dh2rt module.")
    parser.add_argument("--config", required=True, help="module config: a JSON object, or @FILE")
    ns = parser.parse_args(argv)
    report = _stdout_report(sys.stdout)
    try:
        text = ns.config
        if text.startswith("@"):
            text = Path(text[1:]).read_text(encoding="utf-8")
        config = ModuleConfig.from_json(json.loads(text))
        commands: queue.Queue[Command] = queue.Queue()
        host = ModuleHost(config, commands, report)
    except (OSError, ValueError, DH2Error) as exc:
        report(Failure(f"bad config: {exc}"))
        print(f"module_process: bad config: {exc}", file=sys.stderr)
        return 2

    def on_signal(_sig: int, _frame: FrameType | None) -> None:
        host.stop_event.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    threading.Thread(target=_read_commands, args=(sys.stdin, commands, report), daemon=True).start()
    return host.serve()


if __name__ == "__main__":
    sys.exit(main())
