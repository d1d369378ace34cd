"""A bus of emulated ROBOTIS X-series servos on a pty, for the real dynamixel-sdk to talk to.

:class:`ServoEmulator` owns an ``os.openpty()`` pair (both ends raw) and serves Protocol 2.0
on the master from a background thread; ``emulator.port_path`` is the slave's tty name, the
string to give ``dynamixel_sdk.PortHandler`` (it opens a path, not a pyserial URL). A slave fd
stays open in the emulator for its whole life: the SDK's ``setBaudRate`` closes and reopens the
port, and with no slave open the master would read EIO.

This module is the bus: the pty, the thread, the byte stream and the order of replies. Each
servo id is an :class:`~hil.servo_table.EmulatedServo` (an X-series control table, see
:mod:`drivers.dxl_table`) with a pluggable :class:`~hil.servo_joints.JointBackend` that moves
the horn (:mod:`hil.servo_joints`).

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

import errno
import os
import select
import threading
import time
import tty
from collections.abc import Iterable, Mapping

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
from hil.ptys import run_as_hardware
from hil.servo_joints import JointBackend, KinematicJoint, ModuleJointAdapter
from hil.servo_table import EmulatedServo, Fault, u16

#: The servos of a bus: ids (each with a KinematicJoint) or ids mapped to joint backends.
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
    def lock(self) -> threading.RLock:
        """The bus's lock: held while a packet is handled (a backend's state read from another
        thread is read under it)."""
        return self._lock

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
            address, length = u16(params, 0), u16(params, 2)
            err, data = servo.read(address, length)
            return self._status(servo, err, data, kind=1)
        if inst in (Instruction.WRITE, Instruction.REG_WRITE):
            if len(params) < 3:
                return self._status(servo, dxt.ERRNUM_DATA_LENGTH)
            address, data = u16(params, 0), bytes(params[2:])
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
            address, length = u16(params, 0), u16(params, 2)
            for i in params[4:]:
                if i in live:
                    err, data = live[i].read(address, length)
                    replies += self._status(live[i], err, data, kind=1)
        elif inst == Instruction.SYNC_WRITE and len(params) >= 4:
            address, length = u16(params, 0), u16(params, 2)
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
                    servo.write(u16(params, 0), bytes(params[2:]))
                else:
                    servo.pending_write = (u16(params, 0), bytes(params[2:]))
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
        run_as_hardware()  # a servo's controller answers whatever the modules' processors do
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
