"""``dh2rt --transport vcan0 --module-count 8``: the hardware-in-the-loop launcher.

Starts a :class:`~hil.world.World` in this process and one module per topology module
(processes over ``socketcan``/``udp``/``serial``, threads over ``virtual``/``inproc``),
shows a live status table (twice a second on a TTY, progress lines otherwise), applies
``--event`` s at world cycles, writes ``--trace`` (merged from the modules, the JSON Lines
format of ``dh2rt run``) and prints a summary.

``udp`` (python-can ``udp_multicast``) only ever runs inside a private network namespace:
the launcher re-executes itself under ``unshare -rn`` with only loopback up and a multicast
route on it, and refuses when it cannot.

Exit codes: 0 ok; 1 the run went wrong (a module failed, a receptor faulted, an actuator
fault was still in force at the end, a link was lost on a clean link, a module missed its
cycle period in more than LATE_SHARE of its cycles, or the frames do not add up (see
World.frame_accounting): each is named on stderr); 3 the same, when some module started more
than LATE_SHARE of its cycles late, or links were lost while the machine held them as long as
the liveness bound (the link emulator's relay, or a module's start, after little work of the
module's own: :func:`machine_held`) (EXIT_TOO_SLOW: hil.pace reads it); 2 bad input or
transport unavailable; 130 interrupted. The whole log goes to a file the summary names.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from types import FrameType
from typing import IO, Any

from dh2rt.bundled import compile_bundled
from dh2rt.cmdline import (
    BITRATES,
    CAN_BITRATE,
    EXIT_FAIL,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    TRACE_SUFFIXES,
    VARS_HELP,
    add_bus_arguments,
    add_cycle_argument,
    add_run_options,
    int_in,
    output_path,
    variable_lines,
)
from dh2rt.compiler import compile_file
from dh2rt.errors import DH2Error, HilWorldError, OptionError, ProgramError
from dh2rt.events import Event, check_events, parse_event
from dh2rt.runtime import ms_to_s, s_to_ms
from dh2rt.signed_image import read_private_key
from dh2rt.topology import parse_spec
from dh2rt.transport.can_bus import FALLBACKS, VCAN_SETUP, socketcan_problem
from dh2rt.transport.registry import parse_spec as parse_transport_spec
from firmware.config import DEFAULT_STAND_IN, DEFAULTS, MAX_CYCLES, MAX_SILENCE_CYCLES, STAND_INS
from hil.capture_tap import CaptureSink, check_capture, open_capture_sink
from hil.console_cable import ConsoleCable, free_connector
from hil.flash_event import FlashEvent, FlashEvents, is_flash_event, parse_flash_event
from hil.hardware_map import HardwareMap, load_hardware_map
from hil.netns import NETNS_ENV, in_namespace, namespace_problem, only_loopback
from hil.supervisor import reap_exited_children
from hil.visuals import RunVisuals
from hil.world import NEGOTIATED, World
from sim.command import PYBULLET

ROOT = Path(__file__).resolve().parents[1]
#: What --capture writes (tools.capture_sink.SUFFIXES: this layer does not import tools/).
CAPTURE_SUFFIXES = (".pcapng", ".pcap", ".log", ".asc", ".blf", ".csv", ".trc")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dh2rt",
        description="Hardware-in-the-loop: run each module of a robot as its own process over a real "
        "link layer (SocketCAN, python-can udp_multicast in a private network namespace, emulated "
        "serial infrared links) or as threads over an in-process bus.",
        epilog="Without SocketCAN, try: dh2rt --transport serial --module-count 8 --cycles 300. "
        "--event CYCLE:flash:M:IMAGE plugs a programming cable into module M's "
        "first free connector at CYCLE and flashes the signed IMAGE into the running robot "
        "(docs/flashing.md); the run fails unless every module commits it.",
    )
    p.add_argument(
        "--program", type=Path, default=None, help="a .dh2 file (default: the caterpillar shipped with dh2rt)"
    )
    add_run_options(p, program_required=False)
    p.set_defaults(topology=None)
    p.add_argument(
        "--transport",
        default="serial",
        help="vcan0, can0 (any SocketCAN name), can (any python-can interface: see --interface), udp, serial, "
        "virtual, inproc (default: serial)",
    )
    can = add_bus_arguments(p, group_title="--transport can: any python-can bus")
    can.add_argument("--fd", action="store_true", help="CAN FD frames (up to 64 data bytes)")
    can.add_argument("--data-bitrate", type=int_in(*BITRATES), help="CAN FD's data phase bitrate")
    p.add_argument(
        "--hardware-map",
        type=Path,
        metavar="FILE",
        help="real ports per module (TOML): servo port and ids, a UART per connector, a CAN channel; "
        "see docs/firmware.md",
    )
    p.add_argument(
        "--module-count",
        type=int,
        default=8,
        help=f"modules of the default snake:N (default: 8); at most {MODULES_PER_CORE} per core of this machine, "
        f"and fewer when its memory or open-file limit cannot hold that many ({max_modules()[0]} here)",
    )
    add_cycle_argument(p, "cycle period in ms")
    p.add_argument(
        "--silence-cycles",
        type=int_in(1, MAX_SILENCE_CYCLES),
        default=DEFAULTS.silence_cycles,
        help=f"liveness bound in cycles (default: {DEFAULTS.silence_cycles})",
    )
    p.add_argument("--frame-loss", type=float, default=0.0, help="serial: frame loss probability per link")
    p.add_argument("--bit-error", type=float, default=0.0, help="serial: bit error probability")
    p.add_argument(
        "--stand-in",
        choices=STAND_INS,
        default=None,
        help="the modules' body: pybullet (default; each module drives emulated Dynamixel servos whose joints "
        "are PyBullet joints, the full firmware path), recording (each module records its angles; the default "
        "with --hardware-map, for modules it names no servos for), none",
    )
    view = p.add_argument_group("with --stand-in pybullet, as dh2rt run --sim pybullet")
    view.add_argument(
        "--motions-in-modules",
        action="store_true",
        help="each module carries out its program's reach_dock itself (firmware.motion.asking: the chain's "
        "angles and targets as motion frames on its links); the world sends no joint target for it, only "
        "physics, infrared, the tracker and the latch (reach_and_dock stays the world's)",
    )
    view.add_argument(
        "--latch-emulator",
        action="store_true",
        help="each module gets an emulated latch servo (id 3, beside its joints on its emulated bus) on its "
        "front face and a [latch] in its module.toml: it closes its own latch, whose horn passes the pins only "
        "if physics has that face aligned with a free male face; the world docks on the horn closing and "
        "undocks on it opening (needs --stand-in pybullet)",
    )
    view.add_argument(
        "--tracker-udp",
        action="store_true",
        help="each module hears the overhead tracker itself: a [tracker] in its module.toml (a free port on "
        "127.0.0.1 each), and the world sends the stand-in tracker's report there as dh2rt tracker's UDP "
        "datagrams instead of in its Floor command (needs --stand-in pybullet and --motions-in-modules)",
    )
    view.add_argument(
        "--sensor-every",
        type=int_in(1, MAX_CYCLES),
        default=1,
        metavar="N",
        help="push each module its IMU, infrared and contact readings from physics every N world cycles "
        "(default: 1; only the sensors the program declares are measured)",
    )
    PYBULLET.add_arguments(view)  # --record, --camera, --record-speed, --plot, --gui
    p.add_argument(
        "--capture",
        type=Path,
        metavar="FILE",
        help="record every frame on the robot's links: .pcapng (CAN and serial, the program inside; "
        "open it with dh2rt dump or Wireshark), or on a bus .pcap, .log (candump -L), .blf, .asc",
    )
    p.add_argument(
        "--force", action="store_true", help="write --capture, --log or --trace over a capture that is there"
    )
    p.add_argument(
        "--key",
        type=Path,
        metavar="KEY",
        help="the robot's signing key (dh2rt keys new): the modules' program is signed with it and their "
        "trust stores hold it, so that --event CYCLE:flash:M:IMAGE images signed with it are accepted "
        "(default: a key of this run's)",
    )
    p.add_argument(
        "--console",
        type=Path,
        metavar="FILE",
        help="plug a cable for dh2rt console into the first module's free connector (on a bus, through a "
        "serial-to-bus adapter the launcher plays) and write its port to FILE once the robot runs: "
        "dh2rt console --port $(cat FILE) --key KEY ...",
    )
    p.add_argument("--json", action="store_true", help="print the summary as JSON (only that, on stdout)")
    p.add_argument("--vars", action="store_true", help=VARS_HELP + "; on a terminal, the live table too")
    p.add_argument(
        "--log",
        type=Path,
        metavar="FILE",
        help="write the whole log here (default: dh2rt-hil-PID.log in the temporary folder)",
    )
    return p


def _err(message: str) -> None:
    print(f"dh2rt: {message}", file=sys.stderr)


def _reexec_in_namespace(argv: list[str]) -> int:
    """Run this launcher again inside ``unshare -rn`` (loopback only); its exit code."""
    problem = namespace_problem()
    if problem is not None:
        _err(
            "--transport udp runs python-can udp_multicast only inside a private network namespace, "
            f"and {problem}; use --transport serial or virtual"
        )
        return EXIT_USAGE
    env = dict(os.environ)
    env[NETNS_ENV] = "1"
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    cmd = in_namespace([sys.executable, "-m", "hil.launcher", *argv])
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # the child gets Ctrl-C itself
    try:
        return subprocess.run(cmd, env=env, check=False).returncode
    finally:
        signal.signal(signal.SIGINT, previous)


def transport_problem(spec: str) -> str | None:
    """Why ``spec`` cannot run here (SocketCAN missing), or None."""
    kind, options = parse_transport_spec(spec)
    if kind != "socketcan":
        return None
    channel = str(options.get("channel", "vcan0"))
    problem = socketcan_problem(channel)
    if problem is None:
        return None
    return (
        f"--transport {spec}: SocketCAN interface {channel!r} is unavailable: {problem}.\n"
        f"  To create a virtual CAN interface (Linux, root): {VCAN_SETUP}\n"
        f"  Transports that work without SocketCAN: {FALLBACKS}.\n"
        f"  For example: dh2rt --transport serial --module-count 8 --cycles 300"
    )


def main(argv: list[str] | None = None) -> int:
    """The launcher; Ctrl-C at any moment (even while starting) ends it with exit 130."""
    sigints: list[int] = []

    def on_sigint(signum: int, frame: FrameType | None) -> None:
        sigints.append(signum)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, on_sigint) if _in_main_thread() else None
    try:
        try:
            return _main(argv)
        finally:
            reap_exited_children()
    except KeyboardInterrupt:
        _err("interrupted while starting")
        return EXIT_INTERRUPTED
    except ImportError:
        # numpy (loaded by pybullet) turns a Ctrl-C during its import into a bare ImportError
        if not sigints:
            raise
        _err("interrupted while starting")
        return EXIT_INTERRUPTED
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _main(argv: list[str] | None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    try:
        ns = parser.parse_args(args)
    except SystemExit as exc:  # argparse: --help (0) or a bad option (2)
        return int(exc.code) if isinstance(exc.code, int) else EXIT_USAGE
    try:
        if ns.module_count < 1:
            raise OptionError(f"--module-count {ns.module_count}: must be 1 or more")
        check_module_count(ns.module_count, "--module-count")
        if ns.cycles < 0:
            raise OptionError(f"--cycles {ns.cycles}: must be 0 or more")
        # output files are checked before anything runs, not found unwritable after the run
        if ns.trace is not None:
            ns.trace = output_path(ns.trace, "--trace", TRACE_SUFFIXES, force=ns.force)
        if ns.log is not None:  # a name ending in .log reads as a candump capture: --force writes over it
            ns.log = output_path(ns.log, "--log", force=ns.force)
        program = compile_file(str(ns.program)) if ns.program is not None else compile_bundled("caterpillar.dh2")
        spec = ns.topology or f"snake:{ns.module_count}"
        topology = parse_spec(spec, program.profile)
        check_module_count(topology.size, f"--topology {ns.topology}" if ns.topology else "--module-count")
        if ns.topology and any(a.startswith("--module-count") for a in args) and topology.size != ns.module_count:
            raise OptionError(
                f"--topology {ns.topology} has {topology.size} modules but --module-count is {ns.module_count}"
            )
        events = [parse_event(e, topology, program.vocabulary) for e in ns.event if not is_flash_event(e)]
        ns.flash_events = [parse_flash_event(e, topology) for e in ns.event if is_flash_event(e)]
        ns.signer = read_private_key(ns.key) if ns.key is not None else None
        check_flash_events(ns.flash_events, ns.transport, ns.cycles)
        if ns.console is not None:
            ns.console = output_path(ns.console, "--console")
            if parse_transport_spec(ns.transport)[0] not in ("serial", *NEGOTIATED):
                raise OptionError("--console: the console's cable needs links it can join: --transport serial, "
                                  "or a bus (can, udp, virtual)")  # fmt: skip
            free_connector(topology, 0)
        if ns.cycles is not None:
            check_events(events, topology, ns.cycles, sensors=program.sensor_names)
        if ns.sensor_every < 1:
            raise OptionError(f"--sensor-every {ns.sensor_every}: must be 1 or more")
        kind, _ = parse_transport_spec(ns.transport)
        for option, value in (("--frame-loss", ns.frame_loss), ("--bit-error", ns.bit_error)):
            if not 0.0 <= value <= 1.0:
                raise OptionError(f"{option} {value}: a probability, from 0 to 1")
            if value and kind != "serial":
                raise OptionError(
                    f"{option} {value}: only the serial link emulator can lose or corrupt frames; "
                    f"--transport {ns.transport} carries them as its medium does"
                )
        hardware = load_hardware_map(ns.hardware_map, topology) if ns.hardware_map is not None else None
        ns.stand_in = stand_in_for(ns.stand_in, hardware)
        ns.bus_options = bus_options(ns, kind, hardware, topology.size)
        check_hardware(hardware, kind, events)
        check_views(ns)
        if ns.capture is not None:
            ns.capture = output_path(ns.capture, "--capture", CAPTURE_SUFFIXES, force=ns.force)
            check_capture(ns.capture, kind, serial_ok=ns.capture.suffix.lower() == ".pcapng")
            if hardware is not None and any(h.can_channel for h in hardware.modules.values()):
                raise OptionError(
                    "--capture: each module has a CAN channel of its own; capture on the bus itself "
                    "with dh2rt capture -i INTERFACE -c CHANNEL"
                )
    except ProgramError as exc:
        print(exc.render(), file=sys.stderr)
        return EXIT_USAGE
    except (DH2Error, OSError, ValueError) as exc:
        _err(str(exc))
        return EXIT_USAGE
    problem = transport_problem(ns.transport) or bus_problem(ns.bus_options, hardware)
    if problem is not None:
        _err(problem)
        return EXIT_USAGE
    if kind == "udp" and os.environ.get(NETNS_ENV) != "1":
        return _reexec_in_namespace(args)
    if kind == "udp" and not only_loopback():
        _err("--transport udp: refusing to send multicast outside a loopback-only network namespace")
        return EXIT_USAGE
    return _run(ns, program, topology, events, hardware)


#: The most modules the launcher starts per core of this machine: each is a process (or a
#: thread) that must keep its cycle period, and the world serves them all from one process.
MODULES_PER_CORE = 32
#: What one module may take at most of the machine: open files (its pipes, ports, pty pairs
#: and bus sockets, on both ends) and memory (MB resident: a module process is about 30 MB).
FILES_PER_MODULE = 16
MB_PER_MODULE = 64


def max_modules() -> tuple[int, str]:
    """The most modules this machine can run, and what bounds it: MODULES_PER_CORE per core,
    the open-file limit, the memory available."""
    bounds = [(MODULES_PER_CORE * (os.cpu_count() or 1), f"{MODULES_PER_CORE} per core")]
    try:
        import resource

        files = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
        if files != resource.RLIM_INFINITY:
            bounds.append((max(1, (files - 64) // FILES_PER_MODULE), f"{FILES_PER_MODULE} open files each (ulimit -n)"))
    except (ImportError, OSError, ValueError):  # no resource module (Windows): not bounded by it
        pass
    try:
        free = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // (1 << 20)
        bounds.append((max(1, free // MB_PER_MODULE), f"{MB_PER_MODULE} MB of free memory each"))
    except (ValueError, OSError, AttributeError):  # not a POSIX sysconf: not bounded by it
        pass
    return min(bounds)


def check_module_count(count: int, option: str) -> None:
    """Refuse (exit 2) more modules than this machine can run (:func:`max_modules`)."""
    most, why = max_modules()
    if count > most:
        raise OptionError(f"{option}: {count} modules; this machine can run at most {most} ({why})")


def stand_in_for(chosen: str | None, hardware: HardwareMap | None) -> str:
    """The modules' body: as chosen, else PyBullet; with a hardware map, recording (the
    modules it names servos for drive those, and no PyBullet is started)."""
    return chosen or ("recording" if hardware is not None else DEFAULT_STAND_IN)


def bus_options(ns: argparse.Namespace, kind: str, hardware: HardwareMap | None, modules: int) -> dict[str, Any]:
    """python-can options of ``--transport can`` (and refuse them with any other)."""
    given = {
        "--interface": ns.interface, "--channel": ns.channel,
        "--bitrate": None if ns.bitrate == CAN_BITRATE else ns.bitrate,
        "--fd": ns.fd or None, "--data-bitrate": ns.data_bitrate,
    }  # fmt: skip
    if kind != "can":
        used = [option for option, value in given.items() if value is not None]
        if used:
            raise OptionError(f"{used[0]}: only with --transport can (any python-can interface)")
        return {}
    if ns.interface is None:
        raise OptionError("--transport can needs --interface (socketcan, slcan, pcan, kvaser, gs_usb, ...)")
    per_module = hardware is not None and all(hardware.get(m).can_channel for m in range(modules))
    if ns.channel is None and not per_module:
        raise OptionError("--transport can needs --channel, or a can_channel per module in --hardware-map")
    if ns.data_bitrate is not None and not ns.fd:
        raise OptionError("--data-bitrate is CAN FD's data phase: add --fd")
    options: dict[str, Any] = {"interface": ns.interface, "fd": ns.fd}
    for key, value in (("channel", ns.channel), ("bitrate", ns.bitrate), ("data_bitrate", ns.data_bitrate)):
        if value is not None:
            options[key] = value
    return options


def bus_problem(options: dict[str, Any], hardware: HardwareMap | None) -> str | None:
    """Why a ``--transport can`` bus cannot be opened here, found before any module starts."""
    if not options:
        return None
    import can

    channels = {options.get("channel")}
    if hardware is not None:
        channels |= {h.can_channel for h in hardware.modules.values() if h.can_channel}
    channels.discard(None)
    rest = {k: v for k, v in options.items() if k != "channel"}
    for channel in sorted(str(c) for c in channels):
        if options["interface"] == "socketcan":
            problem = socketcan_problem(channel)
            if problem:
                return f"--interface socketcan --channel {channel}: {problem}. {VCAN_SETUP}"
            continue
        if channel.startswith("/"):  # a serial adapter (slcan, ...): opening it is the module's job
            if not os.path.exists(channel):
                return (
                    f"--interface {options['interface']} --channel {channel}: no such device; "
                    f"transports that need no hardware: {FALLBACKS}"
                )
            continue
        try:
            can.Bus(channel=channel, **rest).shutdown()
        except Exception as exc:  # python-can raises what each interface raises: name the bus
            return (
                f"--interface {options['interface']} --channel {channel}: cannot open it ({type(exc).__name__}: "
                f"{exc}); transports that need no hardware: {FALLBACKS}"
            )
    return None


def check_hardware(hardware: HardwareMap | None, kind: str, events: list[Event]) -> None:
    if hardware is None:
        return
    if hardware.has_connectors and kind != "serial":
        raise OptionError(f"--hardware-map {hardware.path}: maps UARTs to connectors; that needs --transport serial")
    if any(h.can_channel for h in hardware.modules.values()) and kind != "can":
        raise OptionError(f"--hardware-map {hardware.path}: names CAN channels; that needs --transport can")
    moving = [ev.text or ev.kind for ev in events if ev.kind in ("cut", "dock")]
    if hardware.has_connectors and moving:
        raise OptionError(f"--event {moving[0]}: real UARTs cannot be undocked by the launcher; undock the modules")


def check_views(ns: argparse.Namespace) -> None:
    wanted = [o for o, v in (("--record", ns.record), ("--plot", ns.plot), ("--gui", ns.gui or None)) if v is not None]
    if ns.motions_in_modules and ns.stand_in != "pybullet":
        raise OptionError("--motions-in-modules: the modules move bodies in physics; it needs --stand-in pybullet")
    if ns.latch_emulator and ns.stand_in != "pybullet":
        raise OptionError("--latch-emulator: the latch servos are emulated in physics; it needs --stand-in pybullet")
    if ns.tracker_udp and not (ns.stand_in == "pybullet" and ns.motions_in_modules):
        raise OptionError(
            "--tracker-udp: the modules hear the stand-in's tracker while they run their motions; "
            "it needs --stand-in pybullet and --motions-in-modules"
        )
    if wanted and ns.stand_in != "pybullet":
        raise OptionError(f"{wanted[0]}: shows the PyBullet stand-in; it needs --stand-in pybullet")
    PYBULLET.check(ns)
    if ns.gui and not os.environ.get("DISPLAY"):
        raise OptionError("--gui opens PyBullet's window and needs a display (DISPLAY is not set)")


def _run(ns: argparse.Namespace, program: Any, topology: Any, events: list[Event], hardware: HardwareMap | None) -> int:
    out = sys.stdout
    # with --json, standard output holds the JSON object only: progress goes to stderr
    progress = sys.stderr if ns.json else out
    tty = progress.isatty()
    log_path = ns.log or Path(tempfile.gettempdir()) / f"dh2rt-hil-{os.getpid()}.log"
    late_warned = False
    capture: CaptureSink | None = None
    try:
        if ns.capture is not None:
            capture = open_capture_sink(ns.capture, [program.image])
    except (DH2Error, OSError) as exc:
        _err(f"cannot write the capture: {exc}")
        return EXIT_USAGE
    try:
        world = World(
            program,
            topology,
            ns.transport,
            seed=ns.seed,
            cycle_period=ms_to_s(ns.cycle_ms),
            cycles=ns.cycles,
            trace=ns.trace is not None,
            silence_cycles=ns.silence_cycles,
            frame_loss=ns.frame_loss,
            bit_error=ns.bit_error,
            emulator_seed=ns.seed,
            stand_in=ns.stand_in,
            capture=capture,
            hardware=hardware,
            bus_options=ns.bus_options,
            gui=ns.gui,
            signer=ns.signer,
            sensor_every=ns.sensor_every,
            modules_move=ns.motions_in_modules,
            latch_emulator=ns.latch_emulator,
            tracker_udp=ns.tracker_udp,
        )
    except (DH2Error, OSError, ValueError) as exc:
        if capture is not None:
            capture.close()
        _err(f"cannot start the world: {exc}")
        return EXIT_USAGE
    interrupted = False
    failed = False
    flashes = FlashEvents(ns.flash_events, world, progress)
    console = ConsoleCable(world, ns.console) if ns.console is not None else None
    started = time.monotonic()
    views = (
        RunVisuals(world.physics, ns.record, ns.plot, camera=ns.camera, speed=ns.record_speed)
        if world.physics is not None
        else None
    )
    try:
        world.start()
        applied: set[int] = set()
        last_draw = 0.0
        while not world.done():
            world.run_events(events, applied)
            flashes.step()
            if console is not None:
                console.step()
            world.tick()
            if views is not None:
                views.after_tick(world.cycle)
            now = time.monotonic()
            if now - last_draw >= (0.5 if tty else 2.0):
                last_draw = now
                _draw(world, progress, tty, ns.vars)
                if not late_warned:
                    late_warned = _warn_if_late(world)
            time.sleep(world.idle(0.02))
        world.tick()
    except KeyboardInterrupt:
        interrupted = True
    except (HilWorldError, DH2Error, OSError) as exc:
        _err(str(exc))
        failed = True
    finally:
        flashes.close()
        if console is not None:
            console.pull_out()
        try:
            world.stop()
        except KeyboardInterrupt:
            world.stop()
        if console is not None:
            console.close()
        if capture is not None:
            capture.close()
    elapsed = time.monotonic() - started
    if capture is not None:
        progress.write(f"capture: {capture.count} frames in {ns.capture}\n")
    if ns.trace is not None:
        _write_trace(ns.trace, world.sorted_records())
    wrong = problems(world, events, clean_links=ns.frame_loss == 0 and ns.bit_error == 0)
    if failed:
        wrong.insert(0, "the world failed (see above)")
    wrong += [f"{e.text}: not every module committed ({flashes.failure(e)})"
              for e in flashes.events if not flashes.event_succeeded(e)]  # fmt: skip
    _write_log(log_path, world, wrong)
    _summary(world, elapsed, out, ns.json, wrong, log_path, flashes, show_vars=ns.vars)
    if views is not None:
        views.finish(f"{program.name} on {topology.spec} over {ns.transport}", progress)
    if interrupted:
        _err(f"interrupted at world cycle {world.cycle}")
        return EXIT_INTERRUPTED
    if wrong:
        for line in wrong:
            _err(line)
        _err(f"the run went wrong in {len(wrong)} way(s); the whole log is in {log_path}")
        slow = any(_late_share(v.status) > LATE_SHARE for v in world.views) or links_held_by_machine(world)
        return EXIT_TOO_SLOW if slow else EXIT_FAIL
    return EXIT_OK


#: Share of a module's cycles that may start late before the run counts as gone wrong.
LATE_SHARE = 0.10
#: The exit code of a run that went wrong with modules that could not keep the period.
EXIT_TOO_SLOW = 3


def machine_held(world: World) -> str | None:
    """What held the links as long as the liveness bound, if it was the machine and not a
    module's own work (tests/hil/holds.py judges the same way): the link emulator's relay
    thread (every serial link waits while it is held: the world process's, shared with
    physics), or a module started that late after little work of its own. None: nothing
    did, or a module's own work came near the bound (then a lost link is dh2rt's)."""
    period_ms = s_to_ms(world.cycle_period)
    bound_ms = world.silence_cycles * period_ms
    near = bound_ms - period_ms
    rows = [v.status for v in world.views]
    if any(float((r.get("work_ms") or {}).get("max", 0.0)) >= bound_ms / 2 for r in rows):
        return None
    relay_ms = _relay_held_running_ms(world)
    if relay_ms >= near:
        return f"this machine held the link emulator's relay {relay_ms:.0f} ms (the liveness bound is {bound_ms:g} ms)"
    late = {v.name: float((v.status.get("lateness_ms") or {}).get("max", 0.0)) for v in world.views}
    name, worst = max(late.items(), key=lambda kv: kv[1], default=("", 0.0))
    if worst >= near:
        return f"this machine started {name} {worst:.0f} ms late (the liveness bound is {bound_ms:g} ms)"
    return None


def _relay_held_running_ms(world: World) -> float:
    """The longest the machine held the link emulator's relay once the modules cycled (ms):
    start-up (module processes starting, the handshake) holds it up to ~80 ms on an idle
    machine, which no liveness bound runs over yet."""
    if world.emulator is None or world.go_at is None:
        return 0.0
    go = world.go_at
    return max((held * 1000 for ended, held in world.emulator.holds() if ended - held >= go), default=0.0)


def links_held_by_machine(world: World) -> bool:
    """Whether links were lost while the machine held them (:func:`machine_held`)."""
    lost = any(int(v.status.get("counters", {}).get("links_lost", 0)) for v in world.views)
    return lost and machine_held(world) is not None


def _late_share(status: Mapping[str, Any]) -> float:
    """Share of its cycles a module (its status) started late (problems() names each)."""
    c = status.get("counters", {})
    return int(c.get("late_cycles", 0)) / max(1, int(c.get("cycles", 0)))


def problems(world: World, events: list[Event], *, clean_links: bool) -> list[str]:
    """What went wrong in a finished run, one line per module and kind (empty: nothing)."""
    changes_links = (
        any(ev.kind in ("cut", "dock", "kill", "restart") for ev in events)
        or any(effect.kind in ("reach_and_dock", "reach_dock", "release") for _m, effect in world.effects)
        or world.cables_plugged > 0
    )
    out: list[str] = []
    held = machine_held(world)
    for v in world.views:
        s = v.status
        c = s.get("counters", {})
        if v.failed:
            out.append(f"module {v.name} failed: {'; '.join(v.errors) or 'see the log'}")
        if int(c.get("engine_faults", 0)):
            out.append(f"module {v.name}: {c['engine_faults']} receptor fault(s), the last at {s.get('last_fault')}")
        if s.get("actuator_fault"):
            out.append(f"module {v.name}: actuator fault at the end: {s['actuator_fault']}")
        if clean_links and not changes_links and int(c.get("links_lost", 0)):
            lost = f"module {v.name} lost {c['links_lost']} link(s) on clean links"
            if held is None:
                out.append(f"{lost} (no loss injected, no surgery)")
            else:
                out.append(f"{lost} while {held}: {_suggest_period(world)}")
        cycles = max(1, int(c.get("cycles", 0)))
        late = int(c.get("late_cycles", 0))
        if late > LATE_SHARE * cycles:
            out.append(
                f"module {v.name} started {late * 100 // cycles}% of its cycles late (more than "
                f"{LATE_SHARE:.0%}): {_suggest_period(world)}"
            )
    for module, ready_at in world.late_restarts:
        out.append(
            f"module {world.views[module].name} was restarted but its new life was ready only at world cycle "
            f"{ready_at}, after the run's last cycle ({world.cycles}): it ran no cycles (give the run more "
            "cycles after the restart)"
        )
    frames = world.frame_accounting()
    # frames always add up (docs/hil.md, "Counting frames"): in every run with a witness of
    # the frames sent to nobody (the link emulator, the inproc bus, the CAN bus's witness);
    # over real serial ports or CAN adapters the world cannot join, in runs whose links stay
    if frames["unaccounted"] and (world.frames_witnessed or not changes_links):
        where = world.unaccounted_where()
        out.append(
            f"{frames['unaccounted']} frame(s) unaccounted for: {frame_identity(frames)}"
            + (f"; where: {'; '.join(where)}" if where else "")
        )
    return out


def frame_identity(f: dict[str, int]) -> str:
    """The run's frames as the identity they add up to (docs/hil.md, "Counting frames")."""
    left = f"{f['sent']} sent" + (f" + {f['split']} split" if f["split"] else "")
    right = [f"{f['received']} received", f"{f['corrupted']} corrupted", f"{f['dropped']} dropped"]
    for key, what in (
        ("unhandled", "unhandled"),
        ("read_by_killed", "read by killed modules"),
        ("lost_on_link", "lost on the links"),
        ("unread", "unread"),
        ("merged", "merged"),
    ):
        if f[key] or key == "lost_on_link":
            right.append(f"{f[key]} {what}")
    if f["unaccounted"]:
        right.append(f"{f['unaccounted']} unaccounted")
    return f"{left} = {' + '.join(right)}"


#: What the summary says of frames a run with no witness cannot account for: over real serial
#: ports (--hardware-map) or CAN adapters the world cannot join (slcan, an adapter per module).
NO_WITNESS = (
    "real ports and adapters of the modules' own have no witness of frames sent to a link nobody held, nor of "
    "what a killed module counted after its last report"
)


#: How a run's problems begin to say that modules could not keep the period.
TOO_SLOW = "this machine cannot keep"


def _suggest_period(world: World) -> str:
    ms = s_to_ms(world.cycle_period)
    return f"{TOO_SLOW} {ms:g} ms cycles with {world.topology.size} modules; try --cycle-ms {ms * 2:g}"


def _warn_if_late(world: World) -> bool:
    """Say during the run when modules cannot keep their period; True once said."""
    worst = 0.0
    for r in world.rows():
        c = r["counters"]
        cycles = int(c.get("cycles", 0))
        if cycles >= 50:
            worst = max(worst, int(c.get("late_cycles", 0)) / cycles)
    if worst <= LATE_SHARE:
        return False
    _err(f"warning: {worst:.0%} of some module's cycles start late; {_suggest_period(world)}")
    return True


def _write_log(path: Path, world: World, wrong: list[str]) -> None:
    try:
        with path.open("w", encoding="utf-8") as f:
            for line in world.log:
                f.write(line + "\n")
            for v in world.views:
                for e in v.errors:
                    f.write(f"module {v.name}: {e}\n")
            for line in wrong:
                f.write(f"went wrong: {line}\n")
    except OSError as exc:
        _err(f"cannot write the log to {path}: {exc.strerror or exc}")


def _write_trace(path: Path, records: list[dict[str, Any]]) -> None:
    with path.open("w", encoding="utf-8") as f:
        for rec in records:
            f.write(json.dumps(rec, separators=(",", ":")))
            f.write("\n")


def _table(world: World, show_vars: bool = False) -> list[str]:
    lines = [
        f"{'module':<8} {'state':<8} {'cycle':>6} {'type':<10} {'T':>3} {'DOF1':>6} {'DOF2':>6} "
        f"{'frames/s':>9} {'errors':>6} {'version':>7} {'sha256':<16}"
    ]
    rows = world.rows()
    for r in rows:
        alias = "" if r["T"] is None else str(r["T"])
        lines.append(
            f"{r['name']:<8} {r['state']:<8} {r['cycle']:>6} {r['type']:<10} {alias:>3} {r['DOF1']:>6.0f} "
            f"{r['DOF2']:>6.0f} {r['frames_per_s']:>9.0f} {r['errors']:>6} {_or_dash(r.get('version')):>7} "
            f"{_or_dash(r.get('sha256'))[:16]:<16}"
        )
    return lines + (variable_lines(rows) if show_vars else [])


def _or_dash(value: object) -> str:
    return "-" if value is None else str(value)


def check_flash_events(events: list[FlashEvent], transport: str, cycles: int | None) -> None:
    """Flash events need cables (the serial link emulator) and a cycle the run reaches."""
    for ev in events:
        if parse_transport_spec(transport)[0] not in ("serial", *NEGOTIATED):
            raise OptionError(
                f"--event {ev.text}: a programming cable needs links it can join: --transport serial, or a bus "
                "(can, udp, virtual)"
            )
        if cycles is not None and ev.cycle >= cycles:
            raise OptionError(f"--event {ev.text}: cycle {ev.cycle} never happens: the run's last is {cycles - 1}")


def _draw(world: World, out: IO[str], tty: bool, show_vars: bool = False) -> None:
    if tty:
        out.write("\x1b[H\x1b[2J")
        out.write(
            f"dh2rt hil: {world.program.name} on {world.topology.spec} over {world.spec}, world cycle {world.cycle}\n"
        )
        out.write("\n".join(_table(world, show_vars)) + "\n")
    else:
        cycles = [r["cycle"] for r in world.rows()]
        out.write(f"world cycle {world.cycle}: module cycles {min(cycles)}..{max(cycles)}\n")
    out.flush()


def _reaches(world: World) -> dict[str, Any] | None:
    """The docking motions of a run on the PyBullet stand-in (hil.reach_loop): each latch and
    each motion that gave up, with where the faces were then; None without the stand-in."""
    r = world.reaches
    if r is None:
        return None
    return {
        "contacts": [c.as_dict() for c in r.contacts],
        "failed": [c.as_dict() for c in r.failed],
        "outcomes": [{**asdict(o), "plan_s": round(o.plan_s, 3)} for o in r.docking.outcomes],
        "arrivals": [asdict(a) for a in r.docking.arrivals],
        "latch_answers": world.latch_answers,
        "holds_sent": world.holds_sent,
        # --tracker-udp: the datagrams the world sent to the modules' ports, and sends refused
        "tracker_udp": None if world.tracker is None else {"sent": world.tracker.sent, "failed": world.tracker.failed},
        # --latch-emulator: each module's latch servo, the closes refused (a jam) and its overloads
        "latch_servos": {
            world.topology.names[m]: {"refused": horn.refused, "overloads": horn.overloads}
            for m, horn in r.physics.latches.items()
        },
    }


def _summary(
    world: World, elapsed: float, out: IO[str], as_json: bool, wrong: list[str], log_path: Path,
    flashes: FlashEvents | None = None, *, show_vars: bool = False,
) -> None:  # fmt: skip
    rows = world.rows()
    if as_json:
        summary = {
            "problems": wrong,
            "log_file": str(log_path),
            "frames": world.frame_accounting(),
            "transport": world.spec,
            "stand_in": world.stand_in,
            "displacement_m": world.physics.displacement() if world.physics is not None else None,
            "seconds": elapsed,
            "cycle_period": world.cycle_period,
            # the longest the machine held the link emulator's relay (serial links; every byte
            # on the links waited that long): a lost link beside a long hold is the bench's
            "relay_held_ms": None if world.emulator is None else round(world.emulator.held_s * 1000, 1),
            # the same once the modules cycled (start-up holds it longest, before any liveness)
            "relay_held_running_ms": None if world.emulator is None else round(_relay_held_running_ms(world), 1),
            "modules": rows,
            "events": [{"text": text, "t": t} for text, t in world.event_times],
            "sensor_push": _push_cost(world),
            "log": world.log[-200:],
            "rollouts": [] if flashes is None else flashes.report(),
            "reaches": _reaches(world),
        }
        json.dump(summary, out)
        out.write("\n")
        return
    out.write(
        f"{world.program.name} on {world.topology.spec} over {world.spec}: {world.topology.size} modules, "
        f"{elapsed:.2f} s, cycle {s_to_ms(world.cycle_period):.0f} ms, seed {world.seed}\n"
    )
    out.write("\n".join(_table(world, show_vars)) + "\n")
    totals: dict[str, int] = {}
    for r in rows:
        for k in (
            "frames_sent",
            "frames_received",
            "frames_dropped",
            "frames_corrupted",
            "refused",
            "links_lost",
            "beacons_missed",
            "late_cycles",
        ):
            totals[k] = totals.get(k, 0) + int(r["counters"].get(k, 0))
    out.write("totals: " + ", ".join(f"{k} {v}" for k, v in totals.items()) + "\n")
    f = world.frame_accounting()
    tail = " (every frame accounted for)"
    if f["unaccounted"]:
        tail = "" if world.frames_witnessed else f" ({NO_WITNESS})"
    out.write(f"frames: {frame_identity(f)}{tail}\n")
    if world.physics is not None:
        faults = sum(1 for r in rows if r.get("actuator_fault"))
        out.write(
            f"physics: {world.physics.simulated_s:.1f} s simulated; moved {world.physics.displacement() * 100:+.1f} cm "
            f"forward; servos driven through dynamixel-sdk and emulators, {faults} module(s) with an actuator fault\n"
        )
    push = _push_cost(world)
    if push is not None:
        out.write(
            f"sensors: {', '.join(world.measured)} pushed {push['pushes']} times from physics, "
            f"{push['mean_ms']:.2f} ms each (p99 {push['p99_ms']:.2f} ms)\n"
        )
    faulted = [r["name"] for r in rows if r.get("actuator_fault") or int(r["counters"].get("engine_faults", 0))]
    if faulted:
        out.write(f"modules with a fault at the end: {', '.join(faulted)}\n")
    for line in world.log[-20:]:
        out.write(f"  {line}\n")
    for line in [] if flashes is None else flashes.lines():
        out.write(f"{line}\n")
    out.write(f"log: {log_path} ({len(world.log)} lines)\n")
    out.flush()


def _push_cost(world: World) -> dict[str, Any] | None:
    """How often the world pushed sensor readings and what a push cost (None: it never did)."""
    times = sorted(world.push_times)
    if not times:
        return None
    return {
        "sensors": list(world.measured),
        "every": world.sensor_every,
        "pushes": len(times),
        "mean_ms": round(sum(times) / len(times) * 1000, 3),
        "p99_ms": round(times[min(len(times) - 1, int(0.99 * len(times)))] * 1000, 3),
    }


if __name__ == "__main__":
    sys.exit(main())
