"""The launcher's ``--capture FILE``: taps on the robot's traffic, written to a capture file.

* On a bus (``virtual``, ``udp`` inside the launcher's network namespace, SocketCAN), a
  :class:`BusTap` opens a python-can bus of its own on the robot's channel before any module
  starts and hands every frame it receives to the sink: it sees what a ``candump`` on the
  same bus would see.
* On serial links, the link emulator's tap (:class:`~hil.link_emulator.LinkEmulator`) hands
  over every frame on every link, with the side that sent it and whether it was lost.

The sink (what writes the file, its format chosen by the suffix) lives in ``tools/``, which
this layer does not import: :func:`open_capture_sink` finds it through the entry-point group
``dh2rt.capture_sinks``, as the umbrella command finds the launcher.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, Protocol

from dh2rt.closing import Closing
from dh2rt.errors import HilWorldError, OptionError, TransportUnavailable

SINK_GROUP = "dh2rt.capture_sinks"
#: Transports whose frames a capture can see (``inproc`` passes objects, not frames).
CAPTURABLE = ("serial", "virtual", "udp", "socketcan", "can")
#: python-can's interface of each bus transport (``can`` names its own).
PYTHON_CAN = {"virtual": "virtual", "udp": "udp_multicast", "socketcan": "socketcan"}


class CaptureSink(Protocol):
    """What the taps write to (``tools.capture_sink.FileSink``)."""

    count: int
    #: whether the file can hold serial link frames (pcapng)
    serial: bool

    def write_message(self, msg: Any) -> None: ...

    def serial_frame(self, timestamp: float, link: int, side: int, wire: bytes, *, lost: bool = False) -> None: ...

    def cycle_mark(
        self, record: Mapping[str, Any], links: Mapping[int, tuple[tuple[int, int], tuple[int, int]]]
    ) -> None: ...

    def links_now(self, links: Mapping[int, tuple[tuple[int, int], tuple[int, int]]]) -> None: ...

    def close(self) -> None: ...


def open_capture_sink(path: Path, programs: Sequence[bytes]) -> CaptureSink:
    """A sink writing ``path`` with ``programs`` inside (or beside) it; OptionError for a
    suffix no sink writes, HilWorldError when no sink is installed."""
    found = {ep.name: ep for ep in entry_points(group=SINK_GROUP)}
    if "file" not in found:
        raise HilWorldError(
            f"--capture needs the capture tools (entry point {SINK_GROUP}:file): pip install 'dh2rt[tools]'"
        )
    sink: CaptureSink = found["file"].load()(path, programs)
    return sink


def check_capture(path: Path, transport_kind: str, serial_ok: bool) -> None:
    """Refuse a capture this run cannot write, before anything starts."""
    if transport_kind not in CAPTURABLE:
        raise OptionError(
            f"--capture: --transport {transport_kind} has no frames on a wire to capture; "
            f"use one of {', '.join(CAPTURABLE)}"
        )
    if transport_kind == "serial" and not serial_ok:
        raise OptionError(f"--capture {path}: serial link frames are written to a .pcapng file only")


class BusTap(Closing):
    """Every frame on one python-can bus, handed to ``sink`` from a thread of its own."""

    def __init__(self, interface: str, channel: str, sink: CaptureSink, **options: Any) -> None:
        import can

        try:
            self._bus: Any = can.Bus(interface=interface, channel=channel, **options)
        except (can.CanError, OSError, ImportError, ValueError) as exc:
            raise TransportUnavailable(f"--capture: cannot open python-can {interface} on {channel!r}: {exc}") from exc
        self._can: Any = can
        self.sink = sink
        self.errors = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="dh2rt-capture-tap", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self._bus.recv(timeout=0.1)
            except self._can.CanOperationError:  # an undecodable datagram: counted, not fatal
                self.errors += 1
                continue
            if msg is not None:
                self.sink.write_message(msg)

    def close(self) -> None:
        """Stop reading (after the frames already received are written) and close the bus."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(2.0)
        self._bus.shutdown()
