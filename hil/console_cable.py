"""The launcher's ``--console FILE``: a cable for ``dh2rt console`` into the first module's
free connector (docs/console.md), as ``--event CYCLE:flash:M:IMAGE`` plugs a flasher's.

On serial links the cable is one more emulated link (a pty pair of the link emulator) into
that connector; the pty's path is written to FILE once the robot runs, and the cable stays in
until the run ends. The console is a process of its own, so its transport's counts are out of
the launcher's reach: the run counts its frames as the link emulator carried them (what it
sent from the cable's end, what it wrote there for the console to read), which keeps the
run's frames adding up (docs/hil.md, "Counting frames").

On a bus the launcher plays a serial-to-bus adapter (:class:`BusBridge`, as a USB-CAN gateway
on a cable would be): the console still opens a serial port (a pty, FILE names it), and the
bridge is a node on the bus whose connector-local channel touches the module's free connector,
negotiates a link with it as the flasher's bus cable does, and carries control frames both
ways. Its node's counts are the run's, as a flasher's are.
"""

from __future__ import annotations

import contextlib
import os
import selectors
import threading
import time
from pathlib import Path

from dh2rt.errors import EventError
from dh2rt.topology import Topology
from dh2rt.transport.base import FrameFamily, Inbound, LinkCounters, Transport
from dh2rt.transport.registry import open_transport
from dh2rt.wire.frame import NO_PROGRAM, Hello
from dh2rt.wire.operator import is_control
from dh2rt.wire.serial_framing import SerialDecoder, encode_serial
from drivers.connector_channel import ConnectorChannels
from firmware.flash.cable import HELLO_TICKS, BusCable, hello_codec
from hil.ptys import close_fd, open_raw_pty
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
        #: on a bus: the adapter between that pty and the bus
        self.bridge: BusBridge | None = None

    def step(self) -> None:
        """Plug the cable in at the first cycle and say where it is."""
        if self.port is not None:
            return
        world = self.world
        if world.contacts is not None:
            self.bridge = BusBridge(world, self.module, self.connector)
            self.port = self.bridge.port
        else:
            _link_id, self.port = world.plug_cable(self.module, self.connector)
        tmp = self.path_file.with_name(self.path_file.name + ".tmp")
        tmp.write_text(self.port + "\n")
        os.replace(tmp, self.path_file)  # a reader never sees half a path
        world.note(f"--console: cable into {world.where(self.module, self.connector)} at {self.port}")

    def pull_out(self) -> None:
        """The run ends, its world still up: a bus adapter releases its link and its contact
        (and counts its node's frames), as a flasher's bus cable does when it is done."""
        if self.bridge is not None:
            self.bridge.close()

    def close(self) -> None:
        """The run ended (its world stopped): on serial links, count the console's frames as
        the link carried them."""
        if self.bridge is not None:
            self.path_file.unlink(missing_ok=True)
            return
        if self.port is None or self.world.emulator is None:
            return
        side = self.world.emulator.side_counts(self.port)
        self.world.count_cable(LinkCounters(sent=side.sent, received=side.written - side.unread))
        self.path_file.unlink(missing_ok=True)


class BusBridge:
    """A serial-to-bus adapter for the console on a bus run: a pty (``port``) the console opens
    as its cable, and a node on the bus that negotiates a link with the module's free
    connector over its connector-local channel; control frames cross between the two, and
    the node says it runs no program (Hellos with NO_PROGRAM), as the console does on a serial
    cable. One thread owns the node and the pty."""

    def __init__(self, world: World, module: int, connector: int) -> None:
        self.world, self.module, self.connector = world, module, connector
        self.mate, contact = world.touch_cable(module, connector)
        self.transport: Transport = open_transport(world.transport_spec, hello_codec(), **world.bus_options)
        try:
            self.cable = BusCable(ConnectorChannels.open_emulated({self.mate: contact}), self.transport, self.mate,
                                  now=time.monotonic(), log=lambda line: world.note(f"--console: {line}"))  # fmt: skip
        except BaseException:
            self.transport.close()
            raise
        self.master, self._slave, self.port = open_raw_pty()
        self._decoder = SerialDecoder()
        self.transport.listen(FrameFamily.CONTROL, self._to_console)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._pump, name="dh2rt-console-bridge", daemon=True)
        self._thread.start()

    def _to_console(self, frame: Inbound) -> None:
        if frame.connector == self.mate:
            with contextlib.suppress(OSError):  # no console there (yet): lost, as on a line
                os.write(self.master, encode_serial(frame.payload))

    def _pump(self) -> None:
        period = self.world.cycle_period
        ticks = HELLO_TICKS
        with selectors.DefaultSelector() as selector:
            selector.register(self.master, selectors.EVENT_READ)
            while not self._stop.is_set():
                self.cable.step(time.monotonic())
                ticks += 1
                if ticks >= HELLO_TICKS:
                    ticks = 0
                    self.transport.send(self.mate, Hello(NO_PROGRAM))
                until = time.monotonic() + period
                while (left := until - time.monotonic()) > 0 and not self._stop.is_set():
                    if selector.select(min(left, period / 4)):
                        self._from_console()
                    self.transport.poll(0.0)

    def _from_console(self) -> None:
        try:
            data = os.read(self.master, 4096)
        except (BlockingIOError, OSError):  # EIO: no console has the port open
            return
        for payload in self._decoder.feed(data):
            if is_control(payload):  # the console's Hellos stay on its side of the adapter
                self.transport.send_raw(self.mate, payload)

    def close(self) -> None:
        """Stop the adapter, count its node's frames as the run's, release the link and the contact."""
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.world.count_cable(self.transport.counters, self.transport.held_ends())
        self.cable.close()
        self.transport.close()
        self.world.pull_cable(self.module, self.connector, self.mate)
        close_fd(self.master)
        close_fd(self._slave)
