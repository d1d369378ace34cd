"""Where captured frames go: one file, its format chosen by its suffix.

* ``.pcapng`` (the default): CAN frames and the serial links' frames, with the program images
  in the section header (:mod:`tools.pcapng`);
* ``.pcap``: CAN frames only (link type 227);
* ``.log`` (candump -L), ``.blf``, ``.asc``, ``.csv``, ``.trc``: CAN frames only, written by
  python-can's own writers.

Formats other than pcapng get the program images in a sidecar file beside the capture
(:func:`tools.capture_reader.write_sidecar`), so every capture decodes with nothing else.

A loop run's capture also keeps the modules' cycle marks beside it (:meth:`FileSink.cycle_mark`,
:mod:`tools.capture_cycles`): what ``dh2rt replay`` needs that the wire does not say.

:func:`open_sink` is what the launcher's ``--capture`` finds through the entry-point group
``dh2rt.capture_sinks``: the launcher lives in ``hil/`` and does not import ``tools/``. The
sink is thread-safe: the launcher's bus tap and its serial link tap write from their own
threads.
"""

from __future__ import annotations

import copy
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO, Any

from dh2rt.errors import DecodeError, OptionError
from dh2rt.wire.serial_framing import decode_serial
from tools import capture_cycles, serial_records
from tools.capture_reader import PYTHON_CAN_SUFFIXES, write_sidecar
from tools.pcap import CapturedFrame, PcapWriter, socketcan_packet
from tools.pcapng import CAN_INTERFACE, SERIAL_INTERFACE, PcapngWriter
from tools.serial_records import SerialRecord

#: Suffixes a capture can be written in; only pcapng holds the serial links' frames.
SUFFIXES = (".pcapng", ".pcap", *(s for s in PYTHON_CAN_SUFFIXES if s != ".db"))
SERIAL_SUFFIXES = (".pcapng",)


class FileSink:
    """Writes frames to ``path``; ``programs`` are the images the robot runs (see module docs)."""

    def __init__(self, path: Path, programs: Sequence[bytes] = ()) -> None:
        suffix = path.suffix.lower()
        if suffix not in SUFFIXES:
            raise OptionError(f"{path}: a capture is written as {', '.join(SUFFIXES)}, not {suffix or 'no suffix'}")
        self.path = path
        self.count = 0
        self.serial = suffix in SERIAL_SUFFIXES
        self._lock = threading.Lock()
        self._pcapng: PcapngWriter | None = None
        self._pcap: PcapWriter | None = None
        self._logger: Any = None
        #: BLF and ASC number their channels; other formats keep python-can's channel as it is
        self._numbered_channels = suffix in (".blf", ".asc")
        self._links_marked: dict[int, tuple[tuple[int, int], tuple[int, int]]] = {}
        self._marks: IO[str] | None = None  # opened at the first mark (see cycle_mark)
        if suffix == ".pcapng":
            self._pcapng = PcapngWriter(path, programs)
        elif suffix == ".pcap":
            self._pcap = PcapWriter(path)
        else:
            import can

            self._logger = can.Logger(str(path))
        if programs and self._pcapng is None:
            write_sidecar(path, programs)
        # the marks of a capture this one replaces must not pass for this one's
        capture_cycles.marks_path(path).unlink(missing_ok=True)

    def write_message(self, msg: Any) -> None:
        """One CAN frame as python-can received it (a ``can.Message``)."""
        with self._lock:
            if self._pcapng is not None:
                self._pcapng.write(CAN_INTERFACE, float(msg.timestamp), socketcan_packet(_captured(msg)))
            elif self._pcap is not None:
                self._pcap.write(_captured(msg))
            else:
                self._logger.on_message_received(_numbered(msg) if self._numbered_channels else msg)
            self.count += 1

    def serial_frame(self, timestamp: float, link: int, side: int, wire: bytes, *, lost: bool = False) -> None:
        """One frame on an emulated serial link, as the link emulator's tap saw it."""
        if self._pcapng is None:
            raise OptionError(f"{self.path}: serial link frames need a .pcapng capture")
        try:
            decode_serial(wire[:-1] if wire.endswith(b"\x00") else wire)
            corrupted = False
        except DecodeError:
            corrupted = True
        packet = serial_records.pack(SerialRecord(timestamp, link, side, wire, lost, corrupted))
        with self._lock:
            self._pcapng.write(SERIAL_INTERFACE, timestamp, packet)
            self.count += 1

    def cycle_mark(
        self, record: Mapping[str, Any], links: Mapping[int, tuple[tuple[int, int], tuple[int, int]]]
    ) -> None:
        """A module's report of one cycle (its trace record), kept as a cycle mark beside
        the capture (:mod:`tools.capture_cycles`), after a link mark for each of ``links``
        (link id -> (module, connector) at side 0 and side 1: the links docked now) not marked
        yet, and an unlink mark for each marked link no longer among them. Marks are not
        frames: :attr:`count` does not count them."""
        with self._lock:
            marks = self._mark_links(links)
            started = capture_cycles.wall_time(float(record["t"]))
            marks.write(capture_cycles.line(capture_cycles.cycle_mark_json(record), started))

    def links_now(self, links: Mapping[int, tuple[tuple[int, int], tuple[int, int]]]) -> None:
        """The links docked now, at once (the world undocked one: its mark's time is the
        cut's, before the frames lost into it)."""
        with self._lock:
            self._mark_links(links)

    def _mark_links(self, links: Mapping[int, tuple[tuple[int, int], tuple[int, int]]]) -> IO[str]:
        now = time.time()
        if self._marks is None:
            self._marks = capture_cycles.marks_path(self.path).open("w", encoding="utf-8")
            self._marks.write(capture_cycles.header())
        for link in sorted(set(self._links_marked) - set(links)):  # undocked since
            gone = capture_cycles.link_mark_json(link, self._links_marked.pop(link), docked=False)
            self._marks.write(capture_cycles.line(gone, now))
        for link, ends in sorted(links.items()):
            if link not in self._links_marked:
                self._links_marked[link] = ends
                self._marks.write(capture_cycles.line(capture_cycles.link_mark_json(link, ends), now))
        return self._marks

    def flush(self) -> None:
        with self._lock:
            if self._pcapng is not None:
                self._pcapng.flush()

    def close(self) -> None:
        with self._lock:
            if self._pcapng is not None:
                self._pcapng.close()
            if self._pcap is not None:
                self._pcap.close()
            if self._logger is not None:
                self._logger.stop()
            if self._marks is not None:
                self._marks.close()


def open_sink(path: Path, programs: Sequence[bytes] = ()) -> FileSink:
    """The ``dh2rt.capture_sinks`` entry point: a sink writing ``path``."""
    return FileSink(path, programs)


def _captured(msg: Any) -> CapturedFrame:
    """A python-can message as the capture files hold it."""
    return CapturedFrame(
        float(msg.timestamp),
        int(msg.arbitration_id),
        bytes(msg.data),
        is_extended_id=msg.is_extended_id,
        is_remote_frame=msg.is_remote_frame,
        is_error_frame=msg.is_error_frame,
        is_fd=msg.is_fd,
        bitrate_switch=msg.bitrate_switch,
    )


def _numbered(msg: Any) -> Any:
    """``msg`` with a channel BLF and ASC can number: python-can makes a number of the digits
    in a channel's name (``vcan0`` is 0), and a name such as ``robot-2026`` would not fit the
    formats' 16 bits; such a frame is logged with no channel rather than not at all."""
    from can.util import channel2int

    number = channel2int(msg.channel)
    if number is not None and 0 <= number < 0xFFFF:
        return msg
    plain = copy.copy(msg)
    plain.channel = None
    return plain
