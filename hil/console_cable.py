"""The launcher's ``--console FILE``: a cable for ``dh2rt console`` into the first module's
free connector (docs/console.md), as ``--event CYCLE:flash:M:IMAGE`` plugs a flasher's.

On serial links the cable is one more emulated link (a pty pair of the link emulator) into
that connector; the pty's path is written to FILE once the robot runs, and the cable stays in
until the run ends. The console is a process of its own, so its transport's counts are out of
the launcher's reach: the run counts its frames as the link emulator carried them (what it
sent from the cable's end, what it wrote there for the console to read), which keeps the
run's frames adding up (docs/hil.md, "Counting frames").
"""

from __future__ import annotations

import os
from pathlib import Path

from dh2rt.errors import EventError
from dh2rt.topology import Topology
from dh2rt.transport.base import LinkCounters
from hil.world import World


def free_connector(topology: Topology, module: int) -> int:
    """The first connector of ``module`` nothing docks to; EventError if none is free."""
    docked = {(lk.a, lk.a_conn) for lk in topology.links} | {(lk.b, lk.b_conn) for lk in topology.links}
    for c in range(1, topology.profile.connector_count + 1):
        if (module, c) not in docked:
            return c
    raise EventError(f"--console: module {topology.names[module]} has no free connector for the cable")


class ConsoleCable:
    """The console's cable of one run: plugged in by :meth:`step` once the world cycles."""

    def __init__(self, world: World, path_file: Path, module: int = 0) -> None:
        self.world = world
        self.path_file = path_file
        self.module = module
        self.connector = free_connector(world.topology, module)
        #: the cable's pty (the console opens it) once plugged in
        self.port: str | None = None

    def step(self) -> None:
        """Plug the cable in at the first cycle and say where it is."""
        if self.port is not None:
            return
        world = self.world
        _link_id, self.port = world.plug_cable(self.module, self.connector)
        tmp = self.path_file.with_name(self.path_file.name + ".tmp")
        tmp.write_text(self.port + "\n")
        os.replace(tmp, self.path_file)  # a reader never sees half a path
        world.note(f"--console: cable into {world.where(self.module, self.connector)} at {self.port}")

    def close(self) -> None:
        """The run ended (its world stopped): count the console's frames as the link carried them."""
        if self.port is None or self.world.emulator is None:
            return
        side = self.world.emulator.side_counts(self.port)
        self.world.count_cable(LinkCounters(sent=side.sent, received=side.written - side.unread))
        self.path_file.unlink(missing_ok=True)
