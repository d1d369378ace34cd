"""The control protocol between the world and its modules: typed commands in, typed
reports out, as JSON lines (one object a line) over a module process's stdin and stdout, or
as the same objects through queues for modules that run as threads.

Commands (``{"cmd": ...}``): :class:`Go`, :class:`Attach`, :class:`Detach`, :class:`Inject`,
:class:`Sense`, :class:`Readings`, :class:`Hold`, :class:`OwnMotions`, :class:`LatchAnswer`,
:class:`StatusRequest`, :class:`Stop`.
Reports (``{"event": ...}``): :class:`Ready`,
:class:`Status` (also the ``final`` one, at exit), :class:`TraceRecord`, :class:`Effect`,
:class:`Log`, :class:`Failure` and :class:`Exited`. Decoding something else raises
ControlProtocolError naming the field; a receiver logs it and goes on.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import EllipsisType
from typing import Any

from dh2rt.errors import ControlProtocolError, ModuleConfigError
from dh2rt.transport.base import LinkEnd
from firmware.config import end_from_json, end_to_json

# ---------------------------------------------------------------- commands


@dataclass(frozen=True)
class Go:
    """Start cycling: at ``at`` (a CLOCK_MONOTONIC reading; Hellos until then) or at once;
    ``cycles`` more cycles (None: until stopped; ``...``: as configured)."""

    at: float | None = None
    cycles: int | EllipsisType | None = ...


@dataclass(frozen=True)
class Attach:
    connector: int
    end: LinkEnd


@dataclass(frozen=True)
class Detach:
    connector: int


@dataclass(frozen=True)
class Inject:
    hormone: str  # as text, e.g. X(A)


@dataclass(frozen=True)
class Sense:
    """A ``sense`` event: sensor ``sensor`` of the module reads ``value`` from now on."""

    sensor: str
    value: int


@dataclass(frozen=True)
class Readings:
    """Sensor readings the world measured for the module (its physics: IMU, infrared, ground
    contact), by sensor name, in the profile's units; the module writes them into S at its next
    cycle (rounded and clamped to the profile's ranges), except where a ``sense`` holds."""

    values: Mapping[str, int]


@dataclass(frozen=True)
class Hold:
    """Joint targets a docking motion holds (hil.reach_loop): from its next cycle the module
    sends its servos these (degrees, by DOF index: 0 is DOF1, 1 is DOF2) in place of its
    program's; empty: the joints are the program's again."""

    targets: Mapping[int, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Floor:
    """The overhead tracker's last report, for the reach a module runs itself (the world fills
    it as it fills the other sensors; on a robot it is ``dh2rt tracker`` over UDP,
    firmware.tracker_feed): the three parts of each module the motion reads, on the floor
    (x, y in metres, heading in radians: centre, front, back), and the module's own IMU
    (roll, pitch in degrees, by its index; another module's tilt reaches it in that module's
    ANGLES, firmware.motion.member)."""

    parts: Mapping[int, tuple[tuple[float, ...], ...]] = field(default_factory=dict)
    attitude: Mapping[int, tuple[float, ...]] = field(default_factory=dict)


@dataclass(frozen=True)
class OwnMotions:
    """From now on the module carries out its program's ``reach_dock`` itself
    (firmware.motion.asking) instead of leaving it to the world (hil.reach_loop)."""


@dataclass(frozen=True)
class LatchAnswer:
    """The world's answer to a module's ``latch`` effect (a reach it runs itself asked for the
    latch of its ``connector``: firmware.motion.asking): ``closed``, the faces latched in
    physics and the link made; else refused (not aligned). The latch is the world's until the
    module has a latch driver (issue 28)."""

    connector: int
    closed: bool


@dataclass(frozen=True)
class StatusRequest:
    pass


@dataclass(frozen=True)
class Stop:
    pass


Command = (
    Go | Attach | Detach | Inject | Sense | Readings | Hold | Floor | OwnMotions | LatchAnswer | StatusRequest | Stop
)


def command_to_json(cmd: Command) -> dict[str, Any]:
    if isinstance(cmd, Go):
        out: dict[str, Any] = {"cmd": "go", "at": cmd.at}
        if cmd.cycles is not ...:
            out["cycles"] = cmd.cycles
        return out
    if isinstance(cmd, Attach):
        return {"cmd": "attach", "connector": cmd.connector, "link": end_to_json(cmd.end)}
    if isinstance(cmd, Detach):
        return {"cmd": "detach", "connector": cmd.connector}
    if isinstance(cmd, Inject):
        return {"cmd": "inject", "hormone": cmd.hormone}
    if isinstance(cmd, Sense):
        return {"cmd": "sense", "sensor": cmd.sensor, "value": cmd.value}
    if isinstance(cmd, Readings):
        return {"cmd": "readings", "values": dict(cmd.values)}
    if isinstance(cmd, Hold):
        return {"cmd": "hold", "targets": {str(dof): v for dof, v in cmd.targets.items()}}
    if isinstance(cmd, Floor):
        parts = {str(m): [list(p) for p in ps] for m, ps in cmd.parts.items()}
        return {"cmd": "floor", "parts": parts, "attitude": {str(m): list(a) for m, a in cmd.attitude.items()}}
    if isinstance(cmd, OwnMotions):
        return {"cmd": "own_motions"}
    if isinstance(cmd, LatchAnswer):
        return {"cmd": "latch", "connector": cmd.connector, "closed": cmd.closed}
    if isinstance(cmd, StatusRequest):
        return {"cmd": "status"}
    return {"cmd": "stop"}


def command_from_json(obj: object) -> Command:
    """A command from its JSON object; ControlProtocolError naming the field otherwise."""
    if not isinstance(obj, Mapping):
        raise ControlProtocolError(f"command: expected an object, got {obj!r}")
    kind = obj.get("cmd")
    if kind == "go":
        at = obj.get("at")
        if at is not None and not isinstance(at, int | float):
            raise ControlProtocolError(f"go command: field 'at' {at!r} is not a time")
        cycles: int | EllipsisType | None = ...
        if "cycles" in obj:
            cycles = None if obj["cycles"] is None else _int(obj, "cycles", "go command")
        return Go(None if at is None else float(at), cycles)
    if kind == "attach":
        try:
            end = end_from_json(obj.get("link"), "attach command: field 'link'")
        except ModuleConfigError as exc:
            raise ControlProtocolError(str(exc)) from None
        return Attach(_int(obj, "connector", "attach command"), end)
    if kind == "detach":
        return Detach(_int(obj, "connector", "detach command"))
    if kind == "inject":
        hormone = obj.get("hormone")
        if not isinstance(hormone, str):
            raise ControlProtocolError(f"inject command: field 'hormone' {hormone!r} is not text")
        return Inject(hormone)
    if kind == "sense":
        sensor = obj.get("sensor")
        if not isinstance(sensor, str) or not sensor:
            raise ControlProtocolError(f"sense command: field 'sensor' {sensor!r} is not a name")
        return Sense(sensor, _int(obj, "value", "sense command"))
    if kind == "readings":
        values = obj.get("values")
        if not isinstance(values, Mapping):
            raise ControlProtocolError(f"readings command: field 'values' {values!r} is not an object")
        for name, value in values.items():
            if not isinstance(value, int) or isinstance(value, bool):
                raise ControlProtocolError(f"readings command: sensor {name!r} value {value!r} is not a whole number")
        return Readings(dict(values))
    if kind == "hold":
        return Hold(_targets(obj.get("targets")))
    if kind == "own_motions":
        return OwnMotions()
    if kind == "floor":
        return Floor(
            {m: tuple(_numbers(p, 3, "floor command: a part") for p in ps) for m, ps in _by_module(obj, "parts", 3)},
            {m: _numbers(a, 2, "floor command: an attitude") for m, a in _by_module(obj, "attitude", None)},
        )
    if kind == "latch":
        closed = obj.get("closed")
        if not isinstance(closed, bool):
            raise ControlProtocolError(f"latch command: field 'closed' {closed!r} is not true or false")
        return LatchAnswer(_int(obj, "connector", "latch command"), closed)
    if kind == "status":
        return StatusRequest()
    if kind == "stop":
        return Stop()
    raise ControlProtocolError(f"command: unknown 'cmd' {kind!r}")


def _by_module(obj: Mapping[str, Any], name: str, parts: int | None) -> list[tuple[int, Any]]:
    """A floor command's object of module -> value; each value a list of ``parts`` items."""
    values = obj.get(name)
    if not isinstance(values, Mapping):
        raise ControlProtocolError(f"floor command: field {name!r} {values!r} is not an object")
    out = []
    for key, value in values.items():
        if not str(key).isdigit():
            raise ControlProtocolError(f"floor command: field {name!r}: module {key!r} is not an index")
        if parts is not None and (not isinstance(value, list) or len(value) != parts):
            raise ControlProtocolError(f"floor command: module {key} has not {parts} parts: {value!r}")
        out.append((int(key), value))
    return out


def _numbers(value: object, n: int, what: str) -> tuple[float, ...]:
    if (
        not isinstance(value, list)
        or len(value) != n
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        raise ControlProtocolError(f"{what} {value!r} is not {n} numbers")
    return tuple(float(v) for v in value)


# ---------------------------------------------------------------- reports


@dataclass(frozen=True)
class Ready:
    """Transport open, links attached: waiting for Go."""


@dataclass(frozen=True)
class Status:
    """The module's runtime status (``ModuleRuntime.status()``: cycle, type, T, DOF1/DOF2,
    ConnectorStatus, counters, faults); ``final`` at exit, with ``failed`` and the last
    commanded ``targets``."""

    status: Mapping[str, Any]
    final: bool = False
    failed: bool = False
    targets: tuple[float, float] | None = None


@dataclass(frozen=True)
class TraceRecord:
    record: Mapping[str, Any]


@dataclass(frozen=True)
class Effect:
    kind: str
    args: list[Any] = field(default_factory=list)


@dataclass(frozen=True)
class Log:
    message: str


@dataclass(frozen=True)
class Failure:
    """The module failed (a bad config, an exception in its loop)."""

    message: str


@dataclass(frozen=True)
class Exited:
    """The module's process or thread ended (made by the supervisor, not sent by a module).
    ``life``: which of the module's lives it was (a killed life's end may be read after the
    next life started: the world must not take it for the new one's)."""

    life: int = 0


Report = Ready | Status | TraceRecord | Effect | Log | Failure | Exited


def report_to_json(rep: Report) -> dict[str, Any]:
    if isinstance(rep, Ready):
        return {"event": "ready"}
    if isinstance(rep, Status):
        out = {**rep.status, "event": "final" if rep.final else "status"}
        if rep.final:
            out["failed"] = rep.failed
            out["targets"] = None if rep.targets is None else list(rep.targets)
        return out
    if isinstance(rep, TraceRecord):
        return {"event": "trace", "record": dict(rep.record)}
    if isinstance(rep, Effect):
        return {"event": "effect", "kind": rep.kind, "args": _jsonable(rep.args)}
    if isinstance(rep, Log):
        return {"event": "log", "message": rep.message}
    if isinstance(rep, Failure):
        return {"event": "error", "message": rep.message}
    return {"event": "exit"}


def report_from_json(obj: object) -> Report:
    """A report from its JSON object; ControlProtocolError naming the field otherwise."""
    if not isinstance(obj, Mapping):
        raise ControlProtocolError(f"report: expected an object, got {obj!r}")
    event = obj.get("event")
    if event == "ready":
        return Ready()
    if event in ("status", "final"):
        status = {k: v for k, v in obj.items() if k not in ("event", "failed", "targets")}
        if not isinstance(status.get("counters", {}), Mapping):
            raise ControlProtocolError(f"{event} report: field 'counters' is not an object")
        targets = obj.get("targets")
        return Status(
            status,
            final=event == "final",
            failed=bool(obj.get("failed", False)),
            targets=None if targets is None else (float(targets[0]), float(targets[1])),
        )
    if event == "trace":
        record = obj.get("record")
        if not isinstance(record, Mapping):
            raise ControlProtocolError("trace report: field 'record' is not an object")
        return TraceRecord(record)
    if event == "effect":
        kind, args = obj.get("kind"), obj.get("args", [])
        if not isinstance(kind, str) or not isinstance(args, list):
            raise ControlProtocolError(f"effect report: fields 'kind' {kind!r} and 'args' {args!r}")
        return Effect(kind, args)
    if event == "log":
        return Log(str(obj.get("message", "")))
    if event == "error":
        return Failure(str(obj.get("message", "")))
    if event == "exit":
        return Exited()
    raise ControlProtocolError(f"report: unknown 'event' {event!r}")


def _int(obj: Mapping[str, Any], name: str, where: str) -> int:
    value = obj.get(name)
    if not isinstance(value, int) or isinstance(value, bool):
        raise ControlProtocolError(f"{where}: field {name!r} {value!r} is not a whole number")
    return value


def _targets(targets: object) -> dict[int, float]:
    """A hold command's joint targets: {"0" or "1": degrees}."""
    if not isinstance(targets, Mapping):
        raise ControlProtocolError(f"hold command: field 'targets' {targets!r} is not an object")
    out: dict[int, float] = {}
    for dof, value in targets.items():
        if dof not in ("0", "1"):
            raise ControlProtocolError(f"hold command: joint {dof!r} is neither DOF1 ('0') nor DOF2 ('1')")
        if not isinstance(value, int | float) or isinstance(value, bool) or value != value:
            raise ControlProtocolError(f"hold command: joint {dof} target {value!r} is not a number of degrees")
        out[int(dof)] = float(value)
    return out


def _jsonable(value: Any) -> Any:
    if isinstance(value, tuple | list):
        return [_jsonable(v) for v in value]
    return value
