"""The pty pairs the loop's emulators (serial links, contacts, slcan adapters) play hardware
with: a raw pair whose master the emulator reads without blocking, and the slave's path the
module opens as its port."""

from __future__ import annotations

import contextlib
import os
import tty


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
