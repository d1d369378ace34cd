"""What the world knows of each module from its reports, and the status table's rows."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any


@dataclass(slots=True)
class ModuleView:
    """What the world last heard from one module."""

    module: int
    name: str
    alive: bool = False
    ready: bool = False
    finished: bool = False
    failed: bool = False
    killed: bool = False
    status: Mapping[str, Any] = field(default_factory=dict)
    frames_per_s: float = 0.0
    errors: list[str] = field(default_factory=list)
    #: the program it last said it runs (a status without one, e.g. a new life's first, keeps it)
    program: Mapping[str, Any] = field(default_factory=dict)
    _last: tuple[float, int] | None = None

    @property
    def state(self) -> str:
        """failed, killed, done (ran its cycles), running or stopped."""
        if self.failed:
            return "failed"
        if self.killed:
            return "killed"
        if self.finished:
            return "done"
        return "running" if self.alive else "stopped"

    def heard(self, status: Mapping[str, Any], now: float, *, sample_rate: bool) -> None:
        """A status report arrived at ``now``; ``sample_rate`` refreshes frames/s (at most
        every 0.2 s, so the rate is not a ratio of two tiny numbers)."""
        counters = status.get("counters", {})
        frames = int(counters.get("frames_sent", 0)) + int(counters.get("frames_received", 0))
        if sample_rate and (self._last is None or now - self._last[0] >= 0.2):
            if self._last is not None:
                self.frames_per_s = (frames - self._last[1]) / (now - self._last[0])
            self._last = (now, frames)
        self.status = status
        if status.get("program"):
            self.program = status["program"]


def rows(views: Sequence[ModuleView]) -> list[dict[str, Any]]:
    """One row per module for the status table and the summary."""
    out: list[dict[str, Any]] = []
    for v in views:
        s = v.status
        c = s.get("counters", {})
        out.append(
            {
                "module": v.module,
                "name": v.name,
                "alive": v.alive,
                "state": v.state,
                "cycle": s.get("cycle", 0),
                "type": s.get("type", "-"),
                "T": s.get("T"),
                "DOF1": s.get("DOF1", 0.0),
                "DOF2": s.get("DOF2", 0.0),
                "frames_per_s": v.frames_per_s,
                "counters": c,
                # how late its cycles started (p50, p99, max ms): tests judge timing with it
                "lateness_ms": s.get("lateness_ms"),
                # the module's own work (CPU ms of its process) between cycle starts: beside
                # lateness_ms, who held a late cycle (the module, or the machine)
                "work_ms": s.get("work_ms"),
                "actuator_fault": s.get("actuator_fault"),
                # with a [tracker] (--tracker-udp): the datagrams its feed took, rejected, dropped as stale
                "tracker": s.get("tracker"),
                "last_fault": s.get("last_fault"),
                "errors": sum(int(c.get(k, 0)) for k in ("frames_dropped", "frames_corrupted", "refused")),
                # the program it runs, booted from its flash (a rollout may have switched it)
                "version": v.program.get("version"),
                "sha256": v.program.get("sha256"),
                # V and S by name, as its last status gave them
                "variables": s.get("variables", {}),
                "sensors": s.get("sensors", {}),
                # the operator's commands it took, refused (by reason) and passed on (dh2rt console)
                "operator": s.get("operator", {}),
            }
        )
    return out
