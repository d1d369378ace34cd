"""An emulated latch servo: a Dynamixel horn whose way to "closed" the faces must allow.

A :class:`LatchJoint` is the :class:`~hil.servo_joints.JointBackend` of the latch servo on an
emulated bus (:class:`~hil.servo_emulator.ServoEmulator`, the real Protocol 2.0 over a pty):
a :class:`~hil.servo_joints.KinematicJoint` between ``open_deg`` and ``closed_deg``. Halfway
(``jam_at``) the latch's pins meet the mating face: they pass only if ``can_close()`` says the
faces are aligned at that moment (the world's physics gives the hook; by default they always
are). Otherwise the horn stops there and pushes at full load, as a servo against an obstacle
does; after ``overload_after_s`` of that it shuts down with an overload alert (Hardware Error
Status 0x20, torque off until a REBOOT), as an X-series servo's Shutdown (63) has it. Opening
always works: nothing blocks the way back. A latch that got past the pins stays closed
whatever the faces do afterwards.

:func:`emulate` puts a latch on a bus beside other servos (the module's two joints) or alone.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any, Final

from dh2rt.errors import EmulatorError
from drivers import dxl_table as dxt
from hil.servo_emulator import ServoEmulator
from hil.servo_joints import DEFAULT_SPEED_TPS, JointBackend, KinematicJoint
from hil.servo_table import EmulatedServo

#: The loop's latch servo (hil.physics_stand_in with ``latches``, the launcher's
#: ``--latch-emulator``): its id beside the joints' 1 and 2, the female face it holds (CONRO's
#: front, its only one), and the module.toml ``[latch]`` the world gives it (hil.world.World.config).
LATCH_ID: Final = 3
LATCH_CONNECTOR: Final = 1
LATCH_SETTINGS: Final[dict[str, Any]] = {"kind": "servo", "id": LATCH_ID, "open_deg": -30.0, "closed_deg": 30.0}


def always() -> bool:
    """The faces are aligned (a world that does not say otherwise)."""
    return True


class LatchJoint:
    """The horn of an emulated latch servo (see the module docstring). Called from the
    emulator's thread; ``can_close`` is called from there too."""

    def __init__(
        self,
        open_deg: float,
        closed_deg: float,
        can_close: Callable[[], bool] = always,
        *,
        start_deg: float | None = None,
        jam_at: float = 0.5,
        overload_after_s: float | None = 0.5,
        speed_limit_tps: float = DEFAULT_SPEED_TPS,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if open_deg == closed_deg or not 0.0 < jam_at < 1.0:
            raise EmulatorError(
                f"a latch needs open_deg != closed_deg and 0 < jam_at < 1, got {open_deg}, {closed_deg}, {jam_at}"
            )
        self.can_close = can_close
        self.overload_after_s = overload_after_s
        self._clock = clock
        self._open = dxt.CENTER_TICKS + open_deg / dxt.DEG_PER_TICK
        self._closed = dxt.CENTER_TICKS + closed_deg / dxt.DEG_PER_TICK
        self._toward = 1.0 if self._closed > self._open else -1.0
        self._jam = self._open + jam_at * (self._closed - self._open)
        start = self._open if start_deg is None else dxt.CENTER_TICKS + start_deg / dxt.DEG_PER_TICK
        self._horn = KinematicJoint(start, speed_limit_tps=speed_limit_tps, clock=clock)
        self._past = self._beyond(start)
        self._pushing_since: float | None = None
        self._overloaded = False
        self._servo: EmulatedServo | None = None
        #: closes refused (the pins met a face out of line) and overload shutdowns, for tests
        self.refused = 0
        self.overloads = 0

    def bind(self, servo: EmulatedServo) -> None:
        """The servo this horn belongs to, which shuts down on an overload."""
        self._servo = servo

    @property
    def is_past_the_pins(self) -> bool:
        """Whether the latch holds (its horn got past the pins toward closed)."""
        self._observe()
        return self._past

    def _beyond(self, ticks: float) -> bool:
        return (ticks - self._jam) * self._toward > 0

    def _observe(self) -> float:
        ticks = self._horn.present_ticks()
        if not self._beyond(ticks):
            self._past = False
            self._pushing_since = None
            return ticks
        if self._past:
            return ticks
        if self.can_close():
            self._past = True
            self._pushing_since = None
            return ticks
        # the pins meet a face out of line: the horn stops there and pushes
        self._horn.position = self._jam
        if self._horn.torque and self._beyond(self._horn.goal):
            now = self._clock()
            if self._pushing_since is None:
                self._pushing_since = now
                self.refused += 1
            pushed = now - self._pushing_since
            if self.overload_after_s is not None and pushed >= self.overload_after_s and not self._overloaded:
                self._overloaded = True
                self.overloads += 1
                if self._servo is not None:
                    self._servo.raise_alert(dxt.HW_OVERLOAD)  # torque off, alert bit in every status
        else:
            self._pushing_since = None
        return self._jam

    # -- JointBackend --

    def set_goal_ticks(self, ticks: float) -> None:
        self._observe()
        self._horn.set_goal_ticks(ticks)
        if not self._beyond(ticks):
            self._pushing_since = None

    def present_ticks(self) -> float:
        return self._observe()

    def set_torque(self, enabled: bool) -> None:
        self._observe()
        self._horn.set_torque(enabled)
        if enabled:
            self._overloaded = False
        else:
            self._pushing_since = None

    def set_speed_limit(self, ticks_per_s: float) -> None:
        self._horn.set_speed_limit(ticks_per_s)

    def present_load_percent(self) -> float:
        """Full load toward closed while the horn pushes against the pins, else none."""
        self._observe()
        return 100.0 * self._toward if self._pushing_since is not None else 0.0


def emulate(
    latch_id: int, latch: LatchJoint, others: Mapping[int, JointBackend] | None = None, **kwargs: object
) -> ServoEmulator:
    """A servo bus with the latch at ``latch_id`` beside ``others`` (the module's joints, by
    id), not started; ``kwargs`` go to :class:`ServoEmulator`."""
    servos = dict(others or {})
    if latch_id in servos:
        raise EmulatorError(f"servo id {latch_id} is taken on this bus: the latch needs its own id")
    servos[latch_id] = latch
    emulator = ServoEmulator(servos, **kwargs)  # type: ignore[arg-type]
    latch.bind(emulator.servo(latch_id))
    return emulator
