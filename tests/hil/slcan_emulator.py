"""A CAN bus of slcan adapters, emulated on ptys: each module opens "its" USB-CAN adapter with
python-can's own ``slcan`` interface, and the emulator carries frames between all the
adapters whose channel is open at the same bitrate, as the wire between real adapters would.

The adapters speak the Lawicel (CANUSB/CANable) ASCII protocol python-can's slcan driver
speaks, one command per line ended by ``\\r``:

* ``S0`` .. ``S8`` set the bitrate (10 kbit/s .. 1 Mbit/s), ``O`` opens the channel, ``L``
  opens it listening only, ``C`` closes it, ``V``/``N`` ask for version and serial number:
  answered ``\\r`` (or with the value), or ``\\a`` (BEL) for a command it does not know;
* ``t``/``T``/``r``/``R``/``d``/``D``/``b``/``B`` transmit a frame (standard/extended id, remote,
  FD, FD with bitrate switch): answered ``z\\r`` (``Z\\r`` for an extended id), and the same
  line delivered to every other open adapter at the same bitrate (never back to the sender,
  as a real adapter does not echo), in the order the emulator read them.

A frame sent on a closed or listen-only channel is refused with ``\\a`` and delivered nowhere.
``close()`` stops the thread and closes every pty. Test-only (tests/hil/test_real_ports.py):
no adapter is needed to run the slcan path of the loop.
"""

from __future__ import annotations

import contextlib
import os
import threading
from dataclasses import dataclass, field

from dh2rt.closing import Closing
from hil.ptys import PtyRelay, close_fd, open_raw_pty

#: slcan's bitrate commands S0..S8, in bit/s.
BITRATES = (10_000, 20_000, 50_000, 100_000, 125_000, 250_000, 500_000, 800_000, 1_000_000)
OK, ERROR = b"\r", b"\a"
FRAME_COMMANDS = b"tTrRdDbB"


@dataclass(slots=True)
class Adapter:
    """One emulated USB-CAN adapter: ``path`` is the port a module opens."""

    master: int
    slave: int
    path: str
    bitrate: int | None = None
    open: bool = False
    listen_only: bool = False
    pending: bytearray = field(default_factory=bytearray)
    sent: int = 0
    received: int = 0
    refused: int = 0


class SlcanBusEmulator(Closing):
    """Adapters on one emulated bus (see the module docs)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._adapters: dict[int, Adapter] = {}
        self._ptys = PtyRelay("dh2rt-slcan-bus", self._lock, self._from_master)

    def add_adapter(self) -> Adapter:
        """A new adapter on the bus; open ``adapter.path`` with ``can.Bus(interface="slcan", ...)``."""
        master, slave, path = open_raw_pty()
        adapter = Adapter(master, slave, path)
        with self._lock:
            self._adapters[master] = adapter
            self._ptys.watch(master)
        return adapter

    @property
    def adapters(self) -> list[Adapter]:
        with self._lock:
            return list(self._adapters.values())

    def close(self) -> None:
        if not self._ptys.stop():
            return
        for adapter in self._adapters.values():
            close_fd(adapter.master)
            close_fd(adapter.slave)
        self._adapters.clear()

    # -- the bus thread -------------------------------------------------------------------

    def _from_master(self, fd: int, data: bytes) -> None:
        with self._lock:
            adapter = self._adapters.get(fd)
            if adapter is not None:
                adapter.pending += data
                self._lines(adapter)

    def _lines(self, adapter: Adapter) -> None:
        while (end := adapter.pending.find(b"\r")) >= 0:
            line = bytes(adapter.pending[:end])
            del adapter.pending[: end + 1]
            if line:
                self._write(adapter, self._command(adapter, line))

    def _command(self, adapter: Adapter, line: bytes) -> bytes:
        head, rest = line[:1], line[1:]
        if head == b"S" and rest.isdigit() and int(rest) < len(BITRATES):
            adapter.bitrate = BITRATES[int(rest)]
            return OK
        if head in (b"O", b"L") and not rest:
            adapter.open, adapter.listen_only = True, head == b"L"
            return OK
        if head == b"C" and not rest:
            adapter.open = False
            return OK
        if head == b"V":
            return b"V1013\r"
        if head == b"N":
            return b"NDH2R\r"
        if head and head in FRAME_COMMANDS:
            return self._transmit(adapter, line)
        return ERROR

    def _transmit(self, sender: Adapter, line: bytes) -> bytes:
        if not sender.open or sender.listen_only:
            sender.refused += 1
            return ERROR
        sender.sent += 1
        for other in self._adapters.values():
            if other is not sender and other.open and other.bitrate == sender.bitrate:
                self._write(other, line + b"\r")
                other.received += 1
        return b"Z\r" if line[:1] in b"TRDB" else b"z\r"

    @staticmethod
    def _write(adapter: Adapter, data: bytes) -> None:
        with contextlib.suppress(OSError):  # a full pty (a module not reading) drops, as a bus overrun
            os.write(adapter.master, data)
