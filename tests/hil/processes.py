"""What the loop tests share about the processes a run leaves behind."""

from __future__ import annotations

import os


def alive(pid: int) -> bool:
    """Whether a process with this id still exists (a zombie counts: it was not reaped)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True
