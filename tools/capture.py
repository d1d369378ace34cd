"""``dh2rt capture -o FILE -i INTERFACE -c CHANNEL``: record a robot's CAN traffic from any
python-can bus (interface and channel named as python-can's own tools name them), until
``--duration`` seconds, ``--count`` frames or Ctrl-C. The format follows the suffix: pcap
(``.pcap``, link type 227, for Wireshark and tshark) or any format python-can writes
(``.log`` candump -L, ``.blf``, ``.asc``, ``.csv``, ``.trc``). Progress (frames, frames/s)
on stderr when it is a terminal; a summary line at the end.

Exit codes: 0 ok (Ctrl-C ends a capture normally), 2 bad input (an output path or a bus that
cannot be opened; the message names it).
"""

from __future__ import annotations

import argparse
import copy
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dh2rt.cmdline import EXIT_OK, EXIT_USAGE, err, output_path
from dh2rt.errors import OptionError
from tools.capture_files import PYTHON_CAN_SUFFIXES
from tools.pcap import CapturedFrame, PcapWriter

SUFFIXES = (".pcap", *(s for s in PYTHON_CAN_SUFFIXES if s != ".db"))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dh2rt capture",
        description="Record a robot's CAN traffic from a python-can bus to a pcap or python-can log file.",
        epilog="Example: dh2rt capture -o robot.pcap -i socketcan -c vcan0 --duration 10",
    )
    p.add_argument("-o", "--output", type=Path, required=True, help=f"the capture file ({', '.join(SUFFIXES)})")
    p.add_argument(
        "-i", "--interface", required=True, help="python-can interface: socketcan, virtual, udp_multicast, ..."
    )
    p.add_argument("-c", "--channel", required=True, help="python-can channel: vcan0, a virtual channel name, ...")
    p.add_argument("-b", "--bitrate", type=int, help="bitrate, where the interface takes one")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--count", type=int, help="stop after this many frames")
    return p


class _Sink:
    """Where captured frames go: our pcap writer or a python-can logger."""

    def __init__(self, path: Path) -> None:
        self.pcap: PcapWriter | None = None
        self.logger: Any = None
        #: BLF and ASC number their channels; other formats keep python-can's channel as it is
        self.numbered_channels = path.suffix.lower() in (".blf", ".asc")
        if path.suffix.lower() == ".pcap":
            self.pcap = PcapWriter(path)
        else:
            import can

            self.logger = can.Logger(str(path))

    def write(self, msg: Any) -> None:
        if self.pcap is not None:
            frame = CapturedFrame(
                msg.timestamp,
                msg.arbitration_id,
                bytes(msg.data),
                is_extended_id=msg.is_extended_id,
                is_remote_frame=msg.is_remote_frame,
                is_error_frame=msg.is_error_frame,
                is_fd=msg.is_fd,
                bitrate_switch=msg.bitrate_switch,
            )
            self.pcap.write(frame)
        else:
            if self.numbered_channels:
                msg = _numbered(msg)
            self.logger.on_message_received(msg)

    def close(self) -> None:
        if self.pcap is not None:
            self.pcap.close()
        if self.logger is not None:
            self.logger.stop()


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


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        ns = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code) if isinstance(exc.code, int) else EXIT_USAGE
    try:
        path = output_path(ns.output, "-o", SUFFIXES)
        if ns.count is not None and ns.count < 1:
            raise OptionError(f"--count {ns.count}: must be 1 or more")
        if ns.duration is not None and ns.duration <= 0:
            raise OptionError(f"--duration {ns.duration}: must be positive")
    except OptionError as exc:
        err(str(exc))
        return EXIT_USAGE
    import can

    options: dict[str, Any] = {"interface": ns.interface, "channel": ns.channel}
    if ns.bitrate:
        options["bitrate"] = ns.bitrate
    try:
        bus = can.Bus(**options)
    except Exception as exc:  # python-can raises what each interface raises: name the bus
        err(f"cannot open python-can {ns.interface} bus on channel {ns.channel!r}: {exc}")
        return EXIT_USAGE
    sink = _Sink(path)
    count, started = 0, time.monotonic()
    deadline = None if ns.duration is None else started + ns.duration
    progress = sys.stderr.isatty()
    stop: list[int] = []
    # Ctrl-C ends a capture normally (its file closed and whole); only the main thread can
    # take signals, so a capture run from another thread stops by duration or count
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, lambda signum, _f: stop.append(signum)) if main_thread else None
    try:
        while not stop and (ns.count is None or count < ns.count):
            timeout = 0.2 if deadline is None else min(0.2, deadline - time.monotonic())
            if timeout <= 0:
                break
            msg = bus.recv(timeout)
            if msg is None:
                continue
            sink.write(msg)
            count += 1
            if progress and count % 500 == 0:
                rate = count / max(1e-9, time.monotonic() - started)
                sys.stderr.write(f"\r{count} frames, {rate:,.0f}/s ")
    finally:
        if main_thread:
            signal.signal(signal.SIGINT, previous)
        sink.close()
        bus.shutdown()
    elapsed = time.monotonic() - started
    if progress:
        sys.stderr.write("\r" + " " * 40 + "\r")
    print(f"{path}: {count} frames in {elapsed:.1f} s" + (" (interrupted)" if stop else ""))
    return EXIT_OK
