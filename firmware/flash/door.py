"""A module's part in rollouts, loaded when a rollout concerns it: :class:`RolloutDoor`.

Most of a module's life no image moves. The rollout's state machines and their I/O
(:mod:`dh2rt.flash`, :class:`firmware.flash.module_host.RolloutHost`) cost a module about 0.5 MB
of resident memory, a sixth of what dh2rt adds to python-can on a bus module
(``benchmarks/bench_footprint.py``), so a module booted from its flash starts with this
door instead and opens the host at the first thing that needs it:

* at boot, an image left in the flash by a previous life: one staged and waiting for the
  switch (``Flash.held``), or one received in part (``partial.json``);
* a transfer frame on any link (an OFFER, a probing REQUEST, ...);
* a neighbour's Hello stating a lower version than the running program's (this module
  offers it its image, as :meth:`dh2rt.flash.rollout.Rollout.hello` does).

Until then the door keeps what the host would have been told: the latest Hello on every
linked connector. When it opens, the new host attaches the transport's links as it always
does and is handed those Hellos (the one that opened it among them), then the transfer frame
that opened it, if one did, so it starts where an eagerly loaded host would be, in the cycle
under way too: its Rollout is told when that cycle began (``Node.join_cycle``), so that it
sends between ticks at once (a Rollout made between ticks otherwise waited for its first two
ticks: each module's REQUEST and first segments went at ticks only, about a cycle a hop in
``benchmarks/bench_flash.py``, 0.73 in tests/dh2rt/rollout_sim.py's snake:20). After that
the host is the runtime's observer, the door's transfer handler (the transport's, registered
once) hands it every transfer frame, and the door only forwards the module host's calls.

The host's code is not loaded on the cycle's path, though: importing and compiling it (a
module process may run without bytecode on disk) held a module past its neighbours' liveness
bound when the first transfer frame opened it, and they dropped the link. So the door
imports :mod:`firmware.flash.module_host` (and :mod:`dh2rt.flash` with it) in a background
thread as the module boots, before its first cycle, and opening the host later only builds
it. The saving left is the host's objects, not its code (``benchmarks/bench_footprint.py``).

Before any of this the door checks that the module's lines can carry a rollout at all
(:func:`dh2rt.flash.pacing.link_pacing`) and raises its ValueError if not, so a module on too
slow a line says so at boot, not at the first offer.
"""

from __future__ import annotations

import importlib
import threading
from collections import Counter
from collections.abc import Callable
from typing import TYPE_CHECKING

from dh2rt.flash.pacing import link_pacing
from dh2rt.runtime import ModuleRuntime
from dh2rt.transport.base import FrameFamily, Inbound, PortEnd
from dh2rt.wire.frame import Hello
from firmware.flash.slots import PARTIAL_INFO, Boot, Flash

if TYPE_CHECKING:
    from firmware.flash.module_host import OnSwitch, RolloutHost

#: The host's module, imported off the cycle's path (see the module docs).
HOST_MODULE = "firmware.flash.module_host"


def preload_host() -> threading.Thread:
    """Import the rollout host's code in a background thread (started; joined by nobody: an
    import the main thread needs meanwhile waits for it on the import lock)."""
    thread = threading.Thread(target=importlib.import_module, args=(HOST_MODULE,), name="dh2rt-rollout-preload",
                              daemon=True)  # fmt: skip
    thread.start()
    return thread


class RolloutDoor:
    """The rollout of one running module, its host loaded on demand (see the module docs)."""

    def __init__(
        self, rt: ModuleRuntime, flash: Flash, boot: Boot, on_switch: OnSwitch, transport: str, bitrate: int
    ) -> None:
        kind = transport.partition(":")[0]
        bauds = [e.baudrate for e in rt.transport.links.values() if isinstance(e, PortEnd)]
        self.pacing = link_pacing(kind, rt.cycle_period, min(bauds, default=115200), bitrate)
        self.rt, self.flash, self.boot, self.on_switch = rt, flash, boot, on_switch
        #: the host, once opened (None: no rollout has concerned this module yet)
        self.host: RolloutHost | None = None
        #: why it was opened, for the log and the tests
        self.opened_by: str | None = None
        self._hellos: dict[int, tuple[int, Hello, float]] = {}
        #: when the cycle under way began (the host's Rollout joins it: Node.join_cycle)
        self._cycle_started: float | None = None
        #: between a cycle's start and its link frames going out (the host holds its frames then)
        self._in_cycle = False
        rt.liveness.version = boot.version  # the Hellos state it from the first one
        rt.observer = self
        #: the transport's transfer frames: they open the host, then go to it
        self.listening = rt.transport.listen(FrameFamily.TRANSFER, self._on_transfer)
        if flash.held is not None:
            self._open("an image staged before this start")
        elif (flash.directory / PARTIAL_INFO).exists():
            self._open("an image received in part before this start")
        #: the host's code loading off the cycle's path (None: loaded at boot, opened then)
        self.preloading = preload_host() if self.host is None else None

    # -- what the module host reads and tells -------------------------------------------------

    @property
    def switched(self) -> bool:
        """The running program came from a switch of this process (its trial is the rollout's)."""
        return self.host is not None and self.host.switched

    @property
    def declined(self) -> Counter[str]:
        """Images refused at their offer, by verdict."""
        return Counter() if self.host is None else self.host.declined

    def settle(self) -> None:
        """Wait for the flash writes the host queued (before the module host writes the
        state record itself: a trial's rejection, written at once, comes after them)."""
        if self.host is not None:
            self.host.writer.flush()

    def write(self, work: Callable[[], object], then: Callable[[object, BaseException | None], None]) -> bool:
        """Hand ``work`` (a flash write) to the host's writer thread, in order after what it
        queued; ``then(result, error)`` runs on the module's thread at the host's next input.
        False when no host is open: the caller writes at once."""
        if self.host is None:
            return False
        self.host.writer.submit(work, then)
        return True

    def confirmed(self) -> None:
        if self.host is not None:
            self.host.confirmed()

    def reverted(self, reason: str) -> None:
        if self.host is not None:  # only a switch of this process is reverted here
            self.host.reverted(reason)

    # -- the runtime's LinkObserver, while closed --------------------------------------------

    def cycle_start(self, rt: ModuleRuntime, now: float) -> None:
        """Nothing to tolerate and nothing to send while no image moves; the cycle's start
        is kept for the host, should it open before the next."""
        self._cycle_started = now
        self._in_cycle = True

    def cycle_sent(self, rt: ModuleRuntime) -> None:
        """Nothing held back while no image moves."""
        self._in_cycle = False

    def hello(self, connector: int, remote: int, hello: Hello, now: float) -> None:
        self._hellos[connector] = (remote, hello, now)
        if hello.version is not None and hello.version < self.boot.version:
            # the host is handed every Hello kept, this one included
            self._open(f"a neighbour on version {hello.version} (through connector {connector})")

    def link_down(self, connector: int, now: float) -> None:
        self._hellos.pop(connector, None)

    def attached(self, connector: int) -> None:
        """The host attaches the transport's links when it opens."""

    def detached(self, connector: int) -> None:
        self._hellos.pop(connector, None)

    def _on_transfer(self, frame: Inbound) -> None:
        host = self._open(f"a transfer frame through connector {frame.connector}")
        host.on_transfer(frame.connector, frame.payload, frame.arrived)

    # -- opening ---------------------------------------------------------------------------

    def _open(self, why: str) -> RolloutHost:
        if self.host is not None:
            return self.host
        from firmware.flash.module_host import RolloutHost

        pacing, segment, latency = self.pacing
        connectors = range(1, self.rt.program.profile.connector_count + 1)
        self.host = host = RolloutHost(
            self.rt, self.flash, self.boot, self.on_switch,
            connectors=connectors, pacing=pacing, segment_size=segment, latency=latency,
            cycle_started=self._cycle_started, in_cycle=self._in_cycle,
        )  # fmt: skip
        self.opened_by = why
        self.rt.log.append(f"cycle {self.rt.cycle}: rollout: opened ({why})")
        for connector, (remote, hello, now) in sorted(self._hellos.items()):
            if connector in self.rt.transport.links:
                host.hello(connector, remote, hello, now)
        self._hellos.clear()
        return host
