"""The ROBOTIS X-series (Protocol 2.0) control table subset dh2rt uses, and angle conversions.

Addresses and sizes follow the XM430-W350 e-Manual; the EEPROM area (addresses below 64) can be
written only while torque is off. Positions are in ticks: 4096 per revolution, and dh2rt puts
0 degrees at tick 2048 (the horn's centre), so -180..+180 degrees maps to 0..4096.

Pure data and arithmetic: no vendor SDK import here, so both the driver and the emulator use it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final


@dataclass(frozen=True, slots=True)
class Field:
    """One control-table entry: address, size in bytes, and whether the host may write it."""

    name: str
    address: int
    size: int
    writable: bool = True
    signed: bool = False

    @property
    def end(self) -> int:
        return self.address + self.size


# --- EEPROM (persisted; writable only with torque off) ---
MODEL_NUMBER: Final = Field("model_number", 0, 2, writable=False)
MODEL_INFORMATION: Final = Field("model_information", 2, 4, writable=False)
FIRMWARE_VERSION: Final = Field("firmware_version", 6, 1, writable=False)
ID: Final = Field("id", 7, 1)
BAUD_RATE: Final = Field("baud_rate", 8, 1)
RETURN_DELAY_TIME: Final = Field("return_delay_time", 9, 1)  # units of 2 microseconds
DRIVE_MODE: Final = Field("drive_mode", 10, 1)
OPERATING_MODE: Final = Field("operating_mode", 11, 1)
SECONDARY_ID: Final = Field("secondary_id", 12, 1)
PROTOCOL_TYPE: Final = Field("protocol_type", 13, 1)
HOMING_OFFSET: Final = Field("homing_offset", 20, 4, signed=True)
MOVING_THRESHOLD: Final = Field("moving_threshold", 24, 4)
TEMPERATURE_LIMIT: Final = Field("temperature_limit", 31, 1)
MAX_VOLTAGE_LIMIT: Final = Field("max_voltage_limit", 32, 2)
MIN_VOLTAGE_LIMIT: Final = Field("min_voltage_limit", 34, 2)
PWM_LIMIT: Final = Field("pwm_limit", 36, 2)
CURRENT_LIMIT: Final = Field("current_limit", 38, 2)
VELOCITY_LIMIT: Final = Field("velocity_limit", 44, 4)
MAX_POSITION_LIMIT: Final = Field("max_position_limit", 48, 4)
MIN_POSITION_LIMIT: Final = Field("min_position_limit", 52, 4)
SHUTDOWN: Final = Field("shutdown", 63, 1)

EEPROM_END: Final = 64  # first RAM address

# --- RAM (reset on power-up and REBOOT) ---
TORQUE_ENABLE: Final = Field("torque_enable", 64, 1)
LED: Final = Field("led", 65, 1)
STATUS_RETURN_LEVEL: Final = Field("status_return_level", 68, 1)
REGISTERED_INSTRUCTION: Final = Field("registered_instruction", 69, 1, writable=False)
HARDWARE_ERROR_STATUS: Final = Field("hardware_error_status", 70, 1, writable=False)
POSITION_P_GAIN: Final = Field("position_p_gain", 84, 2)
GOAL_VELOCITY: Final = Field("goal_velocity", 104, 4, signed=True)
PROFILE_ACCELERATION: Final = Field("profile_acceleration", 108, 4)
PROFILE_VELOCITY: Final = Field("profile_velocity", 112, 4)  # units of 0.229 rev/min
GOAL_POSITION: Final = Field("goal_position", 116, 4, signed=True)
REALTIME_TICK: Final = Field("realtime_tick", 120, 2, writable=False)
MOVING: Final = Field("moving", 122, 1, writable=False)
MOVING_STATUS: Final = Field("moving_status", 123, 1, writable=False)
#: Present Load (0.1 % of the maximum torque) on the models in PRESENT_LOAD_MODELS; on the
#: others (the XM430 this table follows among them) Present Current, in the units of their
#: Current Limit (38): :func:`load_percent` reads either.
PRESENT_LOAD: Final = Field("present_load", 126, 2, writable=False, signed=True)
PRESENT_VELOCITY: Final = Field("present_velocity", 128, 4, writable=False, signed=True)
PRESENT_POSITION: Final = Field("present_position", 132, 4, writable=False, signed=True)
PRESENT_INPUT_VOLTAGE: Final = Field("present_input_voltage", 144, 2, writable=False)  # 0.1 V
PRESENT_TEMPERATURE: Final = Field("present_temperature", 146, 1, writable=False)  # deg C

TABLE_SIZE: Final = 147  # one past Present Temperature; the emulator models this much

FIELDS: Final[tuple[Field, ...]] = (
    MODEL_NUMBER,
    MODEL_INFORMATION,
    FIRMWARE_VERSION,
    ID,
    BAUD_RATE,
    RETURN_DELAY_TIME,
    DRIVE_MODE,
    OPERATING_MODE,
    SECONDARY_ID,
    PROTOCOL_TYPE,
    HOMING_OFFSET,
    MOVING_THRESHOLD,
    TEMPERATURE_LIMIT,
    MAX_VOLTAGE_LIMIT,
    MIN_VOLTAGE_LIMIT,
    PWM_LIMIT,
    CURRENT_LIMIT,
    VELOCITY_LIMIT,
    MAX_POSITION_LIMIT,
    MIN_POSITION_LIMIT,
    SHUTDOWN,
    TORQUE_ENABLE,
    LED,
    STATUS_RETURN_LEVEL,
    REGISTERED_INSTRUCTION,
    HARDWARE_ERROR_STATUS,
    POSITION_P_GAIN,
    GOAL_VELOCITY,
    PROFILE_ACCELERATION,
    PROFILE_VELOCITY,
    GOAL_POSITION,
    REALTIME_TICK,
    MOVING,
    MOVING_STATUS,
    PRESENT_LOAD,
    PRESENT_VELOCITY,
    PRESENT_POSITION,
    PRESENT_INPUT_VOLTAGE,
    PRESENT_TEMPERATURE,
)

# Operating modes (address 11).
MODE_CURRENT: Final = 0
MODE_VELOCITY: Final = 1
MODE_POSITION: Final = 3
MODE_EXTENDED_POSITION: Final = 4
MODE_PWM: Final = 16

# Model numbers (address 0) of common X-series servos.
MODEL_XM430_W350: Final = 1020
MODEL_XM430_W210: Final = 1030
MODEL_XH430_W350: Final = 1010
MODEL_XL430_W250: Final = 1060
MODEL_XM540_W270: Final = 1120
MODEL_NAMES: Final[dict[int, str]] = {
    MODEL_XM430_W350: "XM430-W350",
    MODEL_XM430_W210: "XM430-W210",
    MODEL_XH430_W350: "XH430-W350",
    MODEL_XL430_W250: "XL430-W250",
    MODEL_XM540_W270: "XM540-W270",
}

# Hardware Error Status bits (address 70). The status packet's error byte carries ERRBIT_ALERT
# whenever any of these is set; the register says which.
HW_INPUT_VOLTAGE: Final = 0x01
HW_OVERHEATING: Final = 0x04
HW_MOTOR_ENCODER: Final = 0x08
HW_ELECTRICAL_SHOCK: Final = 0x10
HW_OVERLOAD: Final = 0x20
HARDWARE_ERROR_NAMES: Final[dict[int, str]] = {
    HW_INPUT_VOLTAGE: "input voltage",
    HW_OVERHEATING: "overheating",
    HW_MOTOR_ENCODER: "motor encoder",
    HW_ELECTRICAL_SHOCK: "electrical shock",
    HW_OVERLOAD: "overload",
}
ERRBIT_ALERT: Final = 0x80

# Status packet error numbers (low 7 bits of the error byte).
ERRNUM_RESULT_FAIL: Final = 1
ERRNUM_INSTRUCTION: Final = 2
ERRNUM_CRC: Final = 3
ERRNUM_DATA_RANGE: Final = 4
ERRNUM_DATA_LENGTH: Final = 5
ERRNUM_DATA_LIMIT: Final = 6
ERRNUM_ACCESS: Final = 7
ERROR_NUMBER_NAMES: Final[dict[int, str]] = {
    ERRNUM_RESULT_FAIL: "result fail",
    ERRNUM_INSTRUCTION: "instruction error",
    ERRNUM_CRC: "CRC error",
    ERRNUM_DATA_RANGE: "data range error",
    ERRNUM_DATA_LENGTH: "data length error",
    ERRNUM_DATA_LIMIT: "data limit error",
    ERRNUM_ACCESS: "access error",
}

TICKS_PER_REV: Final = 4096
CENTER_TICKS: Final = 2048  # 0 degrees
MAX_TICKS: Final = TICKS_PER_REV - 1
DEG_PER_TICK: Final = 360.0 / TICKS_PER_REV
RPM_PER_VELOCITY_UNIT: Final = 0.229  # Profile/Present Velocity unit


#: Models whose address 126 is Present Load (0.1 % units, -1000..1000) rather than Present Current.
PRESENT_LOAD_MODELS: Final = frozenset({MODEL_XL430_W250})
LOAD_UNIT_PERCENT: Final = 0.1


def load_percent(raw: int, model: int, current_limit: int) -> float:
    """Address 126 of a servo of ``model`` as a load in percent of its maximum (signed):
    Present Load in 0.1 % units, or Present Current over the Current Limit (same units)."""
    if model in PRESENT_LOAD_MODELS:
        return raw * LOAD_UNIT_PERCENT
    return 100.0 * raw / max(1, current_limit)


def load_raw(percent: float, model: int, current_limit: int) -> int:
    """The value address 126 holds for a load of ``percent`` (the inverse of :func:`load_percent`)."""
    if model in PRESENT_LOAD_MODELS:
        return round(max(-100.0, min(100.0, percent)) / LOAD_UNIT_PERCENT)
    return round(max(-1.0, min(1.0, percent / 100.0)) * current_limit)


def hardware_error_names(bits: int) -> list[str]:
    """Names of the Hardware Error Status bits set in ``bits`` (unknown bits by number)."""
    names = [name for bit, name in HARDWARE_ERROR_NAMES.items() if bits & bit]
    unknown = bits & ~sum(HARDWARE_ERROR_NAMES) & 0xFF
    names.extend(f"bit 0x{1 << i:02x}" for i in range(8) if unknown & (1 << i))
    return names


def deg_to_ticks(deg: float) -> int:
    """Angle (degrees, 0 = centre) to the nearest tick in 0..4095."""
    ticks = round(CENTER_TICKS + deg / DEG_PER_TICK)
    return min(MAX_TICKS, max(0, ticks))


def ticks_to_deg(ticks: float) -> float:
    """Ticks to degrees (0 degrees = tick 2048)."""
    return (ticks - CENTER_TICKS) * DEG_PER_TICK


def dps_to_velocity_units(dps: float) -> int:
    """Degrees per second to Profile Velocity units (0.229 rev/min), at least 1 (0 = unlimited)."""
    return max(1, round(dps / 6.0 / RPM_PER_VELOCITY_UNIT))


def velocity_units_to_dps(units: float) -> float:
    """Profile/Present Velocity units (0.229 rev/min) to degrees per second."""
    return units * RPM_PER_VELOCITY_UNIT * 6.0
