"""``dh2rt flash IMAGE --port DEV`` (or ``--interface I --channel C --contact DEV``): deliver a
signed image to a robot through a programming cable; every module switches to it at one
agreed cycle.

On a robot whose connectors are serial links, the programming cable is a serial port
(``--port``: a USB-serial adapter, a pty, any pyserial URL) wired to one module's free
connector; to the flasher it is connector 1 of a serial transport of its own. On a robot
whose modules share a CAN bus, the flasher is a node on that bus (``--interface`` and
``--channel``, as python-can names them, ``--bitrate``) and the cable is a connector-local
channel (``--contact``: the UART of a connector like the modules' own, or the HIL world's
emulation of one; ``--contact-pin``: its GPIO contact pin) held against one module's free
connector: the two negotiate a link id over it as two docking modules would (docs/link-layer.md),
and the image crosses the bus on that link, paced as a module's share of the bus. The cable
is a connector of the profile (``--cable-connector``, default ``back``: CONRO's male
connectors dock to a free front). The flasher (:class:`firmware.flash.cable.FlashCable`, the
rollout's :class:`dh2rt.flash.flasher.Flasher`) is ticked at the robot's cycle period
(``--cycle-ms``): it offers the image through the cable, the modules pass it on over their
own links, stage it, report back along their paths, and switch at the instant the flasher's
COMMIT names (docs/flashing.md, "Delivery over the links").

Progress goes to standard error (``--quiet``: none): the phase, the modules heard of,
staged, committed and failed, the image bytes the module at the cable acknowledged and the
rate (image bytes delivered per second; before any module staged, the bytes the module at
the cable acknowledged per second). The rollout report goes to standard output: one line per
module, named by its path from the cable (``front>front back>front``: the connector each hop
left through and the one it arrived at), its outcome (staged, committed, confirmed, current,
refused with the verdict and the reason, reverted, withheld, silent) and the version it runs;
``--json``: one JSON object.

Ctrl-C stops the flasher (the cable stops talking; modules the COMMIT already reached still
switch), prints the report so far and exits 130.

Exit codes: 0 every module committed (confirmed, with --confirm); 1 the rollout ran but a
module did not commit, it timed out, or no module answered through the cable; 2 bad input
(an image that cannot be read or is no signed image, a bad option, a port that cannot be
opened); 130 interrupted.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import signal
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dh2rt.cmdline import (
    EXIT_FAIL,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    add_bus_arguments,
    add_cycle_argument,
    bus_options,
    err,
)
from dh2rt.errors import SignedImageError, TransportError
from dh2rt.flash.flasher import Progress
from dh2rt.flash.pacing import Pacing, link_pacing
from dh2rt.flash.reports import COMMITTED, ModuleReport, describe_path
from dh2rt.profile import CONRO
from dh2rt.runtime import ms_to_s
from dh2rt.signed_image import SignedImage, Verdict, describe_key_id, examine, read_public_key
from dh2rt.signed_image import parse as parse_image
from dh2rt.transport.base import PortEnd, Transport
from dh2rt.transport.registry import open_transport
from dh2rt.transport.serial_link import SerialTransport
from dh2rt.wire.transfer import Outcome
from drivers.connector_channel import ConnectorChannels, ContactPin, UartGpioConnectorChannel
from firmware.flash.cable import BusCable, FlashCable, FlashResult, hello_codec

#: The cable is connector 1 of the flasher's own transport.
CABLE = 1
#: What the report says when nobody answered through the cable.
NOBODY = "no module answered through the cable"
#: How the Flasher's failure starts when a module stopped the commit, and the outcomes that do.
NOT_COMMITTED = "not committed: "
BLOCKING = frozenset({Outcome.REFUSED, Outcome.REVERTED, Outcome.WITHHELD})

EXIT_CODES = """\
exit codes:
  0    every module committed the image (confirmed it, with --confirm)
  1    the rollout ran but a module did not commit, it timed out, or no module answered
  2    bad input: an image that cannot be read, is unsigned or is no signed image, one
       that does not verify against --trust (tampered, wrong key), a bad option,
       a port, bus or contact channel that cannot be opened
  130  interrupted (Ctrl-C): the report so far is printed
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dh2rt flash",
        description="Deliver a signed program image to a robot through a programming cable (a serial\n"
        "port on one module's free connector); every module switches to it at one agreed cycle.",
        epilog=EXIT_CODES + "\nexample:\n  dh2rt flash cat2.simg --port /dev/ttyUSB0\n",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("image", type=Path, help="a signed image (dh2rt image PROGRAM --sign KEY --version N -o IMAGE)")
    add_cable_arguments(p)
    p.add_argument("--timeout", type=float, default=120.0, help="seconds before the flasher gives up (default: 120)")
    p.add_argument("--confirm", action="store_true", help="wait until every module confirmed the image (trial over)")
    p.add_argument(
        "--trust",
        type=Path,
        action="append",
        default=[],
        metavar="PUBKEY",
        help="a public key the robot trusts (repeatable): the image must verify against one before a byte is sent",
    )
    p.add_argument("--json", action="store_true", help="the rollout report as one JSON object")
    p.add_argument("--quiet", action="store_true", help="no progress on standard error")
    return p


def add_cable_arguments(p: argparse.ArgumentParser) -> None:
    """The cable's options (``dh2rt console`` takes the same): ``--port`` and ``--baudrate``
    on serial links, or a node on the bus and its ``--contact``; and ``--cycle-ms``."""
    p.add_argument("--port", help="the cable's serial port: a device path or a pyserial URL (serial links)")
    p.add_argument("--baudrate", type=int, default=115200, help="the cable's line speed (default: 115200)")
    bus = add_bus_arguments(p, group_title="on a robot whose modules share a CAN bus (instead of --port)")
    bus.add_argument("--contact", help="the cable's connector-local channel: a UART device (or a pty)")
    bus.add_argument("--contact-pin", help="the contact switch's GPIO value file (active low, as on the modules)")
    bus.add_argument(
        "--cable-connector",
        default="back",
        choices=CONRO.connectors,
        help="which connector of the profile the cable is (default: back, which docks to a free front)",
    )
    add_cycle_argument(p, "the robot's cycle period")


@dataclass(frozen=True, slots=True)
class Image:
    """The image to flash: its bytes, its fields, the SHA-256 of the program it holds."""

    path: Path
    data: bytes
    signed: SignedImage
    sha256: str


def main(argv: Sequence[str] | None = None) -> int:
    try:
        ns = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help (0) or a bad option (2): argparse has said why
        return int(exc.code) if isinstance(exc.code, int) else EXIT_USAGE
    try:
        check_cable_options(ns)
        image = read_image(ns.image, trust=[read_public_key(k) for k in ns.trust])
        pacing, segment = cable_pacing(ns, image)
    except (ValueError, OSError) as exc:  # SignedImageError and KeyFileError are ValueErrors; a key file unread
        err(str(exc))
        return EXIT_USAGE
    bus: BusCable | None = None
    try:
        if ns.port is not None:
            transport: Transport = open_cable(ns.port, ns.baudrate)
        else:
            transport, bus = open_bus_cable(ns)
    except (TransportError, OSError) as exc:
        err(str(exc))
        return EXIT_USAGE
    try:
        result, interrupted = _flash(ns, image, transport, pacing, segment, bus)
    except KeyboardInterrupt:  # a second Ctrl-C: no report
        err("interrupted")
        return EXIT_INTERRUPTED
    finally:
        if bus is not None:
            bus.close()  # the link released on the bus
        transport.close()
    try:
        if ns.json:
            print(json.dumps(to_json(image, result, interrupted=interrupted, confirm=ns.confirm)))
        else:
            print("\n".join(report_lines(image, result, interrupted=interrupted, confirm=ns.confirm)))
    except BrokenPipeError:  # `dh2rt flash ... | head`: the reader has what it wanted
        pass
    if interrupted:
        err(f"interrupted in phase {result.progress.phase.value}: the flasher stopped; modules the commit "
            "already reached still switch")  # fmt: skip
        return EXIT_INTERRUPTED
    return EXIT_OK if result.succeeded else EXIT_FAIL


def check_cable_options(ns: argparse.Namespace) -> None:
    """The cable and timing options `dh2rt flash` and `dh2rt console` share, checked (ValueError
    naming the option)."""
    if not (math.isfinite(ns.cycle_ms) and ns.cycle_ms > 0):
        raise ValueError(f"--cycle-ms {ns.cycle_ms:g}: must be a positive number of milliseconds")
    if math.isnan(ns.timeout) or ns.timeout <= 0:
        raise ValueError(f"--timeout {ns.timeout:g}: must be a positive number of seconds")
    if ns.baudrate <= 0:
        raise ValueError(f"--baudrate {ns.baudrate}: must be a positive number of bits per second")
    if (ns.port is None) == (ns.interface is None):
        raise ValueError("give the cable: --port DEV (serial links) or --interface I --channel C --contact DEV (a bus)")
    if ns.interface is not None:
        if not ns.channel:
            raise ValueError(f"--interface {ns.interface}: --channel is missing (python-can's channel of the bus)")
        if not ns.contact:
            raise ValueError(
                f"--interface {ns.interface}: --contact is missing (the cable's connector-local channel, over which "
                "it negotiates its link with the module it touches)"
            )
        if ns.bitrate <= 0:
            raise ValueError(f"--bitrate {ns.bitrate}: must be a positive number of bits per second")


def read_image(path: Path, trust: Sequence[bytes] = ()) -> Image:
    """The image at ``path``; ValueError (SignedImageError) naming the file and what is wrong.
    An unsigned image is refused here, before a byte is sent (every module would refuse it);
    with ``trust`` the signature must verify against one of those keys (tampered, wrong key)."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SignedImageError(f"{path}: cannot read the image ({exc.strerror or exc})") from None
    try:
        signed = parse_image(data)
        program = signed.program()  # the body must hold the program the header states
    except SignedImageError as exc:
        raise SignedImageError(f"{path}: {exc}") from None
    if signed.signature is None:
        raise SignedImageError(
            f"{path}: unsigned image (key id {describe_key_id(signed.key_id)}): modules take only signed ones; "
            "sign it: dh2rt image PROGRAM --sign KEY --version N -o IMAGE"
        )
    if trust:
        exam = examine(data, trust)
        if exam.verdict is not Verdict.OK:
            raise SignedImageError(f"{path}: {exam.verdict}: {exam.reason}")
    return Image(path, data, signed, hashlib.sha256(program).hexdigest())


def open_cable(port: str, baudrate: int) -> SerialTransport:
    """The cable's transport, ``port`` attached as its connector 1; TransportError naming
    the port when it cannot be opened."""
    transport = SerialTransport(hello_codec())
    try:
        transport.attach(CABLE, PortEnd(port, baudrate))
    except TransportError as exc:
        transport.close()
        why = exc.__cause__ or exc
        raise TransportError(f"--port {port}: cannot open the serial port ({why})") from None
    return transport


def open_bus_cable(ns: argparse.Namespace) -> tuple[Transport, BusCable]:
    """The flasher's node on the bus and its cable's connector-local channel; TransportError
    naming the option when either cannot be opened."""
    try:
        transport = open_transport("can", hello_codec(), **bus_options(ns))
    except TransportError as exc:
        what = f"--interface {ns.interface} --channel {ns.channel}"
        raise TransportError(f"{what}: cannot open the bus ({exc})") from None
    mate = CONRO.connectors.index(ns.cable_connector) + 1
    try:
        channels = open_contact(mate, ns.contact, ns.contact_pin)
    except (TransportError, OSError) as exc:
        transport.close()
        why = f"cannot open the cable's connector-local channel ({exc})"
        raise TransportError(f"--contact {ns.contact}: {why}") from None
    return transport, BusCable(channels, transport, mate, now=time.monotonic(), log=_note)


def open_contact(connector: int, device: str, pin: str | None) -> ConnectorChannels:
    """The cable's connector-local channel: a UART and its GPIO contact pin, or (no pin) a
    channel whose contact is signalled in band, as the HIL world's emulation does."""
    if pin is None:
        return ConnectorChannels.open_emulated({connector: device})
    return ConnectorChannels({connector: UartGpioConnectorChannel(device, ContactPin(pin))})


def _note(line: str) -> None:
    print(f"flash: {line}", file=sys.stderr, flush=True)


@contextmanager
def _ctrl_c_sets(stop: threading.Event) -> Iterator[None]:
    """Ctrl-C sets ``stop`` (the flasher ends at its next tick); a second one interrupts at
    once. Only the main thread can take signals: elsewhere Ctrl-C is not ours."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_sigint(_signum: int, _frame: object) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def cable_pacing(ns: argparse.Namespace, image: Image) -> tuple[Pacing, int]:
    """The rollout's pacing and segment size on the cable (a share of the line's bytes per
    cycle, as on the modules' links); ValueError naming the options when the largest transfer
    frame does not fit a cycle's share."""
    try:
        if ns.interface is not None:
            pacing, segment, _ = link_pacing("can", ms_to_s(ns.cycle_ms), 0, ns.bitrate)
        else:
            pacing, segment, _ = link_pacing("serial", ms_to_s(ns.cycle_ms), ns.baudrate, 0)
    except ValueError as exc:
        line = f"--bitrate {ns.bitrate}" if ns.interface is not None else f"--baudrate {ns.baudrate}"
        raise ValueError(f"{line} --cycle-ms {ns.cycle_ms:g}: {exc}") from None
    return pacing, segment


def _flash(
    ns: argparse.Namespace, image: Image, transport: Transport, pacing: Pacing, segment: int, bus: BusCable | None
) -> tuple[FlashResult, bool]:
    """Run the flasher until it is done, times out or Ctrl-C; (its result, interrupted)."""
    connector = CABLE if bus is None else CONRO.connectors.index(ns.cable_connector) + 1
    cable = FlashCable(
        image.data, transport, period=ms_to_s(ns.cycle_ms), pacing=pacing, segment_size=segment, connector=connector,
        confirm=ns.confirm, on_step=None if bus is None else bus.step,
    )  # fmt: skip
    show = None if ns.quiet else ProgressLines()
    if show is not None:
        print(
            f"flash: {image.path}: version {image.signed.version}, {len(image.data)} bytes, key id "
            f"{describe_key_id(image.signed.key_id)}; {_cable_text(ns)}, "
            f"cycle {ns.cycle_ms:g} ms, timeout {ns.timeout:g} s",
            file=sys.stderr,
            flush=True,
        )
    stop = threading.Event()
    with _ctrl_c_sets(stop):
        result = cable.run(timeout=ns.timeout, stop=stop, progress=show)
    if show is not None:
        show(result.progress)  # where it ended
    # FlashCable says timed_out for any run that ended before the Flasher was done
    return result, stop.is_set() and not cable.flasher.done


class ProgressLines:
    """Progress lines on standard error, one whenever something other than time changed."""

    def __init__(self) -> None:
        self._last: tuple[Any, ...] | None = None

    def __call__(self, p: Progress) -> None:
        key = (p.phase, p.modules, p.staged, p.committed, p.failed, p.bytes_acked)
        if key == self._last:
            return
        self._last = key
        print(
            f"flash: {p.phase.value}: {p.modules} module(s) heard of, {p.staged} staged, {p.committed} committed, "
            f"{p.failed} failed, {p.bytes_acked} bytes acknowledged, {p.rate:.0f} bytes/s, {p.elapsed:.1f} s",
            file=sys.stderr,
            flush=True,
        )


# ----------------------------------------------------------------------------- the report


def connector_name(index: int) -> str:
    """A connector's name in the robot's profile (CONRO), its number when it has none."""
    return CONRO.connector_name(index) if 0 <= index <= CONRO.connector_count else str(index)


def _failure(result: FlashResult, confirm: bool = False) -> str | None:
    """Why not every module committed (confirmed), modules named by their connectors' names."""
    if result.succeeded:
        return None
    if not result.modules:
        return NOBODY + (f" ({result.failure})" if result.failure else "")
    blocking = [m for m in result.modules if m.outcome in BLOCKING]
    if result.failure is not None and result.failure.startswith(NOT_COMMITTED) and blocking:
        # the Flasher names the first module that stopped the commit by connector numbers
        first = blocking[0]
        return f"{NOT_COMMITTED}{describe_path(first.path, connector_name)} {first.outcome.name.lower()} the image"
    if result.failure is not None:
        return result.failure
    # the Flasher settled with modules short of the goal (silent, staged, not yet confirmed)
    wanted = {Outcome.CONFIRMED, Outcome.CURRENT} if confirm else COMMITTED
    short = [m for m in result.modules if m.outcome not in wanted]
    named = ", ".join(f"{describe_path(m.path, connector_name)} {m.outcome.name.lower()}" for m in short[:3])
    more = f" and {len(short) - 3} more" if len(short) > 3 else ""
    return f"not {'confirmed' if confirm else 'committed'}: {named}{more}"


def report_lines(image: Image, result: FlashResult, *, interrupted: bool = False, confirm: bool = False) -> list[str]:
    """The rollout report: a headline, then one line per module by its path from the cable."""
    what = f"{image.path}: version {image.signed.version}, sha256 {image.sha256[:16]}"
    goal = "confirmed" if confirm else "committed"
    if result.succeeded:
        head = f"every module {goal} ({len(result.modules)} module(s))"
    elif interrupted:
        head = f"interrupted in phase {result.progress.phase.value}: NOT every module {goal}"
    else:
        head = f"NOT every module {goal} ({_failure(result, confirm)})"
    return [f"{what}: {head}", *(f"  {m.describe(connector_name)}" for m in result.modules)]


def module_json(m: ModuleReport) -> dict[str, Any]:
    return {
        "path": describe_path(m.path, connector_name),
        "outcome": m.outcome.name.lower(),
        "version": m.version,
        "verdict": m.verdict,
        "reason": m.reason,
    }


def to_json(image: Image, result: FlashResult, *, interrupted: bool = False, confirm: bool = False) -> dict[str, Any]:
    return {
        "image": str(image.path),
        "version": image.signed.version,
        "sha256": image.sha256,
        "succeeded": result.succeeded,
        "failure": "interrupted" if interrupted and not result.succeeded else _failure(result, confirm),
        "timed_out": result.timed_out and not interrupted,
        "interrupted": interrupted,
        "modules": [module_json(m) for m in result.modules],
    }


if __name__ == "__main__":
    sys.exit(main())


def _cable_text(ns: argparse.Namespace) -> str:
    if ns.interface is not None:
        return (f"cable: {ns.cable_connector} against a free connector (contact {ns.contact}), "
                f"bus {ns.interface} {ns.channel} at {ns.bitrate} bit/s")  # fmt: skip
    return f"cable {ns.port} at {ns.baudrate} baud"
