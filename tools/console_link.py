"""The console's end of the cable: signed commands out, answers in (docs/console.md).

The console is a node as the flasher is (:mod:`firmware.flash.cable`): connector ``connector``
of a transport of its own (a serial port into one module's free connector, or a CAN node whose
connector-local channel touches one), saying every few cycles that it runs no program (a
Hello with ``NO_PROGRAM``) so that the module neither links to it nor refuses it. One thread
(:meth:`ConsoleLink.start`) owns the transport: it ticks at the robot's period, sends what the
console queued and hands control frames back; the console's own thread only queues commands
and waits for their answers.

Counters: a command's counter is the wall clock in microseconds, or one more than the last
this console used if that is later, so consoles need no state of their own to stay above
what every module accepted (a module refuses a counter not above its last: one whose clock
runs behind the console that sent the last command is refused as a replay until it catches
up, and says so).
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from dh2rt.closing import Closing
from dh2rt.errors import DecodeError
from dh2rt.transport.base import FrameFamily, Inbound, Transport
from dh2rt.wire import operator as op
from dh2rt.wire.frame import NO_PROGRAM, Hello
from firmware.flash.cable import HELLO_TICKS


@dataclass(frozen=True, slots=True)
class Outcome:
    """What came back for one command: the answers with its counter (a command that floods
    or injects is answered only when refused)."""

    counter: int
    answers: tuple[op.Answer | op.Watched, ...]

    @property
    def refused(self) -> op.Refused | None:
        return next((a for a in self.answers if isinstance(a, op.Refused)), None)

    @property
    def reply(self) -> op.StateReply | None:
        return next((a for a in self.answers if isinstance(a, op.StateReply)), None)


class ConsoleLink(Closing):
    """Signs commands with ``private_key`` and exchanges them through ``connector`` of
    ``transport`` (attached already), ticking every ``period`` s."""

    def __init__(
        self,
        transport: Transport,
        private_key: bytes,
        *,
        connector: int = 1,
        period: float = 0.02,
        on_step: Callable[[float], None] | None = None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.transport = transport
        self.key = private_key
        self.connector = connector
        self.period = period
        self.on_step = on_step
        self.clock = clock
        self._last_counter = 0
        self._outbox: queue.Queue[bytes] = queue.Queue()
        self._answers: queue.Queue[op.Answer | op.Watched] = queue.Queue()
        #: frames through the cable that did not decode (counted, never raised)
        self.malformed = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._listening = transport.listen(FrameFamily.CONTROL, self._on_control)
        #: an error that ended the pump (reported at the next command)
        self.failure: BaseException | None = None

    def start(self) -> ConsoleLink:
        self._thread = threading.Thread(target=self._pump, name="dh2rt-console-cable", daemon=True)
        self._thread.start()
        return self

    def next_counter(self) -> int:
        self._last_counter = max(int(self.clock() * 1_000_000), self._last_counter + 1)
        return self._last_counter

    def command(
        self, command: op.Command, wait: float, on_answer: Callable[[op.Answer | op.Watched], None] | None = None
    ) -> Outcome:
        """Sign and send ``command``; collect the answers with its counter for ``wait`` s, or
        until a STATE is answered or the command refused; each also goes to ``on_answer``
        as it comes (a WATCH's hormones, live)."""
        if self.failure is not None:
            raise OSError(f"the cable failed: {self.failure}")
        signed = op.sign(command, self.next_counter(), self.key)
        self._outbox.put(op.encode(self.connector, signed))
        deadline = time.monotonic() + wait
        got: list[op.Answer | op.Watched] = []
        while (left := deadline - time.monotonic()) > 0:
            try:
                answer = self._answers.get(timeout=left)
            except queue.Empty:
                break
            if answer.counter != signed.counter:
                continue  # a late answer to an earlier command
            got.append(answer)
            if on_answer is not None:
                on_answer(answer)
            if isinstance(command, op.StateRequest) or isinstance(answer, op.Refused):
                break
        return Outcome(signed.counter, tuple(got))

    def send_signed(self, signed: op.Signed) -> None:
        """Send an already signed command as it is (tests replay one with this)."""
        self._outbox.put(op.encode(self.connector, signed))

    def _on_control(self, frame: Inbound) -> None:
        if frame.connector != self.connector:
            return
        try:
            message = op.decode(frame.payload).message
        except DecodeError:
            self.malformed += 1
            return
        if not isinstance(message, op.Signed):  # a command flooded back at the cable: not ours
            self._answers.put(message)

    def _pump(self) -> None:
        ticks = HELLO_TICKS
        next_tick = time.monotonic()
        try:
            while not self._stop.is_set():
                if self.on_step is not None:
                    self.on_step(time.monotonic())
                ticks += 1
                if ticks >= HELLO_TICKS:
                    ticks = 0
                    self.transport.send(self.connector, Hello(NO_PROGRAM))
                while True:
                    try:
                        self.transport.send_raw(self.connector, self._outbox.get_nowait())
                    except queue.Empty:
                        break
                next_tick += self.period
                while (left := next_tick - time.monotonic()) > 0 and self._outbox.empty():
                    self.transport.poll(min(left, self.period / 4))
                next_tick = max(next_tick, time.monotonic() - self.period)
        except Exception as exc:  # the cable went away: the console says so at its next command
            self.failure = exc

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._listening.close()
