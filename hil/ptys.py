"""The pty pairs the loop's emulators (serial links, contacts, slcan adapters) play hardware
with: a raw pair whose master the emulator reads without blocking, and the slave's path the
module opens as its port; and the one relay thread each emulator reads its masters with."""

from __future__ import annotations

import contextlib
import os
import selectors
import threading
import time
import tty
from collections import deque
from collections.abc import Callable

#: How long the relay waits for a byte when nothing else is due (it wakes for a stop at once).
IDLE_WAIT_S = 0.2

#: With ``watch_held``, the longest the relay waits at a time: how finely it notices being held.
HELD_TICK_S = 0.005
#: Holds shorter than this are not kept as episodes (a round's own work is about 0.1 ms).
HELD_KEEP_S = 0.002
#: Hold episodes kept (the latest).
HELD_EPISODES = 4096
#: The relays play wires, which no busy processor holds up: their threads run at this nice
#: value, above the module processes and the world's own work (Linux keeps a nice value per
#: thread; lowering it needs root or CAP_SYS_NICE, and without either the thread runs as it is).
RELAY_NICE = -10


def run_as_hardware() -> None:
    """Give the calling thread RELAY_NICE: it plays hardware (a wire, a servo's controller),
    which no busy processor holds up. Without the privilege it runs at the default."""
    with contextlib.suppress(OSError):  # EACCES without root or CAP_SYS_NICE
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), RELAY_NICE)


def open_raw_pty() -> tuple[int, int, str]:
    """A raw pty pair: (master, non-blocking; slave; the slave's path)."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    os.set_blocking(master, False)
    return master, slave, os.ttyname(slave)


def close_fd(fd: int) -> None:
    """Close ``fd``; one already closed (or never valid) is not an error at shutdown."""
    with contextlib.suppress(OSError):
        os.close(fd)


class PtyRelay:
    """The thread an emulator relays its ptys with: it waits on every pty master it was given
    (and a wake-up pipe) in one selector, and hands each read to ``on_read(master, data)``,
    outside ``lock``; ``after_reads()`` runs after each round of reads (what is due goes out).

    ``lock`` is the emulator's own: :attr:`closed` is read and set under it, and ``wait()``
    (how long the next round may wait for a byte, in seconds) is called under it. A master
    that cannot be read (EIO: no module has its port open) or at its end is skipped.

    With ``watch_held`` the thread measures how long the machine held it: each round waits
    at most HELD_TICK_S, and :attr:`held_s` is the most a round ended later than its wait
    allowed (the time from the previous round's end, less the wait: a relay held up holds
    every byte it carries that long, which neither module's own lateness shows), and
    :attr:`holds` the latest holds of HELD_KEEP_S or more as ``(ended, seconds)`` on
    ``time.monotonic()`` (CLOCK_MONOTONIC, the modules' trace clock).
    """

    def __init__(
        self,
        name: str,
        lock: threading.Lock,
        on_read: Callable[[int, bytes], None],
        *,
        wait: Callable[[], float] = lambda: IDLE_WAIT_S,
        after_reads: Callable[[], None] | None = None,
        watch_held: bool = False,
    ) -> None:
        self.lock = lock
        #: the most the machine held this thread (s), measured with ``watch_held``
        self.held_s = 0.0
        #: the latest holds: (when each ended, how long it was), oldest first
        self.holds: deque[tuple[float, float]] = deque(maxlen=HELD_EPISODES)
        self._watch_held = watch_held
        #: set by :meth:`stop`; an emulator adds no pty once it is
        self.closed = False
        self._on_read = on_read
        self._wait = wait
        self._after_reads = after_reads
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)
        self._sel.register(self._wake_r, selectors.EVENT_READ)
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def watch(self, master: int) -> None:
        """Relay what ``master`` reads from now on."""
        self._sel.register(master, selectors.EVENT_READ)
        self.wake()

    def wake(self) -> None:
        """End the thread's current wait (a new master, a new deadline, a stop)."""
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")

    def stop(self) -> bool:
        """Stop the thread and close the selector and the pipe; False if it was stopped
        already. The emulator closes its own ptys after."""
        with self.lock:
            if self.closed:
                return False
            self.closed = True
        self.wake()
        self._thread.join(5)
        self._sel.close()
        close_fd(self._wake_r)
        close_fd(self._wake_w)
        return True

    @property
    def native_id(self) -> int | None:
        """The relay thread's id in the kernel (its nice value is its own: RELAY_NICE)."""
        return self._thread.native_id

    def _run(self) -> None:
        run_as_hardware()
        last = time.monotonic()
        while True:
            with self.lock:
                if self.closed:
                    return
                timeout = self._wait()
            if self._watch_held:
                timeout = min(timeout, HELD_TICK_S)
            ready = self._sel.select(timeout)
            if self._watch_held:
                now = time.monotonic()
                held = now - last - timeout
                self.held_s = max(self.held_s, held)
                if held >= HELD_KEEP_S:
                    self.holds.append((now, held))
                last = now
            for key, _ in ready:
                fd = int(key.fd)
                try:
                    data = os.read(fd, 4096)
                except OSError:  # EIO: no module has the port open right now; nothing to read
                    continue
                if fd != self._wake_r and data:
                    self._on_read(fd, data)
            if self._after_reads is not None:
                self._after_reads()
