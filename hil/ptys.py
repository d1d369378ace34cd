"""The pty pairs the loop's emulators (serial links, contacts, slcan adapters) play hardware
with: a raw pair whose master the emulator reads without blocking, and the slave's path the
module opens as its port; and the one relay thread each emulator reads its masters with."""

from __future__ import annotations

import contextlib
import os
import selectors
import threading
import tty
from collections.abc import Callable

#: How long the relay waits for a byte when nothing else is due (it wakes for a stop at once).
IDLE_WAIT_S = 0.2


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
    """

    def __init__(
        self,
        name: str,
        lock: threading.Lock,
        on_read: Callable[[int, bytes], None],
        *,
        wait: Callable[[], float] = lambda: IDLE_WAIT_S,
        after_reads: Callable[[], None] | None = None,
    ) -> None:
        self.lock = lock
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

    def _run(self) -> None:
        while True:
            with self.lock:
                if self.closed:
                    return
                timeout = self._wait()
            for key, _ in self._sel.select(timeout):
                fd = int(key.fd)
                try:
                    data = os.read(fd, 4096)
                except OSError:  # EIO: no module has the port open right now; nothing to read
                    continue
                if fd != self._wake_r and data:
                    self._on_read(fd, data)
            if self._after_reads is not None:
                self._after_reads()
