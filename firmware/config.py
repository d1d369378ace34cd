"""A module's configuration: one frozen, typed record shared by the world that starts a
module and the module process that runs it, with one source for every default.

On the wire between processes it is a JSON object (:meth:`ModuleConfig.to_json`); reading
one back (:meth:`ModuleConfig.from_json`) checks every field and raises ModuleConfigError
naming the field. The launcher's option defaults come from here too (``DEFAULTS``), so a
value typed nowhere is the same at every hop: launcher, world, module process, runtime.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from dh2rt.errors import KeyFileError, ModuleConfigError
from dh2rt.liveness import SILENCE_CYCLES
from dh2rt.runtime import CYCLE_PERIOD_S, MAX_CYCLE_PERIOD_S
from dh2rt.signed_image import check_public_key
from dh2rt.transport.base import BusEnd, LinkEnd, PortEnd
from dh2rt.wire.tracker import DEFAULT_PORT as DEFAULT_TRACKER_PORT
from drivers.dxl_table import MODEL_XM430_W350

#: Seconds a module exchanges Hellos before cycle 0 when it is not told when to start.
HANDSHAKE_S = 1.0
#: The longest handshake a config may ask for (s).
MAX_HANDSHAKE_S = 600.0
#: The longest liveness bound (cycles) a config may set: a link silent this long is lost.
MAX_SILENCE_CYCLES = 10_000
#: The most of anything counted in cycles a config may set (cycles, trial and status cycles).
MAX_CYCLES = 1_000_000_000
#: The fastest UART or servo bus a config may name (baud).
MAX_BAUD = 12_000_000
#: Cycles between two status reports of a module to its world.
STATUS_EVERY = 10
#: The modules' body in the loop: PyBullet joints through emulated Dynamixel servos (the
#: full firmware path), a recording stand-in, or nothing.
STAND_INS = ("pybullet", "recording", "none")
DEFAULT_STAND_IN = "pybullet"
#: A module's own driver when it has no servo port: record the angles, or drive nothing.
DRIVERS = ("recording", "none")
#: Dynamixel ids of DOF1 (pitch) and DOF2 (yaw), their bus's baud rate and model.
DEFAULT_SERVO_IDS = (1, 2)
DEFAULT_SERVO_BAUD = 1_000_000
DEFAULT_SERVO_MODEL = MODEL_XM430_W350
#: The longest servo bus latency timer a config may set (ms): a reply timeout of about 1 s.
MAX_SERVO_LATENCY_MS = 500.0
#: The latency timer of servos the HIL world emulates (ms; a reply timeout of 102 ms): their
#: replies come from a thread of the world's process that waits behind physics steps (up to
#: ``hil.physics_stand_in.MAX_CATCH_UP_S`` of them after a hiccup), not from a servo's own hardware.
EMULATED_SERVO_LATENCY_MS = 50.0
#: How a module is controlled: by the HIL world over stdin/stdout, or by nothing (on a robot).
CONTROLS = ("stdio", "none")


def end_to_json(end: LinkEnd) -> dict[str, Any]:
    """A link end as JSON: ``{"link_id", "side"}`` on a bus, ``{"port"}`` on a serial link."""
    if isinstance(end, PortEnd):
        return {"port": end.url}
    return {"link_id": end.link_id, "side": end.side}


def end_from_json(obj: object, where: str) -> LinkEnd:
    if isinstance(obj, Mapping):
        if "port" in obj and isinstance(obj["port"], str):
            return PortEnd(obj["port"])
        link_id, side = obj.get("link_id"), obj.get("side")
        if isinstance(link_id, int) and isinstance(side, int) and side in (0, 1):
            return BusEnd(link_id, side)
    raise ModuleConfigError(f"{where}: expected {{'link_id': N, 'side': 0|1}} or {{'port': PATH}}, got {obj!r}")


@dataclass(frozen=True)
class ChannelSpec:
    """One connector's connector-local channel (drivers.connector_channel): the HIL world's
    emulation on a pty (``device`` only), or on hardware a UART and a GPIO contact pin."""

    device: str
    contact: str | None = None  # a GPIO value file: a UART channel; None: the emulation
    active_low: bool = True
    baud: int = 115_200

    def to_json(self) -> dict[str, Any]:
        return {"device": self.device, "contact": self.contact, "active_low": self.active_low, "baud": self.baud}

    @classmethod
    def from_json(cls, obj: object, where: str) -> ChannelSpec:
        if isinstance(obj, str):
            return cls(obj)
        if isinstance(obj, Mapping) and isinstance(obj.get("device"), str):
            contact = obj.get("contact")
            active_low, baud = obj.get("active_low", True), obj.get("baud", 115_200)
            if (contact is None or isinstance(contact, str)) and isinstance(active_low, bool) and _is_int(baud):
                return cls(obj["device"], contact, active_low, int(baud))
        raise ModuleConfigError(
            f"{where}: expected a device path or {{device, contact, active_low, baud}}, got {obj!r}"
        )


#: What can hold a docked connector: a servo-driven latch (Dynamixel, on the servo bus or a
#: port of its own), a GPIO-driven one (libgpiod), or the recording stand-in.
LATCH_KINDS = ("servo", "gpio", "recording")
#: The most degrees a servo latch may be off its position and count as there; the longest a
#: latch's move may take (s).
MAX_LATCH_TOLERANCE_DEG = 45.0
MAX_LATCH_TIMEOUT_S = 60.0
MAX_SERVO_ID = 252
#: Which keys each kind of latch takes (beyond ``kind`` and ``connector``), with their defaults.
LATCH_KEYS: dict[str, dict[str, Any]] = {
    "servo": {
        "id": None,  # required
        "open_deg": None,
        "closed_deg": None,
        "tolerance_deg": 3.0,
        "timeout_s": 1.0,
        "port": None,  # None: the [servos] port
        "baud": None,  # only with a port of its own
        "latency_ms": None,
    },
    "gpio": {
        "chip": None,
        "output_line": None,
        "input_line": None,
        "output_active_low": False,
        "input_active_low": False,
        "timeout_s": 1.0,
    },
    "recording": {"timeout_s": 1.0},
}


@dataclass(frozen=True)
class LatchSpec:
    """The latch of one connector (module.toml ``[latch]``), every value checked: build one
    with :meth:`from_mapping`, which names the key that is wrong. ``settings`` holds the
    kind's keys (:data:`LATCH_KEYS`) with defaults filled in."""

    kind: str
    connector: int = 1
    settings: Mapping[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "connector": self.connector, **self.settings}

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], where: str, servo_port: str | None = None) -> LatchSpec | None:
        """The latch ``data`` describes (None for ``kind = "none"``); ModuleConfigError names
        the key (``{where} id: expected an integer 0..252, got 300``). A servo latch without a
        ``port`` of its own is on ``servo_port``, and needs one."""

        def fail(key: str, message: str) -> ModuleConfigError:
            return ModuleConfigError(f"{where} {key}: {message}")

        kind = data.get("kind")
        if kind == "none":
            if set(data) - {"kind", "connector"}:
                raise fail(sorted(set(data) - {"kind", "connector"})[0], 'unknown key for kind = "none"')
            return None
        if kind not in LATCH_KINDS:
            raise fail("kind", f"expected one of {', '.join((*LATCH_KINDS, 'none'))}, got {kind!r}")
        known = LATCH_KEYS[kind]
        unknown = sorted(set(data) - set(known) - {"kind", "connector"})
        if unknown:
            raise fail(unknown[0], f"unknown key for kind = {kind!r} (known: kind, connector, {', '.join(known)})")
        connector = data.get("connector", 1)
        if not _is_int(connector) or connector < 1:
            raise fail("connector", f"expected a connector number, got {connector!r}")
        values = {key: data.get(key, default) for key, default in known.items()}
        for key, value in values.items():
            if value is None and key not in ("port", "baud", "latency_ms"):
                raise fail(key, "missing")
            if key in ("id",):
                _check_int(fail, key, value, 0, MAX_SERVO_ID)
            elif key in ("output_line", "input_line"):
                _check_int(fail, key, value, 0, 65_535)
            elif key == "baud" and value is not None:
                _check_int(fail, key, value, 9600, MAX_BAUD)
            elif key in ("open_deg", "closed_deg"):
                _check_number(fail, key, value, -180.0, 180.0, "a number from -180 to 180 (degrees)")
            elif key == "tolerance_deg":
                _check_number(fail, key, value, 0.0, MAX_LATCH_TOLERANCE_DEG, "a positive number at most 45 (degrees)")
            elif key == "timeout_s":
                _check_number(fail, key, value, 0.0, MAX_LATCH_TIMEOUT_S, "a positive number at most 60 (seconds)")
            elif key == "latency_ms" and value is not None:
                _check_number(fail, key, value, 0.0, MAX_SERVO_LATENCY_MS, "a positive number at most 500 (ms)")
            elif key in ("output_active_low", "input_active_low") and not isinstance(value, bool):
                raise fail(key, f"expected true or false, got {value!r}")
            elif key in ("chip", "port") and value is not None and (not isinstance(value, str) or not value):
                raise fail(key, f"expected a device path, got {value!r}")
        if kind == "servo":
            if abs(values["closed_deg"] - values["open_deg"]) <= 2 * values["tolerance_deg"]:
                raise fail(
                    "closed_deg",
                    f"{values['closed_deg']} is within twice tolerance_deg ({values['tolerance_deg']}) of open_deg "
                    f"{values['open_deg']}: one would read as the other",
                )
            if values["port"] is None:
                for key in ("baud", "latency_ms"):
                    if values[key] is not None:
                        raise fail(key, "only with a port of the latch's own")
                if servo_port is None:
                    raise fail("port", "missing: a servo latch is on the [servos] port, and there is none")
        if kind == "gpio" and values["output_line"] == values["input_line"]:
            raise fail("input_line", f"the output and the input need two lines, both are {values['input_line']}")
        return cls(kind, int(connector), values)


#: The most modules the overhead tracker reports in one datagram: 3 markers each, at most
#: dh2rt.wire.tracker.MAX_MARKERS (100) markers a datagram.
MAX_TRACKED_MODULES = 33
#: How old a tracked pose may be before a module leaves it out (s): the default, and the most.
TRACKER_MAX_AGE_S = 0.25
MAX_TRACKER_MAX_AGE_S = 60.0
#: The keys of module.toml's ``[tracker]``, with their defaults (``modules`` is required).
TRACKER_KEYS: dict[str, Any] = {
    "port": DEFAULT_TRACKER_PORT,
    "bind": "127.0.0.1",
    "max_age_s": TRACKER_MAX_AGE_S,
    "modules": None,
    "alpha": None,  # None: the reports raw, as the physics runs take them unless told
}


@dataclass(frozen=True)
class TrackerSpec:
    """Where a module hears the overhead tracker (module.toml ``[tracker]``), every value
    checked: build one with :meth:`from_mapping`, which names the key that is wrong. Marker
    ``3 m + k`` is module ``m``'s part ``k`` (0 centre, 1 front, 2 back), for ``m`` below
    ``modules`` (the robot's module indices). ``alpha``: the reports smoothed by
    firmware.motion.floor_filter.FloorFilter with that gain (None: raw)."""

    port: int
    bind: str = "127.0.0.1"
    max_age_s: float = TRACKER_MAX_AGE_S
    modules: int = 1
    alpha: float | None = None

    def to_json(self) -> dict[str, Any]:
        out = {"port": self.port, "bind": self.bind, "max_age_s": self.max_age_s, "modules": self.modules}
        return out if self.alpha is None else {**out, "alpha": self.alpha}

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], where: str) -> TrackerSpec:
        """The tracker feed ``data`` describes; ModuleConfigError names the key
        (``{where} port: expected an integer 1..65535, got 0``)."""

        def fail(key: str, message: str) -> ModuleConfigError:
            return ModuleConfigError(f"{where} {key}: {message}")

        unknown = sorted(set(data) - set(TRACKER_KEYS))
        if unknown:
            raise fail(unknown[0], f"unknown key (known: {', '.join(TRACKER_KEYS)})")
        values = {**TRACKER_KEYS, **data}
        _check_int(fail, "port", values["port"], 1, 65535)
        bind = values["bind"]
        if not isinstance(bind, str) or not bind.strip() == bind:
            raise fail("bind", f'expected an address to listen on ("127.0.0.1", "" for every interface), got {bind!r}')
        _check_number(fail, "max_age_s", values["max_age_s"], 0, MAX_TRACKER_MAX_AGE_S, "seconds in (0, 60]")
        if values["modules"] is None:
            raise fail("modules", "missing: how many modules the robot has (markers 0 .. 3 x modules - 1)")
        _check_int(fail, "modules", values["modules"], 1, MAX_TRACKED_MODULES)
        alpha = values["alpha"]
        if alpha is not None:
            _check_number(fail, "alpha", alpha, 0, 1.0, "a gain in (0, 1] (0.3: the physics runs' filtered variant)")
        return cls(
            int(values["port"]),
            bind,
            float(values["max_age_s"]),
            int(values["modules"]),
            None if alpha is None else float(alpha),
        )


def _check_int(fail: Callable[[str, str], ModuleConfigError], key: str, value: object, low: int, high: int) -> None:
    if not _is_int(value) or not low <= value <= high:  # type: ignore[operator]
        raise fail(key, f"expected an integer {low}..{high}, got {value!r}")


def _check_number(
    fail: Callable[[str, str], ModuleConfigError], key: str, value: object, low: float, high: float, expected: str
) -> None:
    """A finite number in (low, high] when low is 0, else in [low, high]: TOML's nan and inf are numbers too."""
    number = not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value)
    if not number or not (low < value <= high if low == 0 else low <= value <= high):  # type: ignore[operator]
        raise fail(key, f"expected {expected}, got {value!r}")


@dataclass(frozen=True)
class ModuleConfig:
    """Everything one module needs to run (the firmware's configuration)."""

    #: the program image to run (empty when the module boots from its ``flash``)
    image: bytes = b""
    module: int = 0
    name: str = ""
    transport: str = "inproc"
    attach: Mapping[int, LinkEnd] = field(default_factory=dict)
    timer_phase: int = 0
    #: seconds (dh2rt.runtime.CYCLE_PERIOD_S unless given)
    cycle_period: float = CYCLE_PERIOD_S
    cycles: int | None = None
    silence_cycles: int = SILENCE_CYCLES
    driver: str = "recording"
    servo_port: str | None = None
    servo_ids: tuple[int, int] = DEFAULT_SERVO_IDS
    servo_baud: int = DEFAULT_SERVO_BAUD
    #: the model number every servo must answer a PING with (None: any model)
    servo_model: int | None = DEFAULT_SERVO_MODEL
    #: the servo bus adapter's latency timer (ms), which sets how long the module waits for a
    #: servo's reply (2 x this + 2 ms); None: dynamixel-sdk's 16 ms (an FTDI adapter's default)
    servo_latency_ms: float | None = None
    #: python-can options of the ``can`` transport: interface, channel, bitrate, fd, data_bitrate
    bus_options: Mapping[str, Any] = field(default_factory=dict)
    #: connector -> its connector-local channel: on a bus, links are negotiated over these
    connector_channels: Mapping[int, ChannelSpec] = field(default_factory=dict)
    #: the module's flash (firmware.flash.slots): it boots from there rather than from ``image``
    flash: str | None = None
    #: raw Ed25519 public keys whose images the flash accepts; unsigned ones only if allowed
    trust: tuple[bytes, ...] = ()
    allow_unsigned: bool = False
    #: clean cycles (no fault, every neighbour verified) before a new program is confirmed
    trial_cycles: int = 100
    #: "stdio": commands from the HIL world on stdin, reports on stdout; "none": on its own
    control: str = "stdio"
    #: where JSON log lines go when there is no control channel (None: standard error)
    log_file: str | None = None
    #: a file rewritten (atomically) with the module's status every status_every cycles
    status_file: str | None = None
    trace: bool = False
    status_every: int = STATUS_EVERY
    handshake: float = HANDSHAKE_S
    #: sensors with no device behind them: fixed stand-in readings, by name (module.toml [sensors])
    sensor_values: Mapping[str, int] = field(default_factory=dict)
    #: cycles between two reads of the servos' present position and load (when the program reads any)
    servo_sensor_every: int = 1
    #: the latch of its female connector (module.toml [latch]); None: no latch
    latch: LatchSpec | None = None
    #: where it hears the overhead tracker (module.toml [tracker]); None: the world's Floor reports
    tracker: TrackerSpec | None = None
    #: Which life of the module this is (0 at the first start; each restart adds one), so
    #: that the records of its lives, each counting cycles from 0, can be told apart.
    life: int = 0

    def __post_init__(self) -> None:
        if self.driver not in DRIVERS:
            raise ModuleConfigError(f"config driver {self.driver!r}: expected one of {', '.join(DRIVERS)}")
        if not (math.isfinite(self.cycle_period) and 0 < self.cycle_period <= MAX_CYCLE_PERIOD_S):
            raise ModuleConfigError(
                f"config cycle_period {self.cycle_period}: must be more than 0 and at most {MAX_CYCLE_PERIOD_S:g} s"
            )
        if not (math.isfinite(self.handshake) and 0 <= self.handshake <= MAX_HANDSHAKE_S):
            raise ModuleConfigError(f"config handshake {self.handshake}: must be 0 to {MAX_HANDSHAKE_S:g} s")
        if not 1 <= self.silence_cycles <= MAX_SILENCE_CYCLES:
            raise ModuleConfigError(f"config silence_cycles {self.silence_cycles}: must be 1..{MAX_SILENCE_CYCLES}")
        if self.status_every < 1:
            raise ModuleConfigError(f"config status_every {self.status_every}: must be 1 or more")
        if self.cycles is not None and self.cycles < 0:
            raise ModuleConfigError(f"config cycles {self.cycles}: must be 0 or more")
        if self.servo_sensor_every < 1:
            raise ModuleConfigError(f"config servo_sensor_every {self.servo_sensor_every}: must be 1 or more")
        if self.servo_latency_ms is not None and not 0 < self.servo_latency_ms <= MAX_SERVO_LATENCY_MS:
            raise ModuleConfigError(
                f"config servo_latency_ms {self.servo_latency_ms}: must be more than 0 and at most "
                f"{MAX_SERVO_LATENCY_MS:g}"
            )
        if self.control not in CONTROLS:
            raise ModuleConfigError(f"config control {self.control!r}: expected one of {', '.join(CONTROLS)}")
        if self.tracker is not None and self.module >= self.tracker.modules:
            raise ModuleConfigError(
                f"[tracker] modules: {self.tracker.modules}, but this module's index is {self.module}: "
                f"expected more than {self.module}"
            )

    @property
    def label(self) -> str:
        return self.name or f"m{self.module}"

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "image":
                value = value.hex()
            elif f.name == "attach":
                value = {str(c): end_to_json(e) for c, e in sorted(value.items())}
            elif f.name == "servo_ids":
                value = list(value)
            elif f.name in ("bus_options", "sensor_values"):
                value = dict(value)
            elif f.name == "trust":
                value = [key.hex() for key in value]
            elif f.name == "connector_channels":
                value = {str(c): spec.to_json() for c, spec in sorted(value.items())}
            elif f.name in ("latch", "tracker"):
                value = None if value is None else value.to_json()
            out[f.name] = value
        return out

    @classmethod
    def from_json(cls, obj: object) -> ModuleConfig:
        """Check and convert a JSON object; ModuleConfigError names the field that is wrong.
        ``image_path`` (a file holding the image) may stand for ``image``."""
        if not isinstance(obj, Mapping):
            raise ModuleConfigError("config: expected a JSON object")
        known = {f.name for f in fields(cls)} | {"image_path"}
        unknown = sorted(set(obj) - known)
        if unknown:
            raise ModuleConfigError(f"config: unknown field(s) {', '.join(map(repr, unknown))}")
        kw: dict[str, Any] = {}
        if "image" in obj:
            try:
                kw["image"] = bytes.fromhex(_typed(obj, "image", str))
            except ValueError:
                raise ModuleConfigError("config image: not hexadecimal") from None
        elif "flash" in obj:
            kw["image"] = b""  # booted from the flash
        elif "image_path" in obj:
            path = _typed(obj, "image_path", str)
            try:
                kw["image"] = Path(path).read_bytes()
            except OSError as exc:
                raise ModuleConfigError(f"config image_path {path}: {exc.strerror or exc}") from None
        else:
            raise ModuleConfigError("config: one of 'image' (hex), 'image_path' or 'flash' is required")
        for name, kind in (
            ("module", int),
            ("name", str),
            ("transport", str),
            ("timer_phase", int),
            ("silence_cycles", int),
            ("driver", str),
            ("trace", bool),
            ("status_every", int),
            ("life", int),
            ("servo_baud", int),
            ("control", str),
            ("allow_unsigned", bool),
            ("trial_cycles", int),
            ("servo_sensor_every", int),
        ):
            if name in obj:
                kw[name] = _typed(obj, name, kind)
        for name in ("cycle_period", "handshake"):
            if name in obj:
                kw[name] = float(_typed(obj, name, (int, float)))
        if obj.get("cycles") is not None:
            kw["cycles"] = _typed(obj, "cycles", int)
        if "trust" in obj:
            keys = obj["trust"]
            if not isinstance(keys, list) or not all(isinstance(k, str) for k in keys):
                raise ModuleConfigError("config trust: expected a list of public keys in hexadecimal")
            try:
                kw["trust"] = tuple(check_public_key(bytes.fromhex(k)) for k in keys)
            except KeyFileError as exc:  # a weak key (anyone could sign for it), or no key
                raise ModuleConfigError(f"config trust: {exc}") from None
            except ValueError:
                raise ModuleConfigError("config trust: not hexadecimal") from None
        for name in ("servo_port", "log_file", "status_file", "flash"):
            if obj.get(name) is not None:
                kw[name] = _typed(obj, name, str)
        if obj.get("servo_latency_ms") is not None:
            kw["servo_latency_ms"] = float(_typed(obj, "servo_latency_ms", (int, float)))
        if "servo_model" in obj:
            kw["servo_model"] = None if obj["servo_model"] is None else _typed(obj, "servo_model", int)
        if "bus_options" in obj:
            kw["bus_options"] = dict(_typed(obj, "bus_options", Mapping))
        if "sensor_values" in obj:
            values = _typed(obj, "sensor_values", Mapping)
            if not all(isinstance(k, str) and _is_int(v) for k, v in values.items()):
                raise ModuleConfigError(f"config sensor_values {values!r}: expected sensor name -> whole number")
            kw["sensor_values"] = dict(values)
        if "servo_ids" in obj:
            ids = obj["servo_ids"]
            if not (isinstance(ids, list | tuple) and len(ids) == 2 and all(_is_int(i) for i in ids)):
                raise ModuleConfigError(f"config servo_ids {ids!r}: expected two servo ids [DOF1, DOF2]")
            kw["servo_ids"] = (int(ids[0]), int(ids[1]))
        if "connector_channels" in obj:
            channels = obj["connector_channels"]
            if not isinstance(channels, Mapping) or not all(str(c).isdigit() for c in channels):
                raise ModuleConfigError("config connector_channels: expected an object of connector -> channel")
            kw["connector_channels"] = {
                int(c): ChannelSpec.from_json(v, f"config connector_channels[{c}]") for c, v in channels.items()
            }
        if obj.get("latch") is not None:
            latch = _typed(obj, "latch", Mapping)
            kw["latch"] = LatchSpec.from_mapping(latch, "config latch", kw.get("servo_port"))
        if obj.get("tracker") is not None:
            kw["tracker"] = TrackerSpec.from_mapping(_typed(obj, "tracker", Mapping), "config tracker")
        if "attach" in obj:
            attach = obj["attach"]
            if not isinstance(attach, Mapping):
                raise ModuleConfigError("config attach: expected an object of connector -> link end")
            ends: dict[int, LinkEnd] = {}
            for c, end in attach.items():
                if not str(c).isdigit():
                    raise ModuleConfigError(f"config attach: connector {c!r} is not a number")
                ends[int(c)] = end_from_json(end, f"config attach[{c}]")
            kw["attach"] = ends
        return cls(**kw)


def _is_int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _typed(obj: Mapping[str, Any], name: str, kind: type | tuple[type, ...]) -> Any:
    value = obj[name]
    wrong_bool = isinstance(value, bool) and kind is not bool
    if wrong_bool or not isinstance(value, kind):
        expected = kind.__name__ if isinstance(kind, type) else " or ".join(k.__name__ for k in kind)
        raise ModuleConfigError(f"config {name} {value!r}: expected {expected}")
    return value


#: The launcher's option defaults, from the one source above.
DEFAULTS = ModuleConfig(image=b"")
