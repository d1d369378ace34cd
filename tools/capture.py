"""``dh2rt capture -o FILE -i INTERFACE -c CHANNEL``: record a robot's CAN traffic from any
python-can bus (interface and channel named as python-can's own tools name them), until
``--duration`` seconds, ``--count`` frames or Ctrl-C. The format follows the suffix
(:mod:`tools.capture_sink`): pcapng (``.pcapng``, for Wireshark and tshark), pcap (``.pcap``,
link type 227) or any format python-can writes (``.log`` candump -L, ``.blf``, ``.asc``,
``.csv``, ``.trc``). ``--program`` puts the program's image in the capture (pcapng) or beside
it, so that the capture decodes with nothing else. Progress (frames, frames/s) on stderr when
it is a terminal; a summary line at the end.

The output is checked before the bus is opened, by the rule every command follows
(:func:`dh2rt.output_paths.check_output`): an existing capture is kept unless ``--force``.
python-can's ``virtual`` bus lives inside one process, so a capture of it from this command
would wait for ever for frames no other process can send: it is refused, unless another bus
of the same process has the channel open (a test's sender; the launcher's ``--capture``
records a virtual bus from inside the run).

Exit codes: 0 ok, 2 bad input (an output path or a bus that cannot be opened; the message
names it), 130 Ctrl-C (the file closed whole first: what was captured is readable).
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from dh2rt.cmdline import EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, add_bus_arguments, bus_options, err
from dh2rt.errors import CaptureError, OptionError, ProgramError
from dh2rt.output_paths import check_output
from tools.capture_sink import SUFFIXES, FileSink
from tools.reading import interruptible, program_file


def nobody_else_on(interface: str, channel: str) -> bool:
    """True for python-can's ``virtual`` bus on a channel no other bus of this process has
    open: a virtual bus exists only inside one process, so nothing could ever be sent on it
    (always so when ``dh2rt capture`` runs as a command of its own)."""
    if interface != "virtual":
        return False
    from can.interfaces import virtual

    with virtual.channels_lock:
        return not virtual.channels.get(channel)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dh2rt capture",
        description="Record a robot's CAN traffic from a python-can bus to a pcapng, pcap or python-can log file.",
        epilog="Example: dh2rt capture -o robot.pcapng -i socketcan -c vcan0 --program caterpillar.dh2 --duration 10",
    )
    p.add_argument("-o", "--output", type=Path, required=True, help=f"the capture file ({', '.join(SUFFIXES)})")
    add_bus_arguments(p, required=True)
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--count", type=int, help="stop after this many frames")
    p.add_argument(
        "--program", type=Path, help="the .dh2 program the robot runs, or its image: the image goes with the capture"
    )
    p.add_argument("--force", action="store_true", help="overwrite an existing capture")
    return p


@interruptible
def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        ns = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code) if isinstance(exc.code, int) else EXIT_USAGE
    try:
        path = check_output(ns.output, "-o", SUFFIXES, force=ns.force)
        if nobody_else_on(ns.interface, ns.channel):
            raise OptionError(
                f"-i {ns.interface}: python-can's virtual bus exists only inside the process that opens it, "
                "so this command would record nothing, for ever; capture a loop run with the launcher's "
                "--capture (dh2rt --transport virtual --capture FILE), or a bus other processes share "
                "(socketcan, udp_multicast in a network namespace, a CAN adapter)"
            )
        if ns.count is not None and ns.count < 1:
            raise OptionError(f"--count {ns.count}: must be 1 or more")
        if ns.duration is not None and not (math.isfinite(ns.duration) and ns.duration > 0):
            raise OptionError(f"--duration {ns.duration}: must be a positive number of seconds")
        programs = [program_file(ns.program).image] if ns.program else []
    except (OptionError, CaptureError) as exc:
        err(str(exc))
        return EXIT_USAGE
    except ProgramError as exc:
        print(exc.render(), file=sys.stderr)
        return EXIT_USAGE
    import can

    try:
        bus = can.Bus(**bus_options(ns))
    except Exception as exc:  # python-can raises what each interface raises: name the bus
        err(f"cannot open python-can {ns.interface} bus on channel {ns.channel!r}: {exc}")
        return EXIT_USAGE
    sink = FileSink(path, programs)
    count, started = 0, time.monotonic()
    deadline = None if ns.duration is None else started + ns.duration
    progress = sys.stderr.isatty()
    stop: list[int] = []
    # Ctrl-C ends a capture (its file closed and whole, then exit 130); only the main thread can
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
            sink.write_message(msg)
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
    return EXIT_INTERRUPTED if stop else EXIT_OK
