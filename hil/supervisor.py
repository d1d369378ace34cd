"""Starting, talking to and ending module processes and threads.

A module runs as an OS process (``python -m firmware.main_loop``) over the transports that
cross processes, or as a thread of the world's process over the in-process buses. Either
way the world holds a :class:`ModuleHandle`: it sends typed commands (:mod:`firmware.control`)
and receives typed reports on one queue shared by all modules.

Each process starts in a session and process group of its own (``start_new_session``), so
ending it ends everything it may have started, and a Ctrl-C at the terminal reaches the
launcher only (which then stops the modules in order). No ``/proc`` scan is needed: the
world holds a handle from the moment a process exists.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from types import FrameType
from typing import Protocol

from dh2rt.errors import ControlProtocolError
from firmware.config import ModuleConfig
from firmware.control import Command, Exited, Log, Report, command_to_json, report_from_json
from firmware.module_toml import IMAGE_NAME, dump_toml

ROOT = Path(__file__).resolve().parents[1]

Reports = queue.Queue[tuple[int, Report]]


class ModuleHandle(Protocol):
    """One running module, as its world sees it."""

    module: int
    pid: int

    def send(self, cmd: Command) -> None: ...

    def running(self) -> bool: ...

    def exit_code(self) -> int | None: ...

    def end(self, grace: float) -> None: ...


class ProcessModule:
    """One module as an OS process in a process group of its own; commands on its stdin,
    reports from its stdout."""

    def __init__(self, config: ModuleConfig, reports: Reports, workdir: Path, flash_image: bytes | None = None) -> None:
        self.module = config.module
        self.life = config.life
        env = dict(os.environ)
        env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        # the module boots as a robot's module does: `dh2rt module --config module.toml`, its
        # program in a flash directory; [hil] adds the world's control channel. The flash is
        # the module's across its lives (a restarted module boots what it last confirmed, or
        # reverts a trial it did not finish); each life gets its own module.toml
        folder = workdir / config.label / f"life{config.life}"
        path = folder / "module.toml"
        folder.mkdir(parents=True, exist_ok=True)
        flash = workdir / config.label / "flash"
        path.write_text(dump_toml(config, flash, image=flash_image), encoding="utf-8")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "dh2rt", "module", "--config", str(path)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=str(ROOT),
            env=env,
            start_new_session=True,
        )
        self.pid = self.proc.pid
        try:
            self._reader = threading.Thread(target=self._read, args=(reports,), daemon=True)
            self._reader.start()
        except BaseException:  # interrupted before the world holds this handle: end it here
            self._signal_group(signal.SIGKILL)
            self.proc.wait()
            raise

    def _read(self, reports: Reports) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if not line.strip():
                continue
            try:
                reports.put((self.module, report_from_json(json.loads(line))))
            except (json.JSONDecodeError, ControlProtocolError) as exc:
                reports.put((self.module, Log(f"malformed report from the module process ({exc}): {line[:200]!r}")))
        reports.put((self.module, Exited(self.life)))

    def send(self, cmd: Command) -> None:
        stdin = self.proc.stdin
        if stdin is None or self.proc.poll() is not None:
            return
        with contextlib.suppress(BrokenPipeError, ValueError, OSError):
            stdin.write(json.dumps(command_to_json(cmd)) + "\n")
            stdin.flush()

    def running(self) -> bool:
        return self.proc.poll() is None

    def exit_code(self) -> int | None:
        return self.proc.poll()

    def _signal_group(self, sig: signal.Signals) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.pid, sig)  # its group id is its pid (start_new_session)

    def end(self, grace: float) -> None:
        """Ask politely (SIGTERM to its process group), then SIGKILL; reap it, close its pipes."""
        if self.proc.poll() is None:
            self._signal_group(signal.SIGTERM)
            try:
                self.proc.wait(grace)
            except subprocess.TimeoutExpired:
                self._signal_group(signal.SIGKILL)
                self.proc.wait(5)
        else:
            self._signal_group(signal.SIGKILL)  # anything it left behind in its group
        self._reader.join(2)
        for stream in (self.proc.stdin, self.proc.stdout):
            if stream is not None:
                with contextlib.suppress(OSError, BrokenPipeError):
                    stream.close()


class ThreadModule:
    """One module as a thread of the world's process (in-process buses only)."""

    def __init__(self, config: ModuleConfig, reports: Reports) -> None:
        from firmware.main_loop import ModuleHost

        module = self.module = config.module
        life = self.life = config.life
        self.pid = os.getpid()
        self.commands: queue.Queue[Command] = queue.Queue()
        self._code: int | None = None
        # the module's own work is its thread's CPU time: the process's is every module's and
        # the world's physics (hil.launcher.machine_held reads it to tell who held a late cycle)
        self.host = ModuleHost(
            config, self.commands, lambda rep: reports.put((module, rep)), cpu_clock=time.thread_time
        )

        def body() -> None:
            self._code = self.host.serve()
            reports.put((module, Exited(life)))

        self.thread = threading.Thread(target=body, name=f"dh2rt-module-{module}", daemon=True)
        self.thread.start()

    def send(self, cmd: Command) -> None:
        self.commands.put(cmd)

    def running(self) -> bool:
        return self.thread.is_alive()

    def exit_code(self) -> int | None:
        return None if self.thread.is_alive() else (self._code if self._code is not None else 1)

    def end(self, grace: float) -> None:
        self.host.stop_event.set()
        self.thread.join(grace + 2)


@contextlib.contextmanager
def deferred_interrupts() -> Iterator[None]:
    """Hold Ctrl-C and SIGTERM back until the block is done, so that a process is never
    started without its handle being recorded: an interrupt in between (inside Popen, after
    the fork) would leave a module that nobody knows to end. A signal that comes meanwhile
    is recorded and handled as it would have been once the block ends.

    The Python-level handlers are swapped rather than the signal mask: a process-directed
    signal is delivered to any thread that does not block it, and Python runs its handler
    in the main thread all the same."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []

    def hold(signum: int, _frame: FrameType | None) -> None:
        pending.append(signum)

    held = (signal.SIGINT, signal.SIGTERM)
    previous = {sig: signal.signal(sig, hold) for sig in held}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for signum in pending:
            handler = previous[signal.Signals(signum)]
            if callable(handler):
                handler(signum, None)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(signum)


def reap_exited_children() -> list[int]:
    """Collect every child of this process that has exited and nobody waited for (a helper
    a library ran during an import that a Ctrl-C cut short): without this they would stay
    zombies once this process is gone. Running children are left alone. Returns their pids."""
    reaped: list[int] = []
    while True:
        try:
            pid, _status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return reaped
        if pid == 0:
            return reaped
        reaped.append(pid)


def start_module(
    config: ModuleConfig, reports: Reports, *, thread: bool, workdir: Path, flash_image: bytes | None = None
) -> ModuleHandle:
    """Start one module as a thread (in-process buses) or as a process whose config and
    flash (holding ``flash_image``, a signed image, or else the config's image) are written
    under ``workdir``. A thread boots from a flash holding ``flash_image`` too, or, with no
    signed image, runs the config's image as it is."""
    if thread:
        if flash_image is None:  # nothing signed (no cryptography): the image as it is
            return ThreadModule(config, reports)
        # a thread boots from a flash of its own too (kept across its lives), so that it
        # takes part in rollouts as a process does
        flash = workdir / config.label / "flash"
        flash.mkdir(parents=True, exist_ok=True)
        (flash / IMAGE_NAME).write_bytes(flash_image)
        return ThreadModule(replace(config, flash=str(flash)), reports)
    return ProcessModule(config, reports, workdir, flash_image)
