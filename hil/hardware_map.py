"""``--hardware-map FILE``: which real ports the launcher's modules use, instead of emulated ones.

A TOML file with one table per module, named as the topology names its modules (``m0`` ..
for ``snake:N``; a topology file's own names), each optional::

    [m0]
    servo_port = "/dev/ttyUSB0"      # its Dynamixel servos (DOF1, DOF2) on a U2D2
    servo_ids = [1, 2]
    servo_baud = 1000000
    servo_model = "XM430-W350"       # or "any"
    can_channel = "/dev/ttyACM0"     # --transport can: this module's own adapter (slcan, say)

    [m0.connectors]                  # --transport serial: a UART per docked connector
    back = "/dev/ttyAMA1"            # or { device = "/dev/ttyAMA1", baud = 115200 }

A module the map names no servos for takes the stand-in (``recording`` by default with a
map); a docked connector of a serial robot must be mapped for every module or for none (the
link emulator plays the rest only when nothing is mapped). Every error names the file and
the key, and the launcher exits 2.
"""

from __future__ import annotations

import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dh2rt.errors import OptionError
from dh2rt.topology import Topology
from dh2rt.transport.base import PortEnd
from drivers.dxl_table import MODEL_NAMES
from firmware.config import DEFAULTS

_KEYS = ("servo_port", "servo_ids", "servo_baud", "servo_model", "can_channel", "connectors")


@dataclass(frozen=True)
class ModuleHardware:
    """One module's real ports."""

    servo_port: str | None = None
    servo_ids: tuple[int, int] = DEFAULTS.servo_ids
    servo_baud: int = DEFAULTS.servo_baud
    servo_model: int | None = DEFAULTS.servo_model
    can_channel: str | None = None
    connectors: Mapping[int, PortEnd] = field(default_factory=dict)


@dataclass(frozen=True)
class HardwareMap:
    """Module index -> its hardware."""

    path: Path
    modules: Mapping[int, ModuleHardware]

    def get(self, module: int) -> ModuleHardware:
        return self.modules.get(module, ModuleHardware())

    @property
    def has_connectors(self) -> bool:
        return any(h.connectors for h in self.modules.values())


def load_hardware_map(path: Path, topology: Topology) -> HardwareMap:
    """Read and check ``path`` against ``topology``; OptionError names the key."""
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise OptionError(f"--hardware-map {path}: {exc.strerror or exc}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise OptionError(f"--hardware-map {path}: not valid TOML: {exc}") from None
    names = {name: m for m, name in enumerate(topology.names)}
    modules: dict[int, ModuleHardware] = {}
    for name, table in data.items():
        if name not in names:
            raise OptionError(f"{path}: [{name}]: no such module in {topology.spec} ({', '.join(topology.names)})")
        if not isinstance(table, Mapping):
            raise OptionError(f"{path}: {name}: expected a table [{name}]")
        modules[names[name]] = _module(path, name, table, topology)
    hardware = HardwareMap(path, modules)
    _check_connectors(hardware, topology)
    return hardware


def _fail(path: Path, where: str, message: str) -> OptionError:
    return OptionError(f"{path}: [{where}]: {message}")


def _module(path: Path, name: str, t: Mapping[str, Any], topology: Topology) -> ModuleHardware:
    unknown = sorted(set(t) - set(_KEYS))
    if unknown:
        raise _fail(path, name, f"{unknown[0]}: unknown key (known: {', '.join(_KEYS)})")
    kw: dict[str, Any] = {}
    for key in ("servo_port", "can_channel"):
        if key in t:
            if not isinstance(t[key], str) or not t[key]:
                raise _fail(path, name, f"{key}: expected a device path, got {t[key]!r}")
            kw[key] = t[key]
    if "servo_ids" in t:
        ids = t["servo_ids"]
        ok = isinstance(ids, list) and len(ids) == 2 and all(type(i) is int and 0 <= i <= 252 for i in ids)
        if not ok or ids[0] == ids[1]:
            raise _fail(path, name, f"servo_ids: expected two different ids 0..252 [DOF1, DOF2], got {ids!r}")
        kw["servo_ids"] = (ids[0], ids[1])
    if "servo_baud" in t:
        if type(t["servo_baud"]) is not int or t["servo_baud"] <= 0:
            raise _fail(path, name, f"servo_baud: expected a baud rate, got {t['servo_baud']!r}")
        kw["servo_baud"] = t["servo_baud"]
    if "servo_model" in t:
        kw["servo_model"] = _model(path, name, t["servo_model"])
    if "connectors" in t:
        kw["connectors"] = _connectors(path, name, t["connectors"], topology)
    if "servo_port" not in kw and any(k in kw for k in ("servo_ids", "servo_baud", "servo_model")):
        raise _fail(path, name, "servo_ids, servo_baud and servo_model need a servo_port")
    return ModuleHardware(**kw)


def _model(path: Path, name: str, value: object) -> int | None:
    if value == "any":
        return None
    for number, model in MODEL_NAMES.items():
        if value == number or (isinstance(value, str) and value.upper() == model.upper()):
            return number
    raise _fail(
        path, name, f"servo_model: unknown Dynamixel model {value!r} (known: {', '.join(MODEL_NAMES.values())})"
    )


def _connectors(path: Path, name: str, table: object, topology: Topology) -> dict[int, PortEnd]:
    where = f"{name}.connectors"
    if not isinstance(table, Mapping):
        raise _fail(path, name, "connectors: expected a table")
    profile = topology.profile
    out: dict[int, PortEnd] = {}
    for key, value in table.items():
        if key not in profile.connectors:
            raise _fail(path, where, f"{key}: no such connector ({', '.join(profile.connectors)})")
        c = profile.connectors.index(key) + 1
        if isinstance(value, str) and value:
            out[c] = PortEnd(value)
        elif isinstance(value, Mapping) and isinstance(value.get("device"), str):
            baud = value.get("baud", 115_200)
            if type(baud) is not int or baud <= 0:
                raise _fail(path, where, f"{key}: baud: expected a baud rate, got {baud!r}")
            out[c] = PortEnd(value["device"], baud)
        else:
            raise _fail(path, where, f"{key}: expected a device path or {{ device = ..., baud = ... }}, got {value!r}")
    return out


def _check_connectors(hardware: HardwareMap, topology: Topology) -> None:
    """Connectors are mapped for every docked one or for none."""
    if not hardware.has_connectors:
        return
    name = topology.profile.connector_name
    for lk in topology.links:
        for m, c in ((lk.a, lk.a_conn), (lk.b, lk.b_conn)):
            if c not in hardware.get(m).connectors:
                raise OptionError(
                    f"{hardware.path}: [{topology.names[m]}.connectors]: {name(c)} is docked in {topology.spec} "
                    "but not mapped (map every docked connector, or none to emulate the links)"
                )
