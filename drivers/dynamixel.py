"""ROBOTIS Dynamixel X-series servos (Protocol 2.0) behind :class:`ModuleDriver`.

One module's DOF1 (pitch) and DOF2 (yaw) are two servos on one half-duplex bus, ids
``dof1_id`` and ``dof2_id`` (1 and 2 by default). Built on the vendor's ``dynamixel-sdk``,
imported lazily so that ``import drivers`` never needs it. The SDK's result tuples
``(value, comm_result, error)`` become exceptions here and nowhere else:

===============================  ===========================================================
:class:`ServoNotFound`           no status packet in reply to a PING (absent, unpowered,
                                 wrong id or baud rate)
:class:`ServoModelMismatch`      the PING answer carries another model number
:class:`ServoCommError`          a status packet was corrupt (``COMM_RX_CORRUPT``), timed out
                                 outside a PING, or the port failed
:class:`ServoHardwareAlert`      the status error byte has the alert bit (0x80); the message
                                 names the Hardware Error Status (70) bits
:class:`ServoInstructionError`   the servo rejected an instruction (access, range, limit)
===============================  ===========================================================

Calls are serialised by a lock, so a runtime thread may call :meth:`set_targets` while another
calls :meth:`health` or :meth:`recover`.

What the runtime should call when:

* every control tick: :meth:`set_targets` (one SYNC_WRITE; there is no status packet, so it
  raises only if the port fails) and, when it needs feedback, :meth:`read_positions` or
  :meth:`read_feedback` (positions and loads; one SYNC_READ either way; it reports timeouts,
  corruption and hardware alerts);
* on a :class:`ServoCommError`: retry on the next tick; a single corrupt packet is line noise;
* on :class:`ServoHardwareAlert`, or when comm errors persist for a few ticks, or when
  :meth:`health` lists faults: call :meth:`recover`. It pings both servos, reboots any with a
  hardware alert, restores operating mode, limits and torque (a reboot or power loss leaves
  torque off) and re-sends the last targets. If it raises :class:`ServoNotFound` the servo is
  still gone: keep the module's program running without that joint, poll :meth:`health`
  (about once a second; it never raises) and call :meth:`recover` again when it answers.
"""

from __future__ import annotations

import contextlib
import importlib
import select
import threading
import time
from collections.abc import Iterator
from types import ModuleType
from typing import Any, Final

from dh2rt.closing import Closing
from dh2rt.errors import (
    DriverConfigError,
    DriverError,
    ServoCommError,
    ServoHardwareAlert,
    ServoInstructionError,
    ServoModelMismatch,
    ServoNotFound,
)
from drivers import dxl_table as dxt
from drivers.base import Feedback, Health, Joint, JointLimits, ModuleDriver

SUPPORTED_BAUDRATES: Final = (
    9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600,
    1000000, 1152000, 2000000, 2500000, 3000000, 3500000, 4000000,
)  # fmt: skip
MAX_UNICAST_ID: Final = 252
#: Present Load (or Current), Velocity and Position: addresses 126..135, read together.
_FEEDBACK_SIZE: Final = dxt.PRESENT_POSITION.end - dxt.PRESENT_LOAD.address


def _load_sdk() -> ModuleType:
    try:
        return importlib.import_module("dynamixel_sdk")
    except ImportError as exc:  # pragma: no cover - the [dynamixel] extra is missing
        raise DriverError("dynamixel-sdk is not installed; install dh2rt[dynamixel] to drive Dynamixel servos") from exc


#: What the SDK's communication results mean for someone debugging a servo bus.
_COMM_MEANING = {
    -3001: "no reply in time: servo missing, unpowered, wrong id or baud rate",
    -3002: "corrupt reply: bad CRC or framing on the bus",
}


#: PINGs after a REBOOT before the servo counts as not coming back (with reboot_timeout_s).
REBOOT_PINGS: Final = 3
#: The longest one wait for reply bytes blocks (the SDK then checks its timeout and reads
#: again): long enough not to spin, short next to any reply timeout.
_READ_WAIT_S: Final = 0.005
#: Time (ms) beyond what this process asked to wait, or between two of its reads of the
#: port, that means the process was not running (a busy machine, a paused VM): that time is
#: not counted against the servo's reply.
_STALL_MS: Final = 25.0


def port_handler(sdk: ModuleType, path: str, latency_timer_ms: float | None) -> Any:
    """The SDK's PortHandler as :class:`DynamixelDriver` makes it (for a program that talks
    to servos through the SDK itself): one that waits for reply bytes instead of spinning and
    counts only the time this process ran against a reply's timeout; with ``latency_timer_ms``,
    whose timeout uses that instead of the process-wide ``dynamixel_sdk.port_handler.LATENCY_TIMER`` (16 ms, the
    FTDI default).

    The SDK opens its port with ``timeout=0`` and, awaiting a status packet, calls
    ``readPort`` in a tight loop until the bytes or its timeout come: the process burns a
    core for every reply it awaits, and a servo emulator sharing that core (the HIL world's,
    or one in the same process, which then also fights it for the GIL) answers late, often
    past the 34 ms timeout. Here ``readPort`` first waits in ``select`` (no CPU, GIL
    released) until a byte is there, the packet's timeout is due, or ``_READ_WAIT_S`` passed.

    When this process was not running for more than ``_STALL_MS`` (a wait that returned that
    much later than asked, or that long between two reads), the stall is added to the
    packet's deadline. A real servo's reply waits in the kernel's buffer meanwhile and is
    read at once; an emulated one (a thread, stalled too) gets the time it was owed. A servo
    that is missing still times out after the full timeout of running time."""
    latency = None if latency_timer_ms is None else float(latency_timer_ms)

    class _PortHandler(sdk.PortHandler):  # type: ignore[misc, name-defined]
        _seen_ms = 0.0  # when this process last read the port, on the SDK's clock (ms)

        def setPacketTimeout(self, packet_length: int) -> None:  # noqa: N802 - SDK's name
            if latency is None:
                super().setPacketTimeout(packet_length)
            else:  # same formula as the SDK, with this port's latency timer
                self.packet_start_time = self.getCurrentTime()
                self.packet_timeout = self.tx_time_per_byte * packet_length + latency * 2.0 + 2.0
            self._seen_ms = self.packet_start_time

        def setPacketTimeoutMillis(self, msec: float) -> None:  # noqa: N802 - SDK's name
            super().setPacketTimeoutMillis(msec)
            self._seen_ms = self.packet_start_time

        def readPort(self, length: int) -> bytes:  # noqa: N802 - SDK's name
            ser = self.ser
            if length > 0 and self.packet_timeout > 0:
                now = self.getCurrentTime()
                if now - self._seen_ms > _STALL_MS:  # not running since the last read
                    self.packet_start_time += now - self._seen_ms
                if not ser.in_waiting:
                    left_ms = self.packet_timeout - self.getTimeSinceStart()
                    if left_ms > 0:
                        wait_s = min(left_ms / 1000.0, _READ_WAIT_S)
                        with contextlib.suppress(OSError, ValueError):
                            select.select([ser.fileno()], [], [], wait_s)
                        late = self.getCurrentTime() - now - wait_s * 1000.0
                        if late > _STALL_MS:  # the wait ended long after it was due
                            self.packet_start_time += late
                self._seen_ms = self.getCurrentTime()
            return ser.read(length)  # type: ignore[no-any-return]

    return _PortHandler(path)


#: Protocol 2.0 instructions whose status carries no parameters (WRITE, REG_WRITE, ACTION, REBOOT).
_NO_PARAMETERS: Final = frozenset({0x03, 0x04, 0x05, 0x08})
#: A PING's status: model number (2 bytes) and firmware version.
_PING_PARAMETERS: Final = 3
#: What a status packet's length field counts besides its parameters: instruction, error, CRC (2).
_STATUS_OVERHEAD: Final = 4


def _expected_parameters(txpacket: list[int]) -> int | None:
    """How many parameters the status answering ``txpacket`` carries (None: not checked)."""
    instruction = txpacket[7]
    if instruction == 0x01:  # PING
        return _PING_PARAMETERS
    if instruction in (0x02, 0x82):  # READ, SYNC_READ: address (2), then the data length (2)
        return txpacket[10] | (txpacket[11] << 8)
    if instruction in _NO_PARAMETERS:
        return 0
    return None


def _packet_handler(sdk: ModuleType) -> Any:
    """A Protocol 2.0 PacketHandler that does not take a late reply to an earlier request as
    the answer to this one.

    A status packet does not say which instruction it answers; the SDK takes the first well
    formed one from the awaited id. A reply that came after its request timed out (a servo
    emulator that was not scheduled, a servo busy past the timeout) is still in the port when
    the next request is sent (the SDK clears the port just before sending, and the reply may
    come after that): a PING then read a SYNC_READ's data as its model number (seen in the
    loop: "DOF1 servo id 1 is model 315, expected 1020"), and a read could have read another
    register's value. Here a status whose parameter count is not the one the request asks
    for is such a late reply: it is dropped (counted in ``stale``) and the wait goes on, within
    the same timeout. A late reply to the same kind of request (one SYNC_READ for the next) is
    of the right length and is taken: data one request old."""

    class _PacketHandler(sdk.Protocol2PacketHandler):  # type: ignore[misc, name-defined]
        stale = 0  # late replies dropped
        _expect: int | None = None

        def txPacket(self, port: Any, txpacket: list[int]) -> int:  # noqa: N802 - SDK's name
            self._expect = _expected_parameters(txpacket)
            return super().txPacket(port, txpacket)  # type: ignore[no-any-return]

        def rxPacket(self, port: Any, fast_option: bool) -> tuple[list[int], int]:  # noqa: N802 - SDK's name
            while True:
                rxpacket, result = super().rxPacket(port, fast_option)
                if result != 0 or fast_option or self._expect is None:
                    return rxpacket, result
                if (rxpacket[5] | (rxpacket[6] << 8)) - _STATUS_OVERHEAD == self._expect:
                    return rxpacket, result
                self.stale += 1

    return _PacketHandler()


class DynamixelBus(Closing):
    """One half-duplex Dynamixel bus: a port at a baud rate, and everything that talks on it.

    The joints' :class:`DynamixelDriver` and a latch servo (:class:`drivers.latch.ServoLatch`)
    on the same wires share one bus, so that one lock orders their packets and one place turns
    the SDK's result tuples into exceptions. Each servo is addressed by its id and named by
    ``who`` (``"DOF1 servo id 1"``, ``"latch servo id 7"``) in every message. Callers take
    :attr:`lock` around a sequence of packets that must not be interleaved.
    """

    def __init__(
        self,
        port: str,
        baudrate: int = 1_000_000,
        *,
        latency_timer_ms: float | None = None,
        reboot_timeout_s: float = 1.0,
    ) -> None:
        if not isinstance(port, str) or not port:
            raise DriverConfigError(f"port must be a device path such as /dev/ttyUSB0: {port!r}")
        if "://" in port:
            raise DriverConfigError(f"port {port!r} is a URL; dynamixel-sdk's PortHandler opens a device path")
        if baudrate not in SUPPORTED_BAUDRATES:
            raise DriverConfigError(f"baudrate {baudrate!r} is not one dynamixel-sdk supports: {SUPPORTED_BAUDRATES}")
        self.port_path = port
        self.baudrate = baudrate
        self.reboot_timeout_s = reboot_timeout_s
        self.lock = threading.RLock()
        self._latency_timer_ms = latency_timer_ms
        self._sdk: ModuleType | None = None
        self.port: Any = None
        self.ph: Any = None

    @property
    def is_open(self) -> bool:
        return self.port is not None

    def open(self) -> None:
        """Open the port at the bus's rate (nothing if it is open)."""
        with self.lock:
            if self.port is not None:
                return
            sdk = self._sdk = _load_sdk()
            port = port_handler(sdk, self.port_path, self._latency_timer_ms)
            try:
                # setBaudRate (re)opens the port; openPort() would open it at the default rate first.
                ok = port.setBaudRate(self.baudrate)
            except Exception as exc:  # pyserial's SerialException and OSError
                raise ServoCommError(f"cannot open servo port {self.port_path!r}: {exc}") from exc
            if not ok:
                raise ServoCommError(f"cannot set {self.baudrate} bps on {self.port_path!r}")
            self.port = port
            self.ph = _packet_handler(sdk)

    def close(self) -> None:
        """Close the port (torque is left as it is, so the servos keep their pose)."""
        with self.lock:
            if self.port is not None:
                try:
                    self.port.closePort()
                finally:
                    self.port = None

    def require_open(self) -> None:
        if self.port is None:
            raise ServoCommError(f"servo port {self.port_path} is not open")

    def ping(self, dxl_id: int, who: str, expected_model: int | None = None) -> int:
        """PING one servo; its model number. ServoNotFound when nothing answers."""
        with self.lock, self.io(f"PING of {who}"):
            self.require_open()
            model, result, error = self.ph.ping(self.port, dxl_id)
        if result == self.sdk_const("COMM_RX_TIMEOUT"):
            raise ServoNotFound(f"{who} did not answer a PING on {self.port_path} at {self.baudrate} bps")
        self.check(dxl_id, who, "PING", result, error)
        if expected_model is not None and model != expected_model:
            raise ServoModelMismatch(f"{who} is model {_model_name(model)}, expected {_model_name(expected_model)}")
        return int(model)

    def read(self, dxl_id: int, who: str, field: dxt.Field) -> int:
        with self.lock, self.io(f"READ of {field.name} from {who}"):
            self.require_open()
            data, result, error = self.ph.readTxRx(self.port, dxl_id, field.address, field.size)
        self.check(dxl_id, who, f"READ of {field.name}", result, error)
        return int.from_bytes(bytes(data[: field.size]), "little", signed=field.signed)

    def write(self, dxl_id: int, who: str, field: dxt.Field, value: int) -> None:
        data = list(value.to_bytes(field.size, "little", signed=field.signed))
        with self.lock, self.io(f"WRITE of {field.name} to {who}"):
            self.require_open()
            result, error = self.ph.writeTxRx(self.port, dxl_id, field.address, field.size, data)
        self.check(dxl_id, who, f"WRITE of {field.name}={value}", result, error)

    def reboot(self, dxl_id: int, who: str) -> None:
        """REBOOT one servo and wait until it answers a PING again (RAM back to defaults:
        torque off, hardware alert cleared)."""
        with self.lock:
            with self.io(f"REBOOT of {who}"):
                self.require_open()
                result, _ = self.ph.reboot(self.port, dxl_id)  # the status predates the reboot
            if result != 0:
                raise ServoCommError(f"REBOOT of {who}: {self.result(result)}")
            deadline = time.monotonic() + self.reboot_timeout_s
            attempts = 0
            while True:  # the servo is silent while it restarts
                time.sleep(0.02)
                attempts += 1
                try:
                    self.ping(dxl_id, who)
                    return
                except ServoNotFound:
                    # a PING sent while the servo restarts goes unanswered and costs a whole reply
                    # timeout, longer on a machine that stalls (see port_handler): give up only
                    # after REBOOT_PINGS, not after the first because its timeout ran past the deadline
                    if attempts >= REBOOT_PINGS and time.monotonic() > deadline:
                        raise

    @contextlib.contextmanager
    def io(self, what: str) -> Iterator[None]:
        """The port itself failing (a USB adapter pulled, a pty closed) as ServoCommError:
        pyserial and termios raise their own errors from inside the SDK."""
        try:
            yield
        except DriverError:
            raise
        except Exception as exc:  # OSError, termios.error, serial.SerialException
            raise ServoCommError(f"{what}: port {self.port_path!r} failed: {exc}") from exc

    def check(self, dxl_id: int, who: str, what: str, result: int, error: int) -> None:
        """Turn one SDK result pair into an exception (or nothing)."""
        if result != 0:
            raise ServoCommError(f"{what} to {who}: {self.result(result)}")
        if error & dxt.ERRBIT_ALERT:
            raise ServoHardwareAlert(f"{who} hardware alert: {self._alert(dxl_id, who)}")
        if error:
            name = dxt.ERROR_NUMBER_NAMES.get(error, f"error number {error}")
            raise ServoInstructionError(f"{what} to {who} was rejected: {name}")

    def _alert(self, dxl_id: int, who: str) -> str:
        f = dxt.HARDWARE_ERROR_STATUS
        with self.lock, self.io(f"READ of {f.name} from {who}"):
            data, result, _ = self.ph.readTxRx(self.port, dxl_id, f.address, f.size)
        if result != 0:
            return f"Hardware Error Status unreadable ({self.result(result)})"
        bits = int(data[0])
        names = ", ".join(dxt.hardware_error_names(bits)) or "no bits set"
        return f"{names} (Hardware Error Status 0x{bits:02x})"

    def result(self, result: int) -> str:
        text = str(self.ph.getTxRxResult(result)).removeprefix("[TxRxResult] ")
        meaning = _COMM_MEANING.get(result)
        return f"{text} (comm result {result}{': ' + meaning if meaning else ''})"

    def sdk_const(self, name: str) -> int:
        assert self._sdk is not None
        return int(getattr(self._sdk, name))

    @property
    def stale_replies(self) -> int:
        """Late replies to an earlier request dropped since the port opened (see
        :func:`_packet_handler`): a servo or emulator that answers past the timeout."""
        return 0 if self.ph is None else int(self.ph.stale)


class DynamixelDriver(ModuleDriver):
    """Both joints of one module on two Dynamixel X-series servos, in degrees.

    0 degrees is tick 2048 (4096 ticks per revolution). Targets are clamped to ``limits``,
    which are also written to the servos' position limits (48/52) and, as Profile Velocity,
    their speed. With ``connect=True`` (the default) the constructor opens the port and calls
    :meth:`open`; if that fails it closes the port again before raising. The port is a
    :class:`DynamixelBus` (:attr:`bus`), which another servo on the same wires (a latch) shares.
    """

    def __init__(
        self,
        port: str,
        dof1_id: int = 1,
        dof2_id: int = 2,
        baudrate: int = 1_000_000,
        expected_model: int | None = dxt.MODEL_XM430_W350,
        limits: tuple[JointLimits, JointLimits] | None = None,
        *,
        connect: bool = True,
        latency_timer_ms: float | None = None,
        reboot_timeout_s: float = 1.0,
    ) -> None:
        bus = DynamixelBus(port, baudrate, latency_timer_ms=latency_timer_ms, reboot_timeout_s=reboot_timeout_s)
        for name, value in (("dof1_id", dof1_id), ("dof2_id", dof2_id)):
            if not isinstance(value, int) or not 0 <= value <= MAX_UNICAST_ID:
                raise DriverConfigError(f"{name} must be in 0..{MAX_UNICAST_ID}, got {value!r}")
        if dof1_id == dof2_id:
            raise DriverConfigError(f"dof1_id and dof2_id must differ, both are {dof1_id}")
        if limits is not None:
            if len(limits) != 2:
                raise DriverConfigError(f"limits must be two JointLimits, got {limits!r}")
            for joint, lim in zip(Joint, limits, strict=True):
                if not -180.0 <= lim.min_deg < lim.max_deg <= 180.0 or lim.max_speed_dps <= 0:
                    raise DriverConfigError(
                        f"limits[{joint.name}] must have -180 <= min_deg < max_deg <= 180 and "
                        f"max_speed_dps > 0, got {lim}"
                    )
            self.limits = (limits[0], limits[1])
        self.bus = bus
        self.port_path = port
        self.ids: tuple[int, int] = (dof1_id, dof2_id)
        self.baudrate = baudrate
        self.expected_model = expected_model
        self.reboot_timeout_s = reboot_timeout_s
        self.last_targets: tuple[float, float] | None = None
        self._lock = bus.lock
        self._sync_write: Any = None
        self._sync_read: Any = None
        self._sync_feedback: Any = None
        #: Each servo's model (from its PING) and Current Limit (read when it is configured;
        #: 0 for models that report Present Load): what address 126 means, dxl_table.load_percent.
        self.models: list[int | None] = [None, None]
        self._current_limits = [0, 0]
        if connect:
            try:
                self.open()
            except BaseException:
                self.close()
                raise

    # -- setup --

    def open(self) -> None:
        """Open the port (if needed), check both servos and put them in position mode with
        torque on. On a servo error the port stays open so :meth:`health` and
        :meth:`recover` can be used."""
        with self._lock:
            if self._sync_write is None or not self.bus.is_open:
                self._open_port()
            for joint in Joint:
                self._ping(joint)
            for joint in Joint:
                self._configure(joint)

    def _open_port(self) -> None:
        self.bus.open()
        sdk, port, ph = self.bus._sdk, self.bus.port, self.bus.ph
        assert sdk is not None
        goal, present = dxt.GOAL_POSITION, dxt.PRESENT_POSITION
        self._sync_write = sdk.GroupSyncWrite(port, ph, goal.address, goal.size)
        self._sync_read = sdk.GroupSyncRead(port, ph, present.address, present.size)
        # load, velocity and position are adjacent: one read from 126 to 135 gives them all
        self._sync_feedback = sdk.GroupSyncRead(port, ph, dxt.PRESENT_LOAD.address, _FEEDBACK_SIZE)
        for dxl_id in self.ids:
            self._sync_read.addParam(dxl_id)
            self._sync_feedback.addParam(dxl_id)

    def close(self) -> None:
        """Close the port (torque is left as it is, so the module keeps its pose)."""
        self.bus.close()

    # -- ModuleDriver --

    def set_targets(self, dof1_deg: float, dof2_deg: float) -> None:
        """Both goal positions in one SYNC_WRITE (no reply: raises only if the port fails)."""
        targets = (self.limits[0].clamp(dof1_deg), self.limits[1].clamp(dof2_deg))
        with self._lock:
            self.last_targets = targets  # kept even if sending fails, for recover()
            self._send_targets(targets)

    def _send_targets(self, targets: tuple[float, float]) -> None:
        self._require_open()
        sync = self._sync_write
        sync.clearParam()
        for dxl_id, deg in zip(self.ids, targets, strict=True):
            sync.addParam(dxl_id, list(dxt.deg_to_ticks(deg).to_bytes(4, "little", signed=True)))
        with self.bus.io("SYNC_WRITE of goal positions"):
            result = sync.txPacket()
        if result != 0:
            raise ServoCommError(f"SYNC_WRITE of goal positions failed: {self.bus.result(result)}")

    def read_positions(self) -> tuple[float, float]:
        """Both present positions from one SYNC_READ."""
        with self._lock:
            data = self._sync_read_both(self._sync_read, dxt.PRESENT_POSITION.size, "present position")
            angles = [dxt.ticks_to_deg(_field(d, dxt.PRESENT_POSITION, dxt.PRESENT_POSITION.address)) for d in data]
            return angles[0], angles[1]

    def read_loads(self) -> tuple[float, float]:
        """Both present loads (percent of the maximum torque, signed), from one SYNC_READ."""
        return self.read_feedback().loads

    def read_feedback(self) -> Feedback:
        """Present positions and loads of both servos from one SYNC_READ of addresses 126..135
        (Present Load or Current, Velocity, Position)."""
        with self._lock:
            data = self._sync_read_both(self._sync_feedback, _FEEDBACK_SIZE, "present load and position")
            base = dxt.PRESENT_LOAD.address
            angles = [dxt.ticks_to_deg(_field(d, dxt.PRESENT_POSITION, base)) for d in data]
            raw = [_field(d, dxt.PRESENT_LOAD, base) for d in data]
            loads = [self._load_percent(joint, r) for joint, r in zip(Joint, raw, strict=True)]
            return Feedback((angles[0], angles[1]), (loads[0], loads[1]))

    def _sync_read_both(self, sync: Any, size: int, what: str) -> list[bytes]:
        """Send one prepared SYNC_READ and receive both servos' data (caller holds the lock)."""
        self._require_open()
        bus = self.bus
        with bus.io(f"SYNC_READ of {what}"):
            result = sync.txPacket()
            if result != 0:
                raise ServoCommError(f"SYNC_READ of {what}: {bus.result(result)}")
            # GroupSyncRead.rxPacket() drops each status's error byte, so receive the
            # statuses with the packet handler to see hardware alerts.
            replies = [bus.ph.readRx(bus.port, dxl_id, size) for dxl_id in self.ids]
        out = []
        for joint, (data, result, error) in zip(Joint, replies, strict=True):
            self._check(joint, f"SYNC_READ of {what}", result, error)
            out.append(bytes(data[:size]))
        return out

    def set_torque(self, enabled: bool) -> None:
        with self._lock:
            self._require_open()
            for joint in Joint:
                self._write(joint, dxt.TORQUE_ENABLE, int(enabled))

    @property
    def stale_replies(self) -> int:
        """Late replies to an earlier request dropped since the port opened (see
        :func:`_packet_handler`): a servo or emulator that answers past the timeout."""
        return self.bus.stale_replies

    def reply_timeout_ms(self, packet_length: int) -> float:
        """How long this port waits for a status packet of ``packet_length`` bytes: the SDK's
        formula with this driver's ``latency_timer_ms`` (the SDK's own default without one)."""
        with self._lock:
            self._require_open()
            self.bus.port.setPacketTimeout(packet_length)
            return float(self.bus.port.packet_timeout)

    # -- health and recovery --

    def health(self) -> Health:
        """Ping and inspect both servos; faults are listed, never raised."""
        with self._lock:
            if not self.bus.is_open:
                return Health(faults=(f"servo port {self.port_path} is closed",))
            faults: list[str] = []
            details: dict[str, float] = {}
            for joint in Joint:
                key = joint.name.lower()
                try:
                    self._ping(joint)
                    torque = self._read(joint, dxt.TORQUE_ENABLE)
                    details[f"{key}_temperature_c"] = self._read(joint, dxt.PRESENT_TEMPERATURE)
                    volts = self._read(joint, dxt.PRESENT_INPUT_VOLTAGE) / 10
                    details[f"{key}_voltage_v"] = volts
                    if not torque:
                        faults.append(f"{self._who(joint)}: torque is off (rebooted or lost power?)")
                except DriverError as exc:
                    faults.append(str(exc))
            return Health(faults=tuple(faults), details=details)

    def recover(self) -> Health:
        """Bring both servos back after a fault; see the module docstring for when to call it.

        Raises :class:`ServoNotFound` if a servo still does not answer, or another
        :class:`DriverError` if it cannot be brought back; returns :meth:`health` otherwise.
        """
        with self._lock:
            if not self.bus.is_open or self._sync_write is None:
                self._open_port()
            for joint in Joint:
                try:
                    self._ping(joint)
                    alert = bool(self._read(joint, dxt.HARDWARE_ERROR_STATUS))
                except ServoHardwareAlert:
                    alert = True
                except ServoCommError:
                    self._ping(joint)  # one garbled packet is not a lost servo: try once more
                    alert = bool(self._read(joint, dxt.HARDWARE_ERROR_STATUS))
                if alert:
                    self.bus.reboot(self.ids[joint], self._who(joint))
                self._configure(joint)
            if self.last_targets is not None:
                self._send_targets(self.last_targets)
            return self.health()

    # -- bus helpers (callers hold the lock) --

    def _configure(self, joint: Joint) -> None:
        """Position mode, position limits and speed from ``limits``, then torque on."""
        lim = self.limits[joint]
        configure_position_servo(
            self.bus, self.ids[joint], self._who(joint), (lim.min_deg, lim.max_deg), lim.max_speed_dps
        )
        if self.models[joint] not in dxt.PRESENT_LOAD_MODELS:  # address 126 is Present Current
            self._current_limits[joint] = self._read(joint, dxt.CURRENT_LIMIT)

    def _load_percent(self, joint: Joint, raw: int) -> float:
        return dxt.load_percent(raw, self.models[joint] or 0, self._current_limits[joint])

    def _ping(self, joint: Joint) -> int:
        model = self.bus.ping(self.ids[joint], self._who(joint), self.expected_model)
        self.models[joint] = model
        return model

    def _read(self, joint: Joint, field: dxt.Field) -> int:
        return self.bus.read(self.ids[joint], self._who(joint), field)

    def _write(self, joint: Joint, field: dxt.Field, value: int) -> None:
        self.bus.write(self.ids[joint], self._who(joint), field, value)

    def _check(self, joint: Joint, what: str, result: int, error: int) -> None:
        self.bus.check(self.ids[joint], self._who(joint), what, result, error)

    def _who(self, joint: Joint) -> str:
        return f"{joint.name} servo id {self.ids[joint]}"

    def _require_open(self) -> None:
        if not self.bus.is_open or self._sync_write is None:
            raise ServoCommError(f"servo port {self.port_path} is not open")


def configure_position_servo(
    bus: DynamixelBus, dxl_id: int, who: str, range_deg: tuple[float, float], speed_dps: float
) -> None:
    """Position mode, position limits ``range_deg`` and Profile Velocity ``speed_dps``, then
    torque on, which holds the horn where it is (Goal Position becomes Present Position).
    EEPROM is locked while torque is on, and writing it wears the servo's flash: only what
    differs is written."""
    with bus.lock:
        eeprom = (
            (dxt.OPERATING_MODE, dxt.MODE_POSITION),
            (dxt.MAX_POSITION_LIMIT, dxt.deg_to_ticks(range_deg[1])),
            (dxt.MIN_POSITION_LIMIT, dxt.deg_to_ticks(range_deg[0])),
        )
        stale = [(f, v) for f, v in eeprom if bus.read(dxl_id, who, f) != v]
        if stale:
            bus.write(dxl_id, who, dxt.TORQUE_ENABLE, 0)
            for field, value in stale:
                bus.write(dxl_id, who, field, value)
        bus.write(dxl_id, who, dxt.PROFILE_VELOCITY, dxt.dps_to_velocity_units(speed_dps))
        bus.write(dxl_id, who, dxt.TORQUE_ENABLE, 1)


def _field(data: bytes, field: dxt.Field, base: int) -> int:
    """``field``'s value in ``data`` read from address ``base``."""
    start = field.address - base
    return int.from_bytes(data[start : start + field.size], "little", signed=field.signed)


def _model_name(model: int) -> str:
    name = dxt.MODEL_NAMES.get(model)
    return f"{model} ({name})" if name else str(model)
