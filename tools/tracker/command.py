"""``dh2rt tracker``: the modules' poses on the floor, from a camera over the arena, sent over UDP.
Reads frames from a camera (``--camera 0``), a video (``--video FILE``) or a folder of
images (``--frames DIR``, replayed in name order), finds the ArUco markers on the modules'
tops, works out each one's pose on the floor from the camera's calibration (``--calibration
FILE``, :mod:`tools.tracker.calibration`) and publishes one datagram per frame
(:mod:`dh2rt.wire.tracker`) over UDP to each ``--publish HOST:PORT`` (default: loopback, port
47328). docs/tracker.md says more.

A status line (frames/s, markers seen) on stderr when it is a terminal; a summary at the end
(``--json``: one JSON object).

Exit codes: 0 ok, 1 no frame could be read, 2 bad input (the message names the option or the
file's field), 130 Ctrl-C.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import socket
import sys
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from dh2rt.cmdline import EXIT_FAIL, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, err, float_in, int_in
from dh2rt.errors import OptionError
from dh2rt.wire.tracker import DEFAULT_PORT, TrackerDatagram, encode
from tools.reading import interruptible
from tools.tracker.calibration import load_calibration
from tools.tracker.detect import DEFAULT_DICTIONARY, MarkerDetector
from tools.tracker.sources import FrameSource, open_source

DEFAULT_PUBLISH = f"127.0.0.1:{DEFAULT_PORT}"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dh2rt tracker",
        description="Find the ArUco markers on the modules' tops in an overhead camera's frames and "
        "publish their poses on the floor over UDP, one datagram per frame.",
        epilog="Example: dh2rt tracker --camera 0 --calibration camera.json --publish 192.168.4.255:47328",
    )
    source = p.add_argument_group("where frames come from (one of)").add_mutually_exclusive_group(required=True)
    source.add_argument("--camera", type=int_in(0, 255), metavar="INDEX", help="a camera OpenCV opens by index")
    source.add_argument("--video", type=Path, metavar="FILE", help="a video file")
    source.add_argument("--frames", type=Path, metavar="DIR", help="a folder of images (.png .jpg .bmp .tif)")
    p.add_argument(
        "--calibration",
        type=Path,
        required=True,
        metavar="FILE",
        help="the camera's intrinsics and pose over the floor, JSON (docs/tracker.md)",
    )
    p.add_argument(
        "--marker-mm",
        type=float_in(0.0, 10_000.0, low_open=True),
        default=20.0,
        help="the markers' side, black border included, in mm (default: 20)",
    )
    p.add_argument(
        "--dictionary", default=DEFAULT_DICTIONARY, help=f"OpenCV's ArUco dictionary (default: {DEFAULT_DICTIONARY})"
    )
    p.add_argument(
        "--publish",
        action="append",
        metavar="HOST:PORT",
        help="where to send the datagrams; repeatable; a broadcast address reaches a subnet "
        f"(default: {DEFAULT_PUBLISH})",
    )
    p.add_argument(
        "--fps",
        type=float_in(0.0, 1000.0),
        default=0.0,
        help="replay a video or a folder at this rate; 0: as fast as frames are read (default: 0)",
    )
    p.add_argument("--max-frames", type=int_in(1, 2**31), metavar="N", help="stop after N frames")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    return p


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` -> an IPv4 address and port; OptionError naming ``--publish`` otherwise."""
    host, colon, port_text = text.rpartition(":")
    if not colon or not host or not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
        raise OptionError(f"--publish {text!r}: expected HOST:PORT with a port 1..65535")
    try:
        address = socket.getaddrinfo(host, int(port_text), socket.AF_INET, socket.SOCK_DGRAM)[0][4]
    except (socket.gaierror, UnicodeError) as exc:
        raise OptionError(f"--publish {text!r}: no IPv4 address for {host!r} ({exc})") from None
    return str(address[0]), int(address[1])


@dataclass
class Tally:
    """What a run did, for the status line and the summary."""

    started: float = field(default_factory=time.perf_counter)
    frames: int = 0
    unreadable: int = 0
    datagrams: int = 0
    rejected: int = 0
    send_errors: int = 0
    markers: Counter[int] = field(default_factory=Counter)

    @property
    def seconds(self) -> float:
        return time.perf_counter() - self.started

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else 0.0

    def to_json(self, source: str, targets: list[tuple[str, int]]) -> dict[str, Any]:
        return {
            "source": source,
            "frames": self.frames,
            "unreadable": self.unreadable,
            "datagrams": self.datagrams,
            "rejected_detections": self.rejected,
            "send_errors": self.send_errors,
            "seconds": round(self.seconds, 3),
            "frames_per_s": round(self.frames_per_s, 2),
            "markers": {str(m): n for m, n in sorted(self.markers.items())},
            "published_to": [f"{host}:{port}" for host, port in targets],
        }


class StatusLine:
    """frames/s and the markers the last frame showed, redrawn twice a second on a terminal."""

    def __init__(self, stream: IO[str]) -> None:
        self.stream = stream
        self.enabled = stream.isatty()
        self.last = 0.0

    def update(self, tally: Tally, seen: Sequence[int]) -> None:
        now = time.perf_counter()
        if not self.enabled or now - self.last < 0.5:
            return
        self.last = now
        shown = ",".join(map(str, seen)) or "none"
        self.stream.write(f"\rframes {tally.frames}, {tally.frames_per_s:.1f} frames/s, markers {shown}   ")
        self.stream.flush()

    def done(self) -> None:
        if self.enabled and self.last:
            self.stream.write("\n")
            self.stream.flush()


def run(
    source: FrameSource, detector: MarkerDetector, targets: list[tuple[str, int]], ns: argparse.Namespace, tally: Tally
) -> None:
    """Read, detect, publish until the source ends, ``--max-frames`` or Ctrl-C (which the
    caller sees, ``tally`` counting what was done)."""
    status = StatusLine(sys.stderr)
    period = 1.0 / ns.fps if ns.fps else 0.0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock, source:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        due = time.perf_counter()
        try:
            for frame in source:
                if frame.image is None:
                    tally.unreadable += 1
                    continue
                found = detector.detect(frame.image)
                tally.frames += 1
                tally.rejected += found.rejected
                tally.markers.update(pose.marker for pose in found.poses)
                data = encode(TrackerDatagram(tally.frames - 1 & 0xFFFFFFFF, frame.captured_us, tuple(found.poses)))
                for target in targets:
                    try:
                        sock.sendto(data, target)
                    except OSError:  # nobody listening yet (ICMP refused), a full buffer: the next frame
                        tally.send_errors += 1
                tally.datagrams += 1
                status.update(tally, [pose.marker for pose in found.poses])
                if ns.max_frames and tally.frames >= ns.max_frames:
                    break
                if period:
                    due += period
                    time.sleep(max(0.0, due - time.perf_counter()))
        finally:
            status.done()


def summary_line(tally: Tally, source: str) -> str:
    markers = ", ".join(f"{m} ({n})" for m, n in sorted(tally.markers.items())) or "none"
    return (
        f"{source}: {tally.frames} frames in {tally.seconds:.2f} s ({tally.frames_per_s:.1f} frames/s), "
        f"{tally.datagrams} datagrams; markers seen (frames): {markers}"
        + (f"; {tally.unreadable} unreadable image(s)" if tally.unreadable else "")
        + (f"; {tally.rejected} detection(s) rejected" if tally.rejected else "")
    )


@interruptible
def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        ns = parser.parse_args(argv)
    except SystemExit as exc:
        return EXIT_OK if exc.code in (0, None) else EXIT_USAGE
    try:
        targets = [parse_address(text) for text in ns.publish or [DEFAULT_PUBLISH]]
        calibration = load_calibration(ns.calibration)
        detector = MarkerDetector(calibration, ns.marker_mm, ns.dictionary)
        source = open_source(ns)
    except OptionError as exc:
        err(str(exc))
        return EXIT_USAGE
    tally = Tally()
    interrupted = False
    before = None
    with contextlib.suppress(ValueError):  # not the main thread: Ctrl-C is not ours to handle
        # started: Ctrl-C is KeyboardInterrupt now (dh2rt.entry quits quietly while importing)
        before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        run(source, detector, targets, ns, tally)
    except OptionError as exc:  # a frame of another size than the calibration's
        err(f"{source.name}: {exc}")
        return EXIT_USAGE
    except KeyboardInterrupt:
        interrupted = True
    finally:
        if before is not None:
            signal.signal(signal.SIGINT, before)
    if ns.json:
        print(json.dumps(tally.to_json(source.name, targets)))
    else:
        print(summary_line(tally, source.name))
    if interrupted:
        err("interrupted")
        return EXIT_INTERRUPTED
    if not tally.frames:
        err(f"{source.name}: no frame could be read")
        return EXIT_FAIL
    return EXIT_OK
