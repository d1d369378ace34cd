"""Stand-ins of last resort: a driver that records commanded angles and reports them back,
and a latch that records its commands and is where it was told to be."""

from __future__ import annotations

from drivers.base import JointLimits, ModuleDriver
from drivers.latch import DEFAULT_TIMEOUT_S, Latch, Position, Sensed


class RecordingDriver(ModuleDriver):
    """Remembers every command; the present angle is the last target (an ideal servo)."""

    def __init__(self, limits: tuple[JointLimits, JointLimits] | None = None) -> None:
        if limits is not None:
            self.limits = limits
        self.targets = (0.0, 0.0)
        self.history: list[tuple[float, float]] = []
        self.torque = True

    def set_targets(self, dof1_deg: float, dof2_deg: float) -> None:
        self.targets = (self.limits[0].clamp(dof1_deg), self.limits[1].clamp(dof2_deg))
        self.history.append(self.targets)

    def read_positions(self) -> tuple[float, float]:
        return self.targets

    def read_loads(self) -> tuple[float, float]:
        """An ideal servo with nothing to move: no load."""
        return (0.0, 0.0)

    def set_torque(self, enabled: bool) -> None:
        self.torque = enabled


class RecordingLatch(Latch):
    """The latch stand-in: remembers every command and is at once where it was told to be
    (open until told otherwise), so a module without a latch runs a dock's sequence."""

    def __init__(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        super().__init__(timeout_s)
        self.history: list[Position] = []
        self.adopt(Position.OPEN)

    def _drive(self, target: Position) -> None:
        self.history.append(target)

    def _sense(self, target: Position | None) -> Sensed:
        where = target or Position.OPEN
        return Sensed(where, f"recorded {where.value}")
