"""A bus of emulated ROBOTIS X-series servos on a pty, for the real dynamixel-sdk to talk to.

:class:`ServoEmulator` owns an ``os.openpty()`` pair (both ends raw) and serves Protocol 2.0
on the master from a background thread; ``emulator.port_path`` is the slave's tty name, the
string to give ``dynamixel_sdk.PortHandler`` (it opens a path, not a pyserial URL). A slave fd
stays open in the emulator for its whole life: the SDK's ``setBaudRate`` closes and reopens the
port, and with no slave open the master would read EIO.

Each servo id has an X-series control table (see :mod:`drivers.dxl_table`) and a pluggable
:class:`JointBackend` that moves the horn: by default a :class:`KinematicJoint` (first-order
servo with a speed limit, advancing in real time), or one joint of any
:class:`drivers.base.ModuleDriver` through :class:`ModuleJointAdapter` (DOF1 and DOF2 of one
module on two ids), e.g. the PyBullet stand-in. Backends are called from the emulator's thread.

Behaviour modelled on the X-series e-Manual: PING (and broadcast PING, one status per servo in
id order), READ, WRITE, REG_WRITE/ACTION, SYNC_READ (replies in the order the ids are listed),
SYNC_WRITE, REBOOT (status first, then silent for ``reboot_time_s`` with RAM back to defaults).
EEPROM (addresses < 64) is writable only with torque off; read-only fields give an access
error; a goal outside the position limits gives a data-limit error and is not applied; enabling
torque sets Goal Position to Present Position; Status Return Level (68) is honoured; a packet
with a bad CRC addressed to a servo is answered with a CRC-error status.

Fault injection (per id, switchable at run time, see :class:`Fault`): ``NO_REPLY`` (the servo
is absent: it neither answers nor acts), ``CRC_ERROR`` (acts, but its replies carry a corrupted
CRC), ``HARDWARE_ALERT`` (Hardware Error Status bits set, alert bit 0x80 in every status, torque
forced off until REBOOT or clearing), ``WRONG_MODEL`` (reports another model number).
"""

from __future__ import annotations

import enum
import errno
import math
import os
import select
import threading
import time
import tty
from collections.abc import Callable, Iterable, Mapping
from typing import Protocol

from dh2rt.errors import EmulatorError
from drivers import dxl_table as dxt
from drivers.base import Joint, ModuleDriver
from hil.dxl_protocol import (
    BROADCAST_ID,
    MAX_ID,
    CorruptPacket,
    Instruction,
    Packet,
    PacketParser,
    encode_status,
)


class Fault(enum.Enum):
    """Faults the emulator can inject into one servo id."""

    NO_REPLY = "no_reply"
    CRC_ERROR = "crc_error"
    HARDWARE_ALERT = "hardware_alert"
    WRONG_MODEL = "wrong_model"


class JointBackend(Protocol):
    """What moves one servo's horn. Positions are ticks (4096/rev, 2048 = 0 degrees)."""

    def set_goal_ticks(self, ticks: float) -> None:
        """New goal position; called only while torque is on."""

    def present_ticks(self) -> float:
        """Where the horn is now."""

    def set_torque(self, enabled: bool) -> None:
        """Torque on (hold and move to the goal) or off (limp)."""

    def set_speed_limit(self, ticks_per_s: float) -> None:
        """Largest speed the horn may move at."""


DEFAULT_SPEED_TPS = dxt.velocity_units_to_dps(200) / dxt.DEG_PER_TICK  # X-series velocity limit 200


class KinematicJoint:
    """First-order servo with a speed limit, advancing in real time (no load, no gravity).

    The horn approaches the goal exponentially with ``time_constant_s`` but never faster than the
    speed limit; with torque off it stays where it is.
    """

    def __init__(
        self,
        start_ticks: float = dxt.CENTER_TICKS,
        speed_limit_tps: float = DEFAULT_SPEED_TPS,
        time_constant_s: float = 0.02,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if time_constant_s <= 0 or speed_limit_tps <= 0:
            raise EmulatorError(
                f"time_constant_s and speed_limit_tps must be > 0, got {time_constant_s}, {speed_limit_tps}"
            )
        self._clock = clock
        self._t = clock()
        self.position = float(start_ticks)
        self.goal = float(start_ticks)
        self.torque = False
        self.speed_limit_tps = speed_limit_tps
        self.time_constant_s = time_constant_s

    def _advance(self) -> None:
        now = self._clock()
        dt, self._t = now - self._t, now
        if not self.torque or dt <= 0:
            return
        err = self.goal - self.position
        vmax, tau = self.speed_limit_tps, self.time_constant_s
        # Saturated (speed-limited) phase while |err|/tau > vmax, then exponential decay.
        t_sat = max(0.0, (abs(err) - vmax * tau) / vmax)
        step = math.copysign(vmax * min(dt, t_sat), err)
        self.position += step
        err -= step
        if dt > t_sat:
            err *= math.exp(-(dt - t_sat) / tau)
        self.position = self.goal - err

    def set_goal_ticks(self, ticks: float) -> None:
        self._advance()
        self.goal = float(ticks)

    def present_ticks(self) -> float:
        self._advance()
        return self.position

    def set_torque(self, enabled: bool) -> None:
        self._advance()
        self.torque = enabled
        if enabled:
            self.goal = self.position

    def set_speed_limit(self, ticks_per_s: float) -> None:
        self._advance()
        self.speed_limit_tps = max(ticks_per_s, 1e-6)


class ModuleJointAdapter:
    """Expose a :class:`ModuleDriver`'s two joints as two :class:`JointBackend` objects.

    The driver has one torque switch for both joints, so torque is on while either emulated
    servo has it on. The driver's own limits (angles, speed) govern motion, so the speed limit
    from the control table is not forwarded.
    """

    def __init__(self, driver: ModuleDriver) -> None:
        self.driver = driver
        self._goals = list(driver.read_positions())
        self._torque = [False, False]
        driver.set_torque(False)

    def joint(self, joint: Joint) -> JointBackend:
        return _AdaptedJoint(self, joint)

    def _set_goal(self, joint: Joint, deg: float) -> None:
        self._goals[joint] = deg
        self.driver.set_targets(self._goals[0], self._goals[1])

    def _set_torque(self, joint: Joint, enabled: bool) -> None:
        self._torque[joint] = enabled
        if enabled:
            # Torque on holds where the horn is: as the servo does, the goal becomes the present.
            self._goals[joint] = self.driver.read_positions()[joint]
            self.driver.set_targets(self._goals[0], self._goals[1])
        self.driver.set_torque(any(self._torque))


class _AdaptedJoint:
    def __init__(self, adapter: ModuleJointAdapter, joint: Joint) -> None:
        self._adapter = adapter
        self._joint = joint

    def set_goal_ticks(self, ticks: float) -> None:
        self._adapter._set_goal(self._joint, dxt.ticks_to_deg(ticks))

    def present_ticks(self) -> float:
        deg = self._adapter.driver.read_positions()[self._joint]
        return dxt.CENTER_TICKS + deg / dxt.DEG_PER_TICK

    def set_torque(self, enabled: bool) -> None:
        self._adapter._set_torque(self._joint, enabled)

    def set_speed_limit(self, ticks_per_s: float) -> None:
        pass


def _field_at(address: int) -> dxt.Field | None:
    for f in dxt.FIELDS:
        if f.address <= address < f.end:
            return f
    return None


_READ_ONLY = frozenset(a for f in dxt.FIELDS if not f.writable for a in range(f.address, f.end))


class EmulatedServo:
    """One servo: its control table, its joint backend and its injected faults."""

    def __init__(
        self,
        dxl_id: int,
        backend: JointBackend,
        model_number: int = dxt.MODEL_XM430_W350,
        firmware_version: int = 48,
        operating_mode: int = dxt.MODE_POSITION,
    ) -> None:
        self.id = dxl_id
        self.backend = backend
        self.model_number = model_number
        self.firmware_version = firmware_version
        self.table = bytearray(dxt.TABLE_SIZE)
        self.faults: set[Fault] = set()
        self.wrong_model = dxt.MODEL_XL430_W250
        self.alert_bits = dxt.HW_OVERLOAD
        self.pending_write: tuple[int, bytes] | None = None
        self.silent_until = 0.0
        self._last_sample: tuple[float, float] | None = None
        self._velocity_units = 0
        self._init_eeprom(operating_mode)
        self._init_ram()

    # -- register access (no access rules; the protocol handler applies them) --

    def get(self, field: dxt.Field) -> int:
        """A field's value as the host would read it (live fields refreshed)."""
        self._refresh(field.address, field.size)
        return _value(self.table, field)

    def put(self, field: dxt.Field, value: int) -> None:
        """Store a field's raw value (a test backdoor: no side effects, no access rules)."""
        self.table[field.address : field.end] = value.to_bytes(field.size, "little", signed=field.signed)

    def _init_eeprom(self, operating_mode: int) -> None:
        for field, value in (
            (dxt.MODEL_NUMBER, self.model_number),
            (dxt.FIRMWARE_VERSION, self.firmware_version),
            (dxt.ID, self.id),
            (dxt.BAUD_RATE, 3),  # 1 Mbps
            (dxt.RETURN_DELAY_TIME, 250),
            (dxt.OPERATING_MODE, operating_mode),
            (dxt.PROTOCOL_TYPE, 2),
            (dxt.MOVING_THRESHOLD, 10),
            (dxt.TEMPERATURE_LIMIT, 80),
            (dxt.MAX_VOLTAGE_LIMIT, 160),
            (dxt.MIN_VOLTAGE_LIMIT, 95),
            (dxt.PWM_LIMIT, 885),
            (dxt.CURRENT_LIMIT, 1193),
            (dxt.VELOCITY_LIMIT, 200),
            (dxt.MAX_POSITION_LIMIT, dxt.MAX_TICKS),
            (dxt.MIN_POSITION_LIMIT, 0),
            (dxt.SHUTDOWN, dxt.HW_OVERHEATING | dxt.HW_ELECTRICAL_SHOCK | dxt.HW_OVERLOAD),
        ):
            self.put(field, value)

    def _init_ram(self) -> None:
        """RAM as after power-up or REBOOT: torque off, goal = present, errors cleared."""
        self.table[dxt.EEPROM_END :] = bytes(dxt.TABLE_SIZE - dxt.EEPROM_END)
        self.backend.set_torque(False)
        self._apply_speed_limit()
        self.put(dxt.STATUS_RETURN_LEVEL, 2)
        self.put(dxt.POSITION_P_GAIN, 800)
        self.put(dxt.PRESENT_INPUT_VOLTAGE, 120)
        self.put(dxt.PRESENT_TEMPERATURE, 36)
        self.put(dxt.GOAL_POSITION, round(self.backend.present_ticks()))
        self.pending_write = None
        self.faults.discard(Fault.HARDWARE_ALERT)

    def _apply_speed_limit(self) -> None:
        units = self.get(dxt.PROFILE_VELOCITY) or self.get(dxt.VELOCITY_LIMIT)
        self.backend.set_speed_limit(dxt.velocity_units_to_dps(units) / dxt.DEG_PER_TICK)

    @property
    def torque_on(self) -> bool:
        return bool(self.table[dxt.TORQUE_ENABLE.address])

    def _refresh(self, address: int, length: int) -> None:
        """Bring the live registers in [address, address+length) up to date."""
        end = address + length

        def wanted(f: dxt.Field) -> bool:
            return f.address < end and address < f.end

        model = self.wrong_model if Fault.WRONG_MODEL in self.faults else self.model_number
        self.put(dxt.MODEL_NUMBER, model)
        alert = Fault.HARDWARE_ALERT in self.faults
        self.put(dxt.HARDWARE_ERROR_STATUS, self.alert_bits if alert else 0)
        self.put(dxt.REALTIME_TICK, int(time.monotonic() * 1000) % 32768)
        if any(wanted(f) for f in (dxt.PRESENT_POSITION, dxt.PRESENT_VELOCITY, dxt.MOVING)):
            now, ticks = time.monotonic(), self.backend.present_ticks()
            if self._last_sample is not None and now - self._last_sample[1] > 1e-3:
                tps = (ticks - self._last_sample[0]) / (now - self._last_sample[1])
                self._velocity_units = round(tps * dxt.DEG_PER_TICK / 6 / dxt.RPM_PER_VELOCITY_UNIT)
            self._last_sample = (ticks, now)
            self.put(dxt.PRESENT_POSITION, round(ticks))
            self.put(dxt.PRESENT_VELOCITY, self._velocity_units)
            moving = abs(self.get_raw(dxt.GOAL_POSITION) - ticks) > self.get_raw(dxt.MOVING_THRESHOLD)
            self.put(dxt.MOVING, int(moving and self.torque_on))

    def get_raw(self, field: dxt.Field) -> int:
        """A field's stored value, without refreshing live registers."""
        return _value(self.table, field)

    # -- the protocol-facing operations; each returns an error number (0 = fine) --

    def read(self, address: int, length: int) -> tuple[int, bytes]:
        if length < 0 or address < 0 or address + length > dxt.TABLE_SIZE:
            return dxt.ERRNUM_ACCESS, b""
        self._refresh(address, length)
        return 0, bytes(self.table[address : address + length])

    def write(self, address: int, data: bytes) -> int:
        end = address + len(data)
        if not data or address < 0 or end > dxt.TABLE_SIZE:
            return dxt.ERRNUM_ACCESS
        if any(a in _READ_ONLY for a in range(address, end)):
            return dxt.ERRNUM_ACCESS
        if address < dxt.EEPROM_END and self.torque_on:
            return dxt.ERRNUM_ACCESS  # EEPROM is locked while torque is on
        staged = bytearray(self.table)
        staged[address:end] = data
        goal = _value(staged, dxt.GOAL_POSITION)
        writes_goal = address < dxt.GOAL_POSITION.end and dxt.GOAL_POSITION.address < end
        mode = _value(staged, dxt.OPERATING_MODE)
        low, high = _value(staged, dxt.MIN_POSITION_LIMIT), _value(staged, dxt.MAX_POSITION_LIMIT)
        if writes_goal and mode == dxt.MODE_POSITION and not low <= goal <= high:
            return dxt.ERRNUM_DATA_LIMIT
        was_on = self.torque_on
        self.table[address:end] = data
        touched = {f for a in range(address, end) if (f := _field_at(a)) is not None}
        if dxt.TORQUE_ENABLE in touched:
            self._torque_changed(was_on)
        if dxt.PROFILE_VELOCITY in touched or dxt.VELOCITY_LIMIT in touched:
            self._apply_speed_limit()
        if dxt.GOAL_POSITION in touched and self.torque_on and mode in (dxt.MODE_POSITION, dxt.MODE_EXTENDED_POSITION):
            self.backend.set_goal_ticks(goal)
        return 0

    def _torque_changed(self, was_on: bool) -> None:
        if Fault.HARDWARE_ALERT in self.faults:
            # Shutdown: torque stays off until the servo is rebooted.
            self.table[dxt.TORQUE_ENABLE.address] = 0
        on = self.torque_on
        if on and not was_on:
            self.put(dxt.GOAL_POSITION, round(self.backend.present_ticks()))
        if on != was_on:
            self.backend.set_torque(on)

    def raise_alert(self, bits: int) -> None:
        self.alert_bits = bits
        self.faults.add(Fault.HARDWARE_ALERT)
        self.table[dxt.TORQUE_ENABLE.address] = 0
        self.backend.set_torque(False)

    def reboot(self, silent_for_s: float) -> None:
        self._init_ram()
        self.silent_until = time.monotonic() + silent_for_s

    @property
    def error_byte(self) -> int:
        return dxt.ERRBIT_ALERT if Fault.HARDWARE_ALERT in self.faults else 0


BackendSpec = Mapping[int, JointBackend] | Iterable[int]


class ServoEmulator:
    """Servos on a pty, served from a background thread. A context manager (starts, stops).

    ``servos`` maps ids to joint backends, or lists ids that each get a :class:`KinematicJoint`.
    ``reply_delay_s`` is the delay before each status packet; ``None`` honours each servo's
    Return Delay Time register (2 us units, factory 250 = 500 us); the default 0 keeps tests fast.
    """

    def __init__(
        self,
        servos: BackendSpec = (1, 2),
        *,
        model_number: int = dxt.MODEL_XM430_W350,
        firmware_version: int = 48,
        operating_mode: int = dxt.MODE_POSITION,
        reply_delay_s: float | None = 0.0,
        reboot_time_s: float = 0.05,
    ) -> None:
        backends: dict[int, JointBackend] = (
            dict(servos) if isinstance(servos, Mapping) else {i: KinematicJoint() for i in servos}
        )
        if not backends:
            raise EmulatorError("a servo bus needs at least one servo id")
        for dxl_id in backends:
            if not isinstance(dxl_id, int) or not 0 <= dxl_id <= MAX_ID:
                raise EmulatorError(f"servo id must be an integer in 0..{MAX_ID}, got {dxl_id!r}")
        self._servos = {
            i: EmulatedServo(i, b, model_number, firmware_version, operating_mode) for i, b in sorted(backends.items())
        }
        self.reply_delay_s = reply_delay_s
        self.reboot_time_s = reboot_time_s
        self.parser = PacketParser()
        self.packets_received = 0
        self.replies_sent = 0
        self.replies_dropped = 0
        self._lock = threading.RLock()
        self._thread: threading.Thread | None = None
        self._stopped = False
        self._master, self._slave = os.openpty()
        tty.setraw(self._master)
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)  # a full pty drops replies, never hangs the thread
        self.port_path = os.ttyname(self._slave)
        self._wake_r, self._wake_w = os.pipe()
        self.error: BaseException | None = None

    @classmethod
    def for_module(cls, driver: ModuleDriver, dof1_id: int = 1, dof2_id: int = 2, **kwargs: object) -> ServoEmulator:
        """One module on two ids: DOF1 and DOF2 of ``driver`` (e.g. the PyBullet stand-in)."""
        adapter = ModuleJointAdapter(driver)
        servos = {dof1_id: adapter.joint(Joint.DOF1), dof2_id: adapter.joint(Joint.DOF2)}
        return cls(servos, **kwargs)  # type: ignore[arg-type]

    # -- servos and faults --

    @property
    def ids(self) -> tuple[int, ...]:
        with self._lock:
            return tuple(sorted(self._servos))

    def servo(self, dxl_id: int) -> EmulatedServo:
        with self._lock:
            try:
                return self._servos[dxl_id]
            except KeyError:
                raise EmulatorError(f"no servo with id {dxl_id} on this bus (ids: {sorted(self._servos)})") from None

    def set_fault(
        self,
        dxl_id: int,
        fault: Fault | str,
        active: bool = True,
        *,
        hardware_bits: int = dxt.HW_OVERLOAD,
        model_number: int = dxt.MODEL_XL430_W250,
    ) -> None:
        """Switch ``fault`` on (or off) for one id. ``hardware_bits`` and ``model_number`` say
        what ``HARDWARE_ALERT`` and ``WRONG_MODEL`` report."""
        try:
            fault = Fault(fault)
        except ValueError:
            raise EmulatorError(f"unknown fault {fault!r}; one of {[f.value for f in Fault]}") from None
        with self._lock:
            servo = self.servo(dxl_id)
            if not active:
                servo.faults.discard(fault)
            elif fault is Fault.HARDWARE_ALERT:
                servo.raise_alert(hardware_bits)
            else:
                if fault is Fault.WRONG_MODEL:
                    servo.wrong_model = model_number
                servo.faults.add(fault)

    def clear_faults(self, dxl_id: int | None = None) -> None:
        """Clear every fault of one id, or of every servo."""
        with self._lock:
            for i in self.ids if dxl_id is None else (dxl_id,):
                self.servo(i).faults.clear()

    def faults(self, dxl_id: int) -> frozenset[Fault]:
        with self._lock:
            return frozenset(self.servo(dxl_id).faults)

    # -- the sans-IO core: one received event in, status packets out --

    def handle(self, event: Packet | CorruptPacket) -> list[tuple[EmulatedServo, bytes]]:
        """Act on one received packet; return the status packets to send, in order."""
        with self._lock:
            self.packets_received += 1
            now = time.monotonic()
            live = {i: s for i, s in self._servos.items() if Fault.NO_REPLY not in s.faults and now >= s.silent_until}
            if isinstance(event, CorruptPacket):
                servo = live.get(event.id)
                return self._status(servo, dxt.ERRNUM_CRC) if servo else []
            if event.is_status:
                return []  # another device's reply on the shared bus
            if event.id == BROADCAST_ID:
                replies = self._broadcast(event, live)
            else:
                servo = live.get(event.id)
                replies = self._unicast(servo, event) if servo else []
            self._follow_id_changes()
            return replies

    def _follow_id_changes(self) -> None:
        # A write to the ID register (7) moves the servo to its new id, as on a real bus.
        for old, servo in list(self._servos.items()):
            new = servo.table[dxt.ID.address]
            if new != old:
                del self._servos[old]
                servo.id = new
                self._servos[new] = servo

    def _status(
        self, servo: EmulatedServo, error: int, data: bytes = b"", *, kind: int = 2
    ) -> list[tuple[EmulatedServo, bytes]]:
        # Status Return Level: 0 answers PING only, 1 also READ, 2 everything. kind 0/1/2.
        if kind > servo.table[dxt.STATUS_RETURN_LEVEL.address]:
            return []
        packet = encode_status(servo.id, error | servo.error_byte, data)
        if Fault.CRC_ERROR in servo.faults:
            packet = packet[:-1] + bytes((packet[-1] ^ 0xA5,))
        return [(servo, packet)]

    def _ping_reply(self, servo: EmulatedServo) -> list[tuple[EmulatedServo, bytes]]:
        data = servo.get(dxt.MODEL_NUMBER).to_bytes(2, "little") + bytes((servo.firmware_version,))
        return self._status(servo, 0, data, kind=0)

    def _unicast(self, servo: EmulatedServo, p: Packet) -> list[tuple[EmulatedServo, bytes]]:
        inst, params = p.instruction, p.params
        if inst == Instruction.PING:
            return self._ping_reply(servo)
        if inst == Instruction.READ:
            if len(params) != 4:
                return self._status(servo, dxt.ERRNUM_DATA_LENGTH, kind=1)
            address, length = _u16(params, 0), _u16(params, 2)
            err, data = servo.read(address, length)
            return self._status(servo, err, data, kind=1)
        if inst in (Instruction.WRITE, Instruction.REG_WRITE):
            if len(params) < 3:
                return self._status(servo, dxt.ERRNUM_DATA_LENGTH)
            address, data = _u16(params, 0), bytes(params[2:])
            if inst == Instruction.WRITE:
                return self._status(servo, servo.write(address, data))
            servo.pending_write = (address, data)
            servo.table[dxt.REGISTERED_INSTRUCTION.address] = 1
            return self._status(servo, 0)
        if inst == Instruction.ACTION:
            return self._status(servo, self._action(servo))
        if inst == Instruction.REBOOT:
            reply = self._status(servo, 0)
            servo.reboot(self.reboot_time_s)
            return reply
        return self._status(servo, dxt.ERRNUM_INSTRUCTION)

    @staticmethod
    def _action(servo: EmulatedServo) -> int:
        if servo.pending_write is None:
            return dxt.ERRNUM_RESULT_FAIL
        address, data = servo.pending_write
        servo.pending_write = None
        servo.table[dxt.REGISTERED_INSTRUCTION.address] = 0
        return servo.write(address, data)

    def _broadcast(self, p: Packet, live: dict[int, EmulatedServo]) -> list[tuple[EmulatedServo, bytes]]:
        inst, params = p.instruction, p.params
        replies: list[tuple[EmulatedServo, bytes]] = []
        if inst == Instruction.PING:
            for i in sorted(live):
                replies += self._ping_reply(live[i])
        elif inst == Instruction.SYNC_READ and len(params) >= 4:
            address, length = _u16(params, 0), _u16(params, 2)
            for i in params[4:]:
                if i in live:
                    err, data = live[i].read(address, length)
                    replies += self._status(live[i], err, data, kind=1)
        elif inst == Instruction.SYNC_WRITE and len(params) >= 4:
            address, length = _u16(params, 0), _u16(params, 2)
            body = params[4:]
            if length and len(body) % (length + 1) == 0:
                for k in range(0, len(body), length + 1):
                    servo = live.get(body[k])
                    if servo is not None:
                        servo.write(address, bytes(body[k + 1 : k + 1 + length]))
        elif inst == Instruction.ACTION:
            for servo in live.values():
                self._action(servo)
        elif inst in (Instruction.WRITE, Instruction.REG_WRITE) and len(params) >= 3:
            for servo in live.values():
                if inst == Instruction.WRITE:
                    servo.write(_u16(params, 0), bytes(params[2:]))
                else:
                    servo.pending_write = (_u16(params, 0), bytes(params[2:]))
        return replies

    # -- the I/O shell --

    def start(self) -> ServoEmulator:
        if self._stopped:
            raise EmulatorError("a stopped ServoEmulator cannot be restarted; make a new one")
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="dxl-emulator", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close every fd. Idempotent."""
        if self._stopped:
            return
        self._stopped = True
        if self._thread is not None:
            os.write(self._wake_w, b"x")
            self._thread.join(timeout=5)
        for fd in (self._master, self._slave, self._wake_r, self._wake_w):
            os.close(fd)

    close = stop

    def __enter__(self) -> ServoEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        try:
            while True:
                ready, _, _ = select.select([self._master, self._wake_r], [], [])
                if self._wake_r in ready:
                    return
                try:
                    data = os.read(self._master, 4096)
                except BlockingIOError:
                    continue
                except OSError as exc:
                    if exc.errno != errno.EIO:
                        raise
                    time.sleep(0.001)  # no slave open right now; we keep one, so rare
                    continue
                for event in self.parser.feed(data):
                    for servo, reply in self.handle(event):
                        self._send(servo, reply)
        except BaseException as exc:  # kept for the owner to inspect; the thread must not die loud
            self.error = exc

    def _send(self, servo: EmulatedServo, reply: bytes) -> None:
        delay = self.reply_delay_s
        if delay is None:
            delay = servo.table[dxt.RETURN_DELAY_TIME.address] * 2e-6
        if delay > 0:
            time.sleep(delay)
        try:
            os.write(self._master, reply)
            self.replies_sent += 1
        except BlockingIOError:
            self.replies_dropped += 1


def _value(table: bytes | bytearray, field: dxt.Field) -> int:
    return int.from_bytes(table[field.address : field.end], "little", signed=field.signed)


def _u16(buf: bytes, offset: int) -> int:
    return buf[offset] | (buf[offset + 1] << 8)
