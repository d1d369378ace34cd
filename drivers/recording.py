"""A driver that records commanded angles and reports them back: the stand-in of last resort."""

from __future__ import annotations

from drivers.base import JointLimits, ModuleDriver


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
