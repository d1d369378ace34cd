"""The entry point of a rollout, with its I/O: :class:`dh2rt.flash.flasher.Flasher` on a transport.

A programming cable into one module's free connector is a serial port (``dh2rt flash
--port``, or the launcher's ``--event CYCLE:flash:M:IMAGE``, a pty of the link emulator); a
node on the bus is a CAN transport. Either way :class:`FlashCable` ticks the Flasher at the
robot's period, hands it the transfer frames and the module's Hellos as they arrive, sends
what it says, and ends with the Flasher's rollout report (see docs/flashing.md).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from dh2rt.closing import Closing
from dh2rt.flash.flasher import Flasher, Progress
from dh2rt.flash.pacing import Pacing
from dh2rt.flash.reports import ModuleReport
from dh2rt.flash.values import Action, Send
from dh2rt.hormone import Vocabulary
from dh2rt.transport.base import FrameFamily, Inbound, Transport
from dh2rt.wire.frame import NO_PROGRAM, FrameCodec, Hello
from dh2rt.wire.transfer import MAX_CONNECTOR
from drivers.connector_channel import ConnectorChannels
from firmware.negotiated_links import NegotiatedLinks

#: A codec that reads every connector's Hellos and no hormone (the cable runs no program).
HELLO_CODEC_CONNECTORS = MAX_CONNECTOR


#: Ticks between the cable's Hellos (it runs no program: see _hello).
HELLO_TICKS = 3


def hello_codec() -> FrameCodec:
    return FrameCodec(Vocabulary(()), HELLO_CODEC_CONNECTORS)


@dataclass(frozen=True, slots=True)
class FlashResult:
    """How a rollout ended: the Flasher's report, whether every module committed, why not."""

    succeeded: bool
    failure: str | None
    modules: list[ModuleReport]
    progress: Progress
    timed_out: bool = False


class FlashCable:
    """The Flasher on ``connector`` of ``transport`` (already attached), at ``period`` s;
    ``expect`` (the robot's module count, when known) and ``connector_name`` go to it."""

    def __init__(
        self,
        image: bytes,
        transport: Transport,
        *,
        period: float,
        pacing: Pacing,
        segment_size: int,
        connector: int = 1,
        clock: Callable[[], float] = time.monotonic,
        confirm: bool = False,
        settle_ticks: int = 250,
        on_step: Callable[[float], None] | None = None,
        expect: int | None = None,
        connector_name: Callable[[int], str] = str,
    ) -> None:
        self.transport = transport
        self.connector = connector
        self.period = period
        self.clock = clock
        transport.clock = clock
        self.flasher = Flasher(
            image, pacing=pacing, period=period, connector=connector, segment_size=segment_size,
            confirm=confirm, settle_ticks=settle_ticks, expect=expect, connector_name=connector_name,
        )  # fmt: skip
        #: called with the clock at the start of every step (a bus cable's link negotiation)
        self.on_step = on_step
        self.lock = threading.Lock()
        self._ticks_since_hello = HELLO_TICKS  # the first one at the first tick
        #: the transport's transfer frames come to the Flasher (the transport is the caller's
        #: and outlives no cable: each run opens its own)
        self.listening = transport.listen(FrameFamily.TRANSFER, self._on_transfer)

    def _on_transfer(self, frame: Inbound) -> None:
        if frame.connector == self.connector:
            self._send(self.flasher.receive(frame.connector, frame.payload, frame.arrived))

    def _send(self, actions: Sequence[Action]) -> None:
        for a in actions:
            if isinstance(a, Send):
                self.transport.send_raw(a.connector, a.frame(self.clock()))  # a COMMIT stamped as it leaves

    def step(self, until: float) -> None:
        """One tick now, then frames in until ``until`` (a reading of the clock)."""
        with self.lock:
            if self.on_step is not None:
                self.on_step(self.clock())
            self._send(self.flasher.tick(self.clock()))
            self._hello()
            while True:  # at least one poll: what came in since the last step
                for r in self.transport.poll(max(0.0, until - self.clock())):
                    if isinstance(r.frame, Hello) and r.at == self.connector:
                        hello = r.frame
                        self._send(self.flasher.hello(r.at, r.remote, hello.version, hello.digest, self.clock()))
                if self.clock() >= until or self.flasher.done:
                    return

    def _hello(self) -> None:
        """Every HELLO_TICKS ticks the cable says it runs no program (a Hello with the digest
        NO_PROGRAM): the module at the cable neither links to it nor refuses it, and its trial
        does not wait for it, so it can confirm with the cable still in."""
        self._ticks_since_hello += 1
        if self._ticks_since_hello >= HELLO_TICKS:
            self._ticks_since_hello = 0
            self.transport.send(self.connector, Hello(NO_PROGRAM))

    def run(
        self,
        *,
        timeout: float,
        stop: threading.Event | None = None,
        progress: Callable[[Progress], None] | None = None,
        progress_every: float = 0.5,
    ) -> FlashResult:
        """Tick at the period until the Flasher is done, ``timeout`` s passed or ``stop`` is set."""
        start = self.clock()
        deadline = start + timeout
        next_tick = start
        next_progress = start
        while not self.flasher.done and not (stop is not None and stop.is_set()):
            now = self.clock()
            if now >= deadline:
                break
            next_tick = max(next_tick + self.period, now)
            self.step(next_tick)
            if progress is not None and self.clock() >= next_progress:
                next_progress = self.clock() + progress_every
                progress(self.flasher.progress())
        return self.result()

    def result(self) -> FlashResult:
        f = self.flasher
        timed_out = not f.done
        return FlashResult(f.succeeded, f.failure or ("timed out" if timed_out else None), f.report(),
                           f.progress(), timed_out)  # fmt: skip


class BusCable(Closing):
    """The flasher's end of a programming cable on a robot whose modules share a bus: its
    connector-local channel touches one module's free connector, the two negotiate a link id
    over it as two modules would (:class:`firmware.negotiated_links.NegotiatedLinks`), and the
    rollout runs over the bus on that link. ``connector`` is the cable's own connector (one
    that may dock to the module's: CONRO's front for a free male connector, back for a free
    front); pass :meth:`step` as the FlashCable's ``on_step``."""

    def __init__(
        self,
        channels: ConnectorChannels,
        transport: Transport,
        connector: int,
        *,
        now: float,
        log: Callable[[str], None],
    ) -> None:
        self.transport = transport
        self.links = NegotiatedLinks(channels, transport, [connector], now, transport.attach, self._detach, log)

    def _detach(self, connector: int) -> None:
        self.transport.detach(connector)

    def step(self, now: float) -> None:
        self.links.step(now)

    def close(self) -> None:
        """Release the link on the bus and close the channel (the transport is the caller's)."""
        self.links.close()
