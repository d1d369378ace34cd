"""One emulated ROBOTIS X-series servo: its control table and what it does with each
instruction (PING, READ, WRITE, REG_WRITE/ACTION, REBOOT, sync read and write), with the
e-Manual's rules (EEPROM writable only with torque off, read-only fields, position limits,
Status Return Level) and switchable faults (:class:`Fault`). No I/O: the bus
(:mod:`hil.servo_emulator`) hands it packets and sends what it answers.
"""

from __future__ import annotations

import enum
import time

from drivers import dxl_table as dxt
from hil.servo_joints import JointBackend


class Fault(enum.Enum):
    """Faults the emulator can inject into one servo id."""

    NO_REPLY = "no_reply"
    CRC_ERROR = "crc_error"
    HARDWARE_ALERT = "hardware_alert"
    WRONG_MODEL = "wrong_model"


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
        if wanted(dxt.PRESENT_LOAD):
            percent = self.backend.present_load_percent() if self.torque_on else 0.0
            self.put(dxt.PRESENT_LOAD, dxt.load_raw(percent, self.model_number, self.get_raw(dxt.CURRENT_LIMIT)))

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


def _value(table: bytes | bytearray, field: dxt.Field) -> int:
    return int.from_bytes(table[field.address : field.end], "little", signed=field.signed)


def u16(buf: bytes, offset: int) -> int:
    return buf[offset] | (buf[offset + 1] << 8)
