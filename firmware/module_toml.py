"""``module.toml``: the configuration a physical module boots with (``dh2rt module --config``),
read into the same typed :class:`~firmware.config.ModuleConfig` the HIL world gives its modules.

Every key is checked before anything starts; an error names the file and the key
(``module.toml: [servos] dof1_id: expected an integer 0..252, got 'one'``), and a file that
is not TOML names the line and column. Relative paths are relative to the file's folder.

::

    name = "spine0"                  # in logs only, never in a program

    [program]
    flash = "flash"                  # the module's flash: two slots and a state record; an
                                     # image put there as program.img is installed at first boot
    trust = ["keys/signer.pub"]      # whose signed images it accepts (dh2rt keys new)
    # allow_unsigned = true          # development only: accept unsigned images
    trial_cycles = 100               # clean cycles before a new program is confirmed

    [cycle]
    period_ms = 20                   # 50 Hz
    silence_cycles = 3               # liveness bound: a link silent this long is lost
    handshake_s = 1.0                # Hellos before the first cycle
    # timer_phase = 0                # LocalTimer at start (default: drawn at random)

    [transport]
    kind = "can"                     # can, serial (or inproc, virtual, udp for tests)
    interface = "socketcan"          # any python-can interface: slcan, pcan, kvaser, gs_usb, ...
    channel = "can0"
    bitrate = 1000000
    fd = false
    # data_bitrate = 2000000         # CAN FD's data phase

    # [transport.links]              # or links wired by hand, with no negotiation
    # back = { link_id = 4, side = 0 }

    # kind = "serial": one UART per connector, like CONRO's infrared pairs
    # [transport.connectors]         # (an empty table: a module with no serial link)
    # front = "/dev/ttyAMA1"
    # back = { device = "/dev/ttyAMA2", baud = 115200 }

    [connectors]                     # on a bus: each connector's local channel (infrared pair):
    front = { device = "/dev/ttyAMA3", contact = "/sys/class/gpio/gpio17/value" }
    back = { device = "/dev/ttyAMA4", contact = "/sys/class/gpio/gpio27/value", active_low = true }
                                     # links are negotiated over them (docs/link-layer.md)

    [servos]
    port = "/dev/ttyUSB0"            # a USB-to-Dynamixel adapter (U2D2)
    baud = 1000000
    dof1_id = 1                      # pitch
    dof2_id = 2                      # yaw
    model = "XM430-W350"             # every servo must answer with it ("any": no check)
    # latency_ms = 16                # the adapter's latency timer: replies wait 2 x this + 2 ms
    # stand_in = "recording"         # instead of port: record the angles ("none": drive nothing)

    [latch]                          # what holds a male face docked to the female one
    kind = "servo"                   # servo, gpio, recording (a stand-in) or none (the default)
    # connector = "front"            # a female connector (the profile's first by default)
    id = 3                           # servo: a Dynamixel at its own id on the [servos] port
    open_deg = -30.0                 #   goal positions (degrees, 0 = tick 2048)
    closed_deg = 30.0
    tolerance_deg = 3.0              #   present position this close to a goal counts as there
    timeout_s = 1.0                  # a move that takes longer is a fault (every kind)
    # port = "/dev/ttyUSB1"          #   a bus of its own instead (then baud, latency_ms too)
    # kind = "gpio": chip = "/dev/gpiochip0", output_line = 5, input_line = 6,
    #   output_active_low = false, input_active_low = true (libgpiod v2: the gpio extra)

    [tracker]                        # the overhead tracker (dh2rt tracker) over UDP, optional:
    port = 47328                     # the tracker's --publish port
    bind = "127.0.0.1"               # "" for every interface (the robot's network)
    max_age_s = 0.25                 # a part's pose older than this is left out
    modules = 5                      # the robot's modules: module m's centre, front and back
                                     # parts carry markers 3m, 3m+1, 3m+2
    # alpha = 0.3                    # smooth the poses (firmware.motion.floor_filter); raw if absent

    [sensors]                        # S.pos1/pos2/load1/load2 come from the servos
    servo_every = 1                  # cycles between two reads of present position and load
    stand_in = { roll = 0, contact = 1 }   # fixed readings of sensors with no device here

    [log]
    file = "-"                       # JSON lines; "-" is standard error
    status_every = 50                # cycles between status lines
    # status_file = "/run/dh2rt/status.json"   # rewritten atomically with each status

``[hil]`` is written by the HIL world only (control over stdin, trace records, the module's
index and life, a cycle count). :func:`dump_toml` writes a config back, so the world starts
each of its modules with a file like the one a robot's module boots with.
"""

from __future__ import annotations

import math
import random
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dh2rt.errors import DH2Error, KeyFileError, ModuleConfigError
from dh2rt.profile import CONRO, Profile
from dh2rt.runtime import MAX_CYCLE_PERIOD_S, ms_to_s, s_to_ms
from dh2rt.signed_image import public_key_pem, read_public_key
from dh2rt.transport.base import BusEnd, LinkEnd, PortEnd
from dh2rt.transport.registry import parse_spec as parse_transport_spec
from drivers.dxl_table import MODEL_NAMES
from firmware.config import (
    DEFAULTS,
    MAX_BAUD,
    MAX_CYCLES,
    MAX_HANDSHAKE_S,
    MAX_SERVO_ID,
    MAX_SERVO_LATENCY_MS,
    MAX_SILENCE_CYCLES,
    STAND_INS,
    ChannelSpec,
    LatchSpec,
    ModuleConfig,
    TrackerSpec,
)

IMAGE_NAME = "program.img"
#: What a flash directory that holds a program has (firmware.flash.slots): the state record,
#: or a single image to install at the first boot.
FLASH_FILES = ("state.json", IMAGE_NAME)
TRANSPORT_KINDS = ("can", "serial", "socketcan", "inproc", "virtual", "udp")
#: The transports on a shared bus, where links are negotiated over the connectors' channels.
BUS_KINDS = ("can", "socketcan", "virtual", "udp")
SECTIONS = (
    "name", "program", "cycle", "transport", "connectors", "servos", "latch", "tracker", "sensors", "log", "hil",
)  # fmt: skip


@dataclass(frozen=True)
class _Table:
    """One table of the file, with the file and the table's name for error messages."""

    source: str
    name: str
    data: Mapping[str, Any]

    def where(self, key: str) -> str:
        return f"{self.source}: [{self.name}] {key}" if self.name else f"{self.source}: {key}"

    def fail(self, key: str, message: str) -> ModuleConfigError:
        return ModuleConfigError(f"{self.where(key)}: {message}")

    def only(self, *keys: str) -> None:
        unknown = sorted(set(self.data) - set(keys))
        if unknown:
            raise self.fail(unknown[0], f"unknown key (known: {', '.join(keys)})")

    def table(self, key: str, required: bool = False) -> _Table:
        value = self.data.get(key)
        full = f"{self.name}.{key}" if self.name else key
        if value is None:
            if required:
                raise ModuleConfigError(f"{self.source}: [{full}]: missing table")
            return _Table(self.source, full, {})
        if not isinstance(value, Mapping):
            raise self.fail(key, f"expected a table, got {value!r}")
        return _Table(self.source, full, value)

    def get_str(self, key: str, default: str | None = None, choices: tuple[str, ...] = ()) -> str | None:
        value = self.data.get(key, default)
        if value is None:
            return None
        if not isinstance(value, str) or not value:
            raise self.fail(key, f"expected a non-empty string, got {value!r}")
        if choices and value not in choices:
            raise self.fail(key, f"expected one of {', '.join(choices)}, got {value!r}")
        return value

    def get_int(self, key: str, default: int | None, low: int, high: int) -> int | None:
        value = self.data.get(key, default)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise self.fail(key, f"expected an integer {low}..{high}, got {value!r}")
        return value

    def get_number(self, key: str, default: float, high: float, positive: bool = True) -> float:
        """A finite number up to ``high``: more than 0 (``positive``), else 0 or more
        (TOML's ``nan`` and ``inf`` are numbers too, and refused here)."""
        value = self.data.get(key, default)
        number = not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value)
        if not number or value > high or value < 0 or (positive and value == 0):
            bounds = f"a positive number at most {high:g}" if positive else f"a number from 0 to {high:g}"
            raise self.fail(key, f"expected {bounds}, got {value!r}")
        return float(value)

    def get_bool(self, key: str, default: bool) -> bool:
        value = self.data.get(key, default)
        if not isinstance(value, bool):
            raise self.fail(key, f"expected true or false, got {value!r}")
        return value

    def get_path(self, key: str, base: Path, default: str | None = None) -> Path | None:
        value = self.get_str(key, default)
        if value is None:
            return None
        return Path(value) if Path(value).is_absolute() else base / value


def load_toml(path: Path, profile: Profile = CONRO) -> ModuleConfig:
    """Read and check ``path``; ModuleConfigError names the key (or line and column)."""
    source = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ModuleConfigError(f"{source}: cannot read it ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise ModuleConfigError(f"{source}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ModuleConfigError(f"{source}: not valid TOML: {exc}") from None
    return parse_toml(data, source, path.resolve().parent, profile)


def parse_toml(data: Mapping[str, Any], source: str, base: Path, profile: Profile = CONRO) -> ModuleConfig:
    """The config in parsed TOML ``data``; ``base`` is the folder relative paths start from."""
    top = _Table(source, "", data)
    top.only(*SECTIONS)
    kw: dict[str, Any] = {"name": top.get_str("name") or ""}
    kw.update(_program(top.table("program", required=True), base))
    kw.update(_cycle(top.table("cycle")))
    kw.update(_transport(top.table("transport", required=True), base, profile))
    kw["connector_channels"] = _channels(top.table("connectors"), profile)
    if kw["connector_channels"] and kw["transport"].partition(":")[0] not in BUS_KINDS:
        raise ModuleConfigError(
            f"{source}: [connectors]: connector-local channels negotiate links on a bus; "
            f"[transport] kind {kw['transport']!r} has its links already"
        )
    kw.update(_servos(top.table("servos"), base))
    kw["latch"] = _latch(top.table("latch"), profile, kw.get("servo_port"))
    tracker = top.table("tracker")
    kw["tracker"] = TrackerSpec.from_mapping(tracker.data, f"{source}: [tracker]") if "tracker" in data else None
    kw.update(_sensors(top.table("sensors"), profile))
    kw.update(_log(top.table("log"), base))
    kw.update(_hil(top.table("hil"), profile))
    try:
        return ModuleConfig(**kw)
    except ModuleConfigError as exc:
        raise ModuleConfigError(f"{source}: {exc}") from None


def _program(t: _Table, base: Path) -> dict[str, Any]:
    """``[program]``: the flash the module boots from and the keys whose images it accepts."""
    t.only("flash", "trust", "allow_unsigned", "trial_cycles")
    flash = t.get_path("flash", base)
    if flash is None:
        raise t.fail("flash", "missing: the directory the module boots its program from")
    if not flash.is_dir():
        raise t.fail("flash", f"{flash} is not a directory")
    keys = t.data.get("trust", [])
    if not isinstance(keys, list) or not all(isinstance(k, str) and k for k in keys):
        raise t.fail("trust", f"expected a list of public key files, got {keys!r}")
    trust = []
    for i, name in enumerate(keys):
        path = Path(name) if Path(name).is_absolute() else base / name
        try:
            trust.append(read_public_key(path))
        except KeyFileError as exc:  # names its file: a weak key, or no key
            raise t.fail(f"trust[{i}]", str(exc)) from None
        except (OSError, DH2Error) as exc:
            raise t.fail(f"trust[{i}]", f"{path}: {getattr(exc, 'strerror', None) or exc}") from None
    allow_unsigned = t.get_bool("allow_unsigned", False)
    if not trust and not allow_unsigned:
        raise t.fail(
            "trust",
            "empty: list the public keys whose images this module accepts (dh2rt keys new), "
            "or allow_unsigned = true for development",
        )
    if not any((flash / name).exists() for name in FLASH_FILES):
        raise t.fail("flash", f"{flash} holds no program: write one with: dh2rt image PROGRAM -o {flash / IMAGE_NAME}")
    return {
        "flash": str(flash),
        "trust": tuple(trust),
        "allow_unsigned": allow_unsigned,
        "trial_cycles": t.get_int("trial_cycles", DEFAULTS.trial_cycles, 0, MAX_CYCLES),
    }


def _cycle(t: _Table) -> dict[str, Any]:
    t.only("period_ms", "silence_cycles", "handshake_s", "timer_phase")
    out: dict[str, Any] = {
        "cycle_period": ms_to_s(t.get_number("period_ms", s_to_ms(DEFAULTS.cycle_period), s_to_ms(MAX_CYCLE_PERIOD_S))),
        "silence_cycles": t.get_int("silence_cycles", DEFAULTS.silence_cycles, 1, MAX_SILENCE_CYCLES),
        "handshake": t.get_number("handshake_s", DEFAULTS.handshake, MAX_HANDSHAKE_S, positive=False),
    }
    phase = t.get_int("timer_phase", None, 0, MAX_CYCLES)
    out["timer_phase"] = random.SystemRandom().randrange(1 << 16) if phase is None else phase
    return out


def _connector(t: _Table, key: str, profile: Profile) -> int:
    for c in range(1, profile.connector_count + 1):
        if key in (profile.connector_name(c), str(c)):
            return c
    names = ", ".join(profile.connectors)
    raise t.fail(key, f"no such connector (this profile's: {names})")


def _transport(t: _Table, base: Path, profile: Profile) -> dict[str, Any]:
    kind = t.get_str("kind", None, TRANSPORT_KINDS)
    if kind is None:
        raise t.fail("kind", f"missing: one of {', '.join(TRANSPORT_KINDS)}")
    if kind == "serial":
        t.only("kind", "connectors", "baud")
        baud = t.get_int("baud", 115_200, 1, MAX_BAUD) or 115_200
        ports = t.table("connectors", required=True)
        attach: dict[int, LinkEnd] = {}
        for key, value in ports.data.items():
            c = _connector(ports, key, profile)
            if isinstance(value, str):
                attach[c] = PortEnd(value, baud)
                continue
            one = ports.table(key)
            one.only("device", "baud")
            device = one.get_str("device")
            if device is None:
                raise one.fail("device", "missing")
            attach[c] = PortEnd(device, one.get_int("baud", baud, 1, MAX_BAUD) or baud)
        return {"transport": "serial", "attach": attach}
    t.only("kind", "interface", "channel", "bitrate", "fd", "data_bitrate", "links")
    out: dict[str, Any] = {"attach": _links(t.table("links"), profile)}
    channel = t.get_str("channel")
    if kind == "can":
        interface = t.get_str("interface")
        if interface is None:
            raise t.fail("interface", "missing: a python-can interface (socketcan, slcan, pcan, ...)")
        options: dict[str, Any] = {"interface": interface, "fd": t.get_bool("fd", False)}
        if channel is None:
            raise t.fail("channel", "missing: the python-can channel (can0, /dev/ttyACM0, PCAN_USBBUS1, ...)")
        options["channel"] = channel
        for key in ("bitrate", "data_bitrate"):
            value = t.get_int(key, None, 10_000, 12_000_000)
            if value is not None:
                options[key] = value
        if "data_bitrate" in options and not options["fd"]:
            raise t.fail("data_bitrate", "is CAN FD's data phase: set fd = true as well")
        out.update(transport="can", bus_options=options)
    else:
        for key in ("interface", "bitrate", "fd", "data_bitrate"):
            if key in t.data:
                raise t.fail(key, f'only for kind = "can" (kind {kind!r} has its own)')
        out["transport"] = f"{kind}:{channel}" if channel else kind
    return out


def _channels(t: _Table, profile: Profile) -> dict[int, ChannelSpec]:
    """``[connectors]``: each connector's local channel (contact and a few bytes), over which
    the modules of a docked pair agree on their link id on the bus."""
    out: dict[int, ChannelSpec] = {}
    for key, value in t.data.items():
        c = _connector(t, key, profile)
        if isinstance(value, str) and value:
            out[c] = ChannelSpec(value)
            continue
        one = t.table(key)
        one.only("device", "contact", "active_low", "baud")
        device = one.get_str("device")
        if device is None:
            raise one.fail("device", "missing: the UART (or the emulation's pty) of this connector's channel")
        baud = one.get_int("baud", 115_200, 1, MAX_BAUD) or 115_200
        out[c] = ChannelSpec(device, one.get_str("contact"), one.get_bool("active_low", True), baud)
    return out


def _links(t: _Table, profile: Profile) -> dict[int, LinkEnd]:
    ends: dict[int, LinkEnd] = {}
    for key in t.data:
        c = _connector(t, key, profile)
        one = t.table(key)
        one.only("link_id", "side")
        link_id = one.get_int("link_id", None, 0, (1 << 18) - 2)
        side = one.get_int("side", None, 0, 1)
        if link_id is None or side is None:
            raise one.fail("link_id" if link_id is None else "side", "missing")
        ends[c] = BusEnd(link_id, side)
    return ends


def _servos(t: _Table, base: Path) -> dict[str, Any]:
    t.only("port", "baud", "dof1_id", "dof2_id", "model", "latency_ms", "stand_in")
    port = t.get_str("port")
    stand_in = t.get_str("stand_in", None, tuple(s for s in STAND_INS if s != "pybullet"))
    if port is not None and stand_in is not None:
        raise t.fail("stand_in", "a module has servos on a port or a stand-in, not both")
    if port is None:
        for key in ("baud", "dof1_id", "dof2_id", "model", "latency_ms"):
            if key in t.data:
                raise t.fail(key, "only with a servo port")
        return {"driver": stand_in or "recording"}
    dof1 = t.get_int("dof1_id", 1, 0, MAX_SERVO_ID)
    dof2 = t.get_int("dof2_id", 2, 0, MAX_SERVO_ID)
    if dof1 == dof2:
        raise t.fail("dof2_id", f"DOF1 and DOF2 need two servos, both are id {dof1}")
    return {
        "servo_port": port,
        "servo_ids": (dof1, dof2),
        "servo_baud": t.get_int("baud", DEFAULTS.servo_baud, 9600, MAX_BAUD),
        "servo_model": _model(t),
        "servo_latency_ms": _latency(t),
        "driver": "none",
    }


def _latch(t: _Table, profile: Profile, servo_port: str | None) -> LatchSpec | None:
    """``[latch]``: what holds the pins of a connector docked to the female face (none
    unless the table says so). ``connector`` names a female connector (the profile's first
    by default)."""
    if not t.data:
        return None
    if "kind" not in t.data:
        raise t.fail("kind", "missing: one of servo, gpio, recording, none")
    data = dict(t.data)
    female = [c for c in range(1, profile.connector_count + 1) if profile.gender(c) == "female"]
    if "connector" in data:
        if not isinstance(data["connector"], str):
            raise t.fail("connector", f"expected a connector's name, got {data['connector']!r}")
        if data["connector"] not in profile.connectors:
            names = ", ".join(profile.connectors)
            raise t.fail("connector", f"no such connector {data['connector']!r} (this profile's: {names})")
        c = profile.connectors.index(data["connector"]) + 1
        if profile.gender(c) != "female":
            raise t.fail(
                "connector", f"{profile.connector_name(c)} is {profile.gender(c)}: a latch holds a female face"
            )
        data["connector"] = c
    elif female:
        data["connector"] = female[0]
    return LatchSpec.from_mapping(data, f"{t.source}: [{t.name}]", servo_port)


def _sensors(t: _Table, profile: Profile) -> dict[str, Any]:
    """``[sensors]``: how often the servos are read as sensors, and the stand-in's fixed
    readings of sensors with no device (each a sensor of the profile, within its range)."""
    t.only("servo_every", "stand_in")
    out: dict[str, Any] = {"servo_sensor_every": t.get_int("servo_every", 1, 1, MAX_CYCLES)}
    stand_in = t.table("stand_in")
    values: dict[str, int] = {}
    for name, value in stand_in.data.items():
        if name not in profile.sensor_names:
            known = ", ".join(profile.sensor_names)
            raise stand_in.fail(name, f"profile {profile.name} has no such sensor (it has: {known})")
        spec = profile.sensor(name)
        if not isinstance(value, int) or isinstance(value, bool) or not spec.low <= value <= spec.high:
            raise stand_in.fail(name, f"expected a whole number {spec.low}..{spec.high} {spec.unit}, got {value!r}")
        values[name] = value
    out["sensor_values"] = values
    return out


def _latency(t: _Table) -> float | None:
    """``latency_ms``: the adapter's latency timer (None: dynamixel-sdk's 16 ms)."""
    if "latency_ms" not in t.data:
        return None
    return t.get_number("latency_ms", 0.0, MAX_SERVO_LATENCY_MS)


def _model(t: _Table) -> int | None:
    value = t.data.get("model", DEFAULTS.servo_model)
    if value == "any":
        return None
    if isinstance(value, int) and not isinstance(value, bool) and value in MODEL_NAMES:
        return value
    for number, name in MODEL_NAMES.items():
        if isinstance(value, str) and value.upper() == name.upper():
            return number
    known = ", ".join(sorted(MODEL_NAMES.values()))
    raise t.fail("model", f'unknown Dynamixel model {value!r} (known: {known}, or "any")')


def _log(t: _Table, base: Path) -> dict[str, Any]:
    t.only("file", "status_every", "status_file")
    target = t.get_path("file", base, "-")
    status = t.get_path("status_file", base)
    log_file = None if target is None or target.name == "-" else str(target)
    return {
        "log_file": log_file,
        "status_every": t.get_int("status_every", 50, 1, MAX_CYCLES),
        "status_file": None if status is None else str(status),
        "control": "none",
    }


def _hil(t: _Table, profile: Profile) -> dict[str, Any]:
    if not t.data:
        return {}
    t.only("control", "module", "life", "trace", "cycles", "attach")
    out: dict[str, Any] = {
        "control": t.get_str("control", "stdio", ("stdio", "none")),
        "module": t.get_int("module", 0, 0, MAX_CYCLES),
        "life": t.get_int("life", 0, 0, MAX_CYCLES),
        "trace": t.get_bool("trace", False),
        "cycles": t.get_int("cycles", None, 0, MAX_CYCLES),
    }
    if "attach" in t.data:
        out["attach"] = _links(t.table("attach"), profile)
    return out


def dump_toml(config: ModuleConfig, flash: Path, profile: Profile = CONRO, image: bytes | None = None) -> str:
    """``config`` as a module.toml booting from ``flash``, where ``image`` (a signed image, or
    the config's program image) is written as program.img; the config's trusted keys are
    written beside the flash."""
    flash.mkdir(parents=True, exist_ok=True)
    (flash / IMAGE_NAME).write_bytes(config.image if image is None else image)
    name = profile.connector_name
    keys = []
    for i, key in enumerate(config.trust):
        key_file = flash.parent / f"trust{i}.pub"
        key_file.write_bytes(public_key_pem(key))
        keys.append(_q(str(key_file)))
    lines = [f"name = {_q(config.label)}", "", "[program]", f"flash = {_q(str(flash))}"]
    lines += [f"trust = [{', '.join(keys)}]", f"allow_unsigned = {_value(config.allow_unsigned)}"]
    lines += [f"trial_cycles = {config.trial_cycles}", ""]
    lines += [
        "[cycle]",
        f"period_ms = {s_to_ms(config.cycle_period)!r}",
        f"silence_cycles = {config.silence_cycles}",
        f"handshake_s = {config.handshake!r}",
        f"timer_phase = {config.timer_phase}",
        "",
        "[transport]",
    ]
    ports = {c: e for c, e in config.attach.items() if isinstance(e, PortEnd)}
    links = {c: e for c, e in config.attach.items() if isinstance(e, BusEnd)}
    kind, options = parse_transport_spec(config.transport)
    channel = options.get("channel")
    lines.append(f"kind = {_q(kind)}")
    if kind == "can":
        lines += [f"{k} = {_value(v)}" for k, v in config.bus_options.items()]
    elif channel:
        lines.append(f"channel = {_q(channel)}")
    if ports or kind == "serial":  # a module with no serial link says so: an empty table
        lines += ["", "[transport.connectors]"]
        lines += [f"{name(c)} = {{ device = {_q(e.url)}, baud = {e.baudrate} }}" for c, e in sorted(ports.items())]
    if config.connector_channels:
        lines += ["", "[connectors]"]
        for c, spec in sorted(config.connector_channels.items()):
            fields = [f"device = {_q(spec.device)}", f"baud = {spec.baud}"]
            if spec.contact is not None:
                fields += [f"contact = {_q(spec.contact)}", f"active_low = {_value(spec.active_low)}"]
            lines.append(f"{name(c)} = {{ {', '.join(fields)} }}")
    lines += ["", "[servos]"]
    if config.servo_port:
        model = "any" if config.servo_model is None else MODEL_NAMES[config.servo_model]
        lines += [
            f"port = {_q(config.servo_port)}",
            f"baud = {config.servo_baud}",
            f"dof1_id = {config.servo_ids[0]}",
            f"dof2_id = {config.servo_ids[1]}",
            f"model = {_q(model)}",
        ]
        if config.servo_latency_ms is not None:
            lines.append(f"latency_ms = {config.servo_latency_ms!r}")
    else:
        lines.append(f"stand_in = {_q(config.driver)}")
    if config.latch is not None:
        lines += ["", "[latch]", f"kind = {_q(config.latch.kind)}", f"connector = {_q(name(config.latch.connector))}"]
        lines += [f"{k} = {_value(v)}" for k, v in config.latch.settings.items() if v is not None]
    if config.tracker is not None:
        lines += ["", "[tracker]"] + [f"{k} = {_value(v)}" for k, v in config.tracker.to_json().items()]
    lines += ["", "[sensors]", f"servo_every = {config.servo_sensor_every}"]
    if config.sensor_values:
        values = ", ".join(f"{k} = {v}" for k, v in config.sensor_values.items())
        lines.append(f"stand_in = {{ {values} }}")
    lines += ["", "[log]", f"file = {_q(config.log_file or '-')}", f"status_every = {config.status_every}"]
    if config.status_file:
        lines.append(f"status_file = {_q(config.status_file)}")
    lines += ["", "[hil]", f"control = {_q(config.control)}", f"module = {config.module}", f"life = {config.life}"]
    lines.append(f"trace = {_value(config.trace)}")
    if config.cycles is not None:
        lines.append(f"cycles = {config.cycles}")
    if links:
        lines += ["", "[hil.attach]"]
        lines += [f"{name(c)} = {{ link_id = {e.link_id}, side = {e.side} }}" for c, e in sorted(links.items())]
    return "\n".join(lines) + "\n"


def _q(text: str) -> str:
    """A TOML basic string."""
    escaped = text.replace("\\", "\\\\").replace('"', '\\"')
    return f'"{escaped}"'


def _value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    return _q(str(value))
