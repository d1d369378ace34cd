"""The frame accounting identity a loop run's summary must satisfy (hil/launcher.py): every
frame sent, and every extra chunk a split made, ends in exactly one of ENDS."""

from __future__ import annotations

#: The terms a frame ends in (the right-hand side of the identity).
ENDS = ("received", "corrupted", "dropped", "unhandled", "read_by_killed", "lost_on_link", "unread", "merged")


def adds_up(frames: dict[str, int]) -> None:
    """Every term measured, and the identity holding with none unaccounted."""
    assert frames["unaccounted"] == 0, frames
    assert frames["sent"] + frames["split"] == sum(frames[k] for k in ENDS), frames
