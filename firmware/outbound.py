"""What a module's sans-IO state machines hand their owner to send: a frame and the connector
it goes out through (the operator channel, :mod:`firmware.operator`; a docking chain's
members and asker, :mod:`firmware.motion`). The owner sends; the machines never touch a port."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Out:
    """A frame to send through ``connector``."""

    connector: int
    frame: bytes
