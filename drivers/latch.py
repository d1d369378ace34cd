"""The connector latch: what holds two docked modules together.

CONRO's female face (the ``front`` connector) latches the male's pins. A :class:`Latch` is
told to :meth:`~Latch.open` or :meth:`~Latch.close` and says, whenever asked, where it is:
:meth:`~Latch.state` gives a :class:`LatchStatus`, one of ``open``, ``closed``, ``moving``
(commanded, not there yet) or ``fault`` with the reason. The calls do not wait for the move
(only a servo latch's REBOOT after a shutdown waits for the servo); a dock polls
:meth:`~Latch.state` once per cycle.

One state machine for every latch lives in :class:`Latch`: a command starts a move that must
end within ``timeout_s`` (else ``fault``: "close did not finish in 1 s ..."), a latch that
reached its target and leaves it by itself is at fault at once, and a fault stays until the
next command. A backend says only how to drive the actuator (:meth:`Latch._drive`) and where
the mechanism is (:meth:`Latch._sense`):

* :class:`ServoLatch`: a Dynamixel servo at its own id on a :class:`~drivers.dynamixel.DynamixelBus`
  (the module's servo bus, shared with the joints, or a bus of its own): goal positions for
  open and closed, present position within a tolerance says which; a Hardware Error Status
  alert (an overloaded, jammed horn) or a horn that stops short of its goal is a fault, and a
  stalled horn is told to stop pushing.
* :class:`GpioLatch`: one output line drives the actuator (a solenoid, CONRO's shape-memory
  alloy wire), one input line reads a "closed" switch, through libgpiod v2 (:func:`gpio_lines`,
  the ``gpio`` extra) or any object with the two calls it uses (:class:`LatchLines`).

``drivers.recording.RecordingLatch`` is the stand-in: it is where it was told to be.
"""

from __future__ import annotations

import abc
import enum
import importlib
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any, Final, Protocol, Self

from dh2rt.errors import DriverConfigError, DriverError, LatchFault, ServoHardwareAlert
from drivers import dxl_table as dxt

if TYPE_CHECKING:
    from drivers.dynamixel import DynamixelBus

#: Seconds a move may take unless told otherwise (a latch travels a few tens of degrees).
DEFAULT_TIMEOUT_S: Final = 1.0
#: Degrees a servo latch may be off its open or closed position and still count as there.
DEFAULT_TOLERANCE_DEG: Final = 3.0
#: Seconds a servo latch's horn may stay put short of its goal before the move counts as stalled.
DEFAULT_STALL_S: Final = 0.3
#: The speed a servo latch moves at (degrees per second, its Profile Velocity).
DEFAULT_SPEED_DPS: Final = 180.0
#: The longest timeout a latch accepts (s).
MAX_TIMEOUT_S: Final = 60.0


class LatchState(enum.Enum):
    OPEN = "open"
    CLOSED = "closed"
    MOVING = "moving"
    FAULT = "fault"


@dataclass(frozen=True, slots=True)
class LatchStatus:
    """What :meth:`Latch.state` says: the state, and for a fault why."""

    state: LatchState
    reason: str = ""

    def __str__(self) -> str:
        return f"{self.state.value}: {self.reason}" if self.reason else self.state.value


class Position(enum.Enum):
    """Where a backend finds its mechanism."""

    OPEN = "open"
    CLOSED = "closed"
    BETWEEN = "between"


@dataclass(frozen=True, slots=True)
class Sensed:
    """One reading of the mechanism: where it is, in words for a fault's reason."""

    position: Position
    where: str


_VERB: Final = {Position.OPEN: "open", Position.CLOSED: "close"}
_STATE: Final = {Position.OPEN: LatchState.OPEN, Position.CLOSED: LatchState.CLOSED}


class Latch(abc.ABC):
    """One connector's latch (see the module docstring). Not thread-safe: one owner polls it.

    ``close()`` closes the latch; :meth:`release` lets go of the device (``with latch:``
    releases it on the way out and leaves the latch where it is).
    """

    def __init__(self, timeout_s: float = DEFAULT_TIMEOUT_S, *, clock: Callable[[], float] = time.monotonic) -> None:
        _check_number("timeout_s", timeout_s, MAX_TIMEOUT_S)
        self.timeout_s = float(timeout_s)
        self._clock = clock
        self._target: Position | None = None
        self._since = 0.0
        self._reached = False
        self._fault: str | None = None

    @property
    def target(self) -> Position | None:
        """The last command's position (None before any)."""
        return self._target

    def open(self) -> None:
        """Start opening (releases the mated pins); clears a fault."""
        self._command(Position.OPEN)

    def close(self) -> None:
        """Start closing (latches the mated pins); clears a fault."""
        self._command(Position.CLOSED)

    def _command(self, target: Position) -> None:
        self._fault = None
        self._reached = False
        self._target = target
        self._since = self._clock()
        try:
            self._drive(target)
        except DriverError as exc:
            self._fault = f"cannot {_VERB[target]}: {exc}"

    def adopt(self, target: Position) -> None:
        """Take ``target`` as commanded, without driving: for a latch found where it is at
        start (a module restarted with its latch closed keeps it closed)."""
        self._fault = None
        self._target = target
        self._since = self._clock()
        self._reached = False

    def state(self) -> LatchStatus:
        if self._fault is not None:
            return LatchStatus(LatchState.FAULT, self._fault)
        target = self._target
        try:
            sensed = self._sense(target)
        except LatchFault as exc:
            return self._fail(str(exc))
        except DriverError as exc:  # a garbled packet is not a jammed latch: asked again, it may answer
            return LatchStatus(LatchState.FAULT, str(exc))
        if target is None:
            if sensed.position is Position.BETWEEN:
                return LatchStatus(LatchState.FAULT, f"{sensed.where}, and neither opened nor closed since start")
            return LatchStatus(_STATE[sensed.position])
        if sensed.position is target:
            self._reached = True
            return LatchStatus(_STATE[target])
        if self._reached:
            return self._fail(f"left {target.value} by itself: {sensed.where}")
        elapsed = self._clock() - self._since
        if elapsed > self.timeout_s:
            return self._fail(f"{_VERB[target]} did not finish in {self.timeout_s:g} s: {sensed.where}")
        return LatchStatus(LatchState.MOVING)

    def _fail(self, reason: str) -> LatchStatus:
        """A fault that stays until the next command; the backend may make it safe first."""
        self._fault = reason
        try:
            self._on_fault()
        except DriverError as exc:
            self._fault = f"{reason}; and then: {exc}"
        return LatchStatus(LatchState.FAULT, self._fault)

    @abc.abstractmethod
    def _drive(self, target: Position) -> None:
        """Drive the actuator toward ``target`` (never blocks for the move)."""

    @abc.abstractmethod
    def _sense(self, target: Position | None) -> Sensed:
        """Where the mechanism is; LatchFault for a fault of the mechanism itself."""

    def _on_fault(self) -> None:
        """Make a faulted latch safe (stop pushing); nothing by default."""
        return None

    def release(self) -> None:
        """Let go of the device; the latch stays where it is (nothing by default)."""
        return None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


class ServoLatch(Latch):
    """A latch driven by a Dynamixel X-series servo at ``dxl_id`` on ``bus``.

    On construction the servo is pinged, put in position mode with limits around its two
    positions and torque on, holding where it is; a latch found within ``tolerance_deg`` of
    open or closed takes that as commanded. :meth:`open` and :meth:`close` write the goal
    (after a REBOOT if the servo has a hardware alert, which leaves torque off until then).
    """

    def __init__(
        self,
        bus: DynamixelBus,
        dxl_id: int,
        open_deg: float,
        closed_deg: float,
        *,
        tolerance_deg: float = DEFAULT_TOLERANCE_DEG,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        stall_s: float = DEFAULT_STALL_S,
        speed_dps: float = DEFAULT_SPEED_DPS,
        expected_model: int | None = None,
        owns_bus: bool = False,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        from drivers.dynamixel import MAX_UNICAST_ID  # a module without a servo latch never loads it

        super().__init__(timeout_s, clock=clock)
        if isinstance(dxl_id, bool) or not isinstance(dxl_id, int) or not 0 <= dxl_id <= MAX_UNICAST_ID:
            raise DriverConfigError(f"latch servo id must be in 0..{MAX_UNICAST_ID}, got {dxl_id!r}")
        for name, value in (("open_deg", open_deg), ("closed_deg", closed_deg)):
            if not (_is_number(value) and -180.0 <= value <= 180.0):
                raise DriverConfigError(f"latch {name} must be a number from -180 to 180 degrees, got {value!r}")
        _check_number("tolerance_deg", tolerance_deg, 90.0)
        _check_number("stall_s", stall_s, MAX_TIMEOUT_S)
        _check_number("speed_dps", speed_dps, 3600.0)
        if abs(closed_deg - open_deg) <= 2 * tolerance_deg:
            raise DriverConfigError(
                f"latch open_deg {open_deg} and closed_deg {closed_deg} must be more than twice "
                f"tolerance_deg ({tolerance_deg}) apart, or one would read as the other"
            )
        self.bus = bus
        self.id = dxl_id
        self.who = f"latch servo id {dxl_id}"
        self.goal_deg = {Position.OPEN: float(open_deg), Position.CLOSED: float(closed_deg)}
        self.tolerance_deg = float(tolerance_deg)
        self.stall_s = float(stall_s)
        self.speed_dps = float(speed_dps)
        self.expected_model = expected_model
        self.owns_bus = owns_bus
        self._progress: tuple[float, float] | None = None  # (degrees, when) of the last movement
        bus.open()
        with bus.lock:
            self._wake()
            found = self._sense(None).position
        if found is not Position.BETWEEN:
            self.adopt(found)

    def _configure(self) -> None:
        low, high = sorted(self.goal_deg.values())
        from drivers.dynamixel import configure_position_servo

        margin = 2 * self.tolerance_deg
        configure_position_servo(
            self.bus, self.id, self.who, (max(-180.0, low - margin), min(180.0, high + margin)), self.speed_dps
        )

    def _wake(self) -> None:
        """A servo that answers, with torque on and no alert (a jammed horn shuts down, and only
        a REBOOT gives it torque again), holding where it is until told otherwise."""
        try:  # every status of a servo in alert carries the alert bit, a PING's too
            self.bus.ping(self.id, self.who, self.expected_model)
            alert = self.bus.read(self.id, self.who, dxt.HARDWARE_ERROR_STATUS) != 0
        except ServoHardwareAlert:
            alert = True
        if alert:
            self.bus.reboot(self.id, self.who)
        if alert or not self.bus.read(self.id, self.who, dxt.TORQUE_ENABLE):
            self._configure()

    def _drive(self, target: Position) -> None:
        with self.bus.lock:
            self._wake()
            self.bus.write(self.id, self.who, dxt.GOAL_POSITION, dxt.deg_to_ticks(self.goal_deg[target]))
        self._progress = None

    def present_deg(self) -> float:
        return dxt.ticks_to_deg(self.bus.read(self.id, self.who, dxt.PRESENT_POSITION))

    def _sense(self, target: Position | None) -> Sensed:
        try:
            deg = self.present_deg()
        except ServoHardwareAlert as exc:
            raise LatchFault(str(exc)) from None
        now = self._clock()
        goals = f"open {self.goal_deg[Position.OPEN]:g}, closed {self.goal_deg[Position.CLOSED]:g}"
        where = f"{self.who} at {deg:.1f} degrees ({goals})"
        for position, goal in self.goal_deg.items():
            if abs(deg - goal) <= self.tolerance_deg:
                self._progress = None
                return Sensed(position, where)
        if target is not None:
            if self._progress is None or abs(deg - self._progress[0]) > self.tolerance_deg / 4:
                self._progress = (deg, now)
            elif now - self._progress[1] > self.stall_s:
                raise LatchFault(f"{_VERB[target]} stalled: {where}, still for {now - self._progress[1]:.2f} s")
        return Sensed(Position.BETWEEN, where)

    def _on_fault(self) -> None:
        """Stop pushing: the goal becomes where the horn is (a jammed servo would overheat)."""
        with self.bus.lock:
            try:
                torque = self.bus.read(self.id, self.who, dxt.TORQUE_ENABLE)
            except ServoHardwareAlert:
                return  # shut down already: no torque until the next command reboots it
            if torque:
                present = self.bus.read(self.id, self.who, dxt.PRESENT_POSITION)
                self.bus.write(self.id, self.who, dxt.GOAL_POSITION, present)

    def release(self) -> None:
        """Close the bus if this latch has it alone (``owns_bus``); a bus shared with the
        module's joints belongs to their driver."""
        if self.owns_bus:
            self.bus.close()


class LatchLines(Protocol):
    """The two calls :class:`GpioLatch` makes: libgpiod v2's ``LineRequest`` has them
    (values are ``gpiod.line.Value``, or anything whose ``bool`` is the level)."""

    def set_value(self, line: int, value: Any) -> None: ...

    def get_value(self, line: int) -> Any: ...


class GpioLatch(Latch):
    """A latch whose actuator one output line drives and whose "closed" switch one input
    line reads, both as logical values (active = drive closed, active = switch closed).

    ``lines`` is what :func:`gpio_lines` returns (active-low lines are configured there), or
    any :class:`LatchLines`. At start the output is driven to match the switch: a latch found
    closed is kept closed, any other is opened.
    """

    def __init__(
        self,
        lines: LatchLines,
        output_line: int,
        input_line: int,
        *,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        active: Any = True,
        inactive: Any = False,
        release: Callable[[], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(timeout_s, clock=clock)
        self.lines = lines
        self.output_line = output_line
        self.input_line = input_line
        self._levels = {Position.CLOSED: active, Position.OPEN: inactive}
        self._release = release
        found = Position.CLOSED if self._switch_closed() else Position.OPEN
        self._drive(found)
        self.adopt(found)

    @classmethod
    def on_chip(
        cls,
        chip: str,
        output_line: int,
        input_line: int,
        *,
        output_active_low: bool = False,
        input_active_low: bool = False,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        consumer: str = "dh2rt-latch",
    ) -> GpioLatch:
        """The latch on two lines of the GPIO character device ``chip`` (libgpiod v2)."""
        gpiod, request = gpio_lines(chip, output_line, input_line, output_active_low, input_active_low, consumer)
        value = gpiod.line.Value
        try:
            return cls(
                request, output_line, input_line, timeout_s=timeout_s,
                active=value.ACTIVE, inactive=value.INACTIVE, release=request.release,
            )  # fmt: skip
        except BaseException:
            request.release()
            raise

    def _switch_closed(self) -> bool:
        try:
            level = self.lines.get_value(self.input_line)
        except OSError as exc:
            raise DriverError(f"latch input line {self.input_line}: {exc.strerror or exc}") from exc
        return bool(level == self._levels[Position.CLOSED])

    def _drive(self, target: Position) -> None:
        try:
            self.lines.set_value(self.output_line, self._levels[target])
        except OSError as exc:
            raise DriverError(f"latch output line {self.output_line}: {exc.strerror or exc}") from exc

    def _sense(self, target: Position | None) -> Sensed:
        closed = self._switch_closed()
        where = f"the closed switch (line {self.input_line}) is {'closed' if closed else 'open'}"
        return Sensed(Position.CLOSED if closed else Position.OPEN, where)

    def release(self) -> None:
        """Release the lines (the kernel then keeps the output where it was, or resets it,
        as the chip's driver does)."""
        if self._release is not None:
            release, self._release = self._release, None
            release()


def load_gpiod() -> ModuleType:
    """libgpiod's Python bindings (v2), or a DriverError that says how to install them."""
    try:
        gpiod = importlib.import_module("gpiod")
    except ImportError as exc:
        raise DriverError("gpiod is not installed; install dh2rt[gpio] to drive a GPIO latch") from exc
    if not hasattr(gpiod, "request_lines"):
        version = getattr(gpiod, "__version__", "?")
        raise DriverError(f"gpiod {version} is libgpiod v1's; a GPIO latch needs v2 (pip install 'gpiod>=2')")
    return gpiod


def gpio_lines(
    chip: str, output_line: int, input_line: int, output_active_low: bool, input_active_low: bool, consumer: str
) -> tuple[ModuleType, Any]:
    """libgpiod and a request for the latch's two lines on ``chip``. The switch is read first,
    alone, so that the output starts where the latch is (active when it is found closed): a
    latch held closed is not let go for an instant when its module restarts."""
    for name, line in (("output_line", output_line), ("input_line", input_line)):
        if isinstance(line, bool) or not isinstance(line, int) or line < 0:
            raise DriverConfigError(f"latch {name} must be a line offset (0 or more), got {line!r}")
    if output_line == input_line:
        raise DriverConfigError(f"latch output_line and input_line must differ, both are {output_line}")
    gpiod = load_gpiod()
    line = gpiod.line
    switch = gpiod.LineSettings(direction=line.Direction.INPUT, active_low=input_active_low)
    try:
        probe = gpiod.request_lines(chip, config={input_line: switch}, consumer=consumer)
        try:
            closed = probe.get_value(input_line) == line.Value.ACTIVE
        finally:
            probe.release()
        start = line.Value.ACTIVE if closed else line.Value.INACTIVE
        drive = gpiod.LineSettings(direction=line.Direction.OUTPUT, active_low=output_active_low, output_value=start)
        return gpiod, gpiod.request_lines(chip, config={output_line: drive, input_line: switch}, consumer=consumer)
    except FileNotFoundError:
        raise DriverError(f"GPIO chip {chip}: no such device") from None
    except (OSError, ValueError) as exc:  # not a GPIO chip, a line it lacks, a line in use
        reason = getattr(exc, "strerror", None) or exc
        raise DriverError(f"GPIO chip {chip}, lines {output_line} and {input_line}: {reason}") from None


def _is_number(value: object) -> bool:
    return not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value)


def _check_number(name: str, value: float, high: float) -> None:
    if not (_is_number(value) and 0 < value <= high):
        raise DriverConfigError(f"latch {name} must be a positive number at most {high:g}, got {value!r}")
