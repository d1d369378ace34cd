"""JSON Lines traces of the in-process robot: one object per module per cycle, in the
format of :mod:`dh2rt.records`."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from dh2rt.records import cycle_json
from dh2rt.robot import CycleRecord, Robot


def record_json(robot: Robot, rec: CycleRecord) -> dict[str, Any]:
    name = robot.topology.names[rec.module]
    return cycle_json(robot.engine(rec.module), rec.cycle, rec.module, name, rec.received, rec.sent, rec.faults)


class TraceWriter:
    """Writes the robot's records after each cycle (the robot must have ``record=True``)."""

    def __init__(
        self,
        stream: IO[str],
        robot: Robot,
        extra: Callable[[int], dict[str, Any]] | None = None,
        *,
        owns_stream: bool = True,
    ) -> None:
        self.stream = stream
        self.owns_stream = owns_stream
        self.robot = robot
        self.extra = extra
        robot.record = True

    @classmethod
    def open(cls, path: Path, robot: Robot, extra: Callable[[int], dict[str, Any]] | None = None) -> TraceWriter:
        """Write to ``path``; ``-`` is standard output (left open at the end)."""
        if str(path) == "-":
            return cls(sys.stdout, robot, extra, owns_stream=False)
        return cls(path.open("w", encoding="utf-8"), robot, extra)

    def write_cycle(self) -> None:
        for rec in sorted(self.robot.records, key=lambda r: r.module):
            if not self.robot.alive(rec.module):
                continue
            obj = record_json(self.robot, rec)
            if self.extra is not None:
                obj.update(self.extra(rec.module))
            self.stream.write(json.dumps(obj, separators=(",", ":")))
            self.stream.write("\n")
        self.robot.records.clear()

    def close(self) -> None:
        if self.owns_stream:
            self.stream.close()
        else:
            self.stream.flush()
