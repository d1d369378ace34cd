"""Reading JSON Lines traces (``dh2rt run --trace``, the launcher's ``--trace``), streaming
and checked: one :class:`TraceRecord` per line, the fields the tools use typed.

The format is :mod:`dh2rt.records`' (one module's cycle per line). The in-process robot
writes the records of a cycle together, module by module; the launcher merges what its
modules reported, by cycle then module, and adds ``t`` (the module's clock) and ``life``
(0, then one more at each restart of the module, whose cycle count starts again at 0).
Fields the tools do not use (``type``, ``T``, ``timer``, ``status``, ``pos``, ``t``) are
not checked.

A line that is not a record raises :class:`TraceError` naming the file, the line and the
column (not JSON) or the field (``received[2].path``) that is wrong.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dh2rt.errors import TraceError, TraceFieldError


@dataclass(frozen=True, slots=True)
class TraceArrival:
    """A hormone a module took in: content as text (``X(A)``), the connector it arrived at
    and the one it was sent through (both None for an injected hormone), and the path it
    arrived with (``(sent through, received at)`` connector names, newest first)."""

    hormone: str
    at: str | None
    remote: str | None
    path: tuple[tuple[str, str], ...]


@dataclass(frozen=True, slots=True)
class TraceRecord:
    """One module's cycle, as far as the tools read it; ``line`` is its line in the file."""

    line: int
    cycle: int
    module: int
    name: str
    life: int
    dof: tuple[float, float]
    received: tuple[TraceArrival, ...]
    faults: tuple[str, ...]


def read_trace(path: Path) -> Iterator[TraceRecord]:
    """The records of the trace at ``path``, in file order (blank lines are skipped)."""
    try:
        stream = path.open(encoding="utf-8")
    except OSError as exc:
        raise TraceError(f"{path}: cannot read it ({exc.strerror or exc})") from None
    with stream:
        line_no = 0
        try:
            for line_no, line in enumerate(stream, 1):
                if line.strip():
                    yield parse_record(line, path, line_no)
        except UnicodeDecodeError as exc:
            raise TraceError(f"{path}:{line_no + 1}: not UTF-8 text ({exc.reason})") from None


def parse_record(line: str, path: Path | str, line_no: int) -> TraceRecord:
    """One line of a trace; raises TraceError naming ``path:line_no`` and what is wrong."""
    try:
        obj = json.loads(line)
    except json.JSONDecodeError as exc:
        raise TraceError(f"{path}:{line_no}:{exc.colno}: not JSON ({exc.msg}); is this a JSON Lines trace?") from None
    if not isinstance(obj, dict):
        raise TraceError(f"{path}:{line_no}: not a trace record (a JSON object per line), but {_kind(obj)}")
    try:
        return _record(obj, line_no)
    except TraceFieldError as exc:
        if exc.expected is None:
            raise TraceError(f"{path}:{line_no}: no field {exc.field!r}; not a trace record") from None
        raise TraceError(
            f"{path}:{line_no}: field {exc.field}: expected {exc.expected}, got {_kind(exc.value)}"
        ) from None


def _record(obj: dict[str, Any], line_no: int) -> TraceRecord:
    cycle, module, name = _count(obj, "cycle"), _count(obj, "module"), _field(obj, "name", str)
    actuators = _field(obj, "actuators", dict)
    dof = (_number(actuators.get("DOF1"), "actuators.DOF1"), _number(actuators.get("DOF2"), "actuators.DOF2"))
    received = tuple(_arrival(a, i) for i, a in enumerate(_field(obj, "received", list)))
    faults = tuple(_string(f, f"faults[{i}]") for i, f in enumerate(_field(obj, "faults", list, optional=True)))
    life = _count(obj, "life", optional=True)
    return TraceRecord(line_no, cycle, module, name, life, dof, received, faults)


_KINDS: dict[type, str] = {dict: "an object", list: "a list", str: "a string"}


def _field(obj: dict[str, Any], key: str, kind: type, *, optional: bool = False) -> Any:
    if key not in obj:
        if optional:
            return kind()
        raise TraceFieldError(key)
    value = obj[key]
    if not isinstance(value, kind):
        raise TraceFieldError(key, _KINDS[kind], value)
    return value


def _count(obj: dict[str, Any], key: str, *, optional: bool = False) -> int:
    if key not in obj:
        if optional:
            return 0
        raise TraceFieldError(key)
    value = obj[key]
    if type(value) is not int or value < 0:
        raise TraceFieldError(key, "a whole number 0 or more", value)
    return value


def _arrival(obj: Any, i: int) -> TraceArrival:
    if not isinstance(obj, dict):
        raise TraceFieldError(f"received[{i}]", "an object", obj)
    path = obj.get("path")
    if not isinstance(path, list):
        raise TraceFieldError(f"received[{i}].path", "a list", path)
    for j, hop in enumerate(path):
        if not (isinstance(hop, list) and len(hop) == 2 and isinstance(hop[0], str) and isinstance(hop[1], str)):
            raise TraceFieldError(f"received[{i}].path[{j}]", "[sent through, received at]", hop)
    at, remote = obj.get("at"), obj.get("from")
    return TraceArrival(
        hormone=_string(obj.get("hormone"), f"received[{i}].hormone"),
        at=None if at is None else _string(at, f"received[{i}].at"),
        remote=None if remote is None else _string(remote, f"received[{i}].from"),
        path=tuple((hop[0], hop[1]) for hop in path),
    )


def _number(value: Any, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise TraceFieldError(field, "a number", value)
    return float(value)


def _string(value: Any, field: str) -> str:
    if not isinstance(value, str):
        raise TraceFieldError(field, "a string", value)
    return value


def _kind(value: Any) -> str:
    """What a JSON value is, for messages: ``a string ("x")``, ``nothing`` for a missing one."""
    if value is None:
        return "nothing (null or missing)"
    if isinstance(value, bool):
        return f"a boolean ({json.dumps(value)})"
    text = json.dumps(value)
    if len(text) > 40:
        text = text[:37] + "..."
    for kind, name in (
        (dict, "an object"),
        (list, "a list"),
        (str, "a string"),
        (int, "a whole number"),
        (float, "a number"),
    ):
        if isinstance(value, kind):
            return f"{name} ({text})"
    return text
