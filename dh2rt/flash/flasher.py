"""The entry point's state machine: one image's rollout from the cable (:class:`Flasher`).

It offers the image through its one connector, decides the switch instant once the module at
the cable reports the robot staged, and collects every module's report; ``dh2rt flash``
(:mod:`tools.flash`, :mod:`firmware.flash.cable`) drives it.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass

from dh2rt.flash.node import Flood, Node, Port
from dh2rt.flash.pacing import Pacing
from dh2rt.flash.reports import COMMITTED, RANK, ModuleReport, describe_path
from dh2rt.flash.sender import SenderState
from dh2rt.flash.store import Store
from dh2rt.flash.values import Action, ImageInfo, Program, Timing
from dh2rt.wire.transfer import Ack, CommitAck, Decline, Message, Outcome, Path, Report, ReportAck, Request, image_id

#: Cycles the commit margin adds to the robot's depth (one per hop: a host that hands frames
#: over at its cycle start forwards a commit a cycle later; the slack covers lost COMMITs,
#: re-sent every cycle, and the first module's move of the instant to its mid-cycle).
COMMIT_SLACK = 4

# ---------------------------------------------------------------------------------------------
# The entry point


class FlasherPhase(enum.Enum):
    SENDING = "sending"  # the image spreads; waiting for the neighbour's report
    COMMITTING = "committing"  # the commit spreads; the switch instant is ahead
    SETTLING = "settling"  # past the switch: collecting the modules' reports
    DONE = "done"


@dataclass(frozen=True, slots=True)
class Progress:
    """What ``dh2rt flash`` shows while it runs."""

    phase: FlasherPhase
    modules: int  # modules heard of
    staged: int
    committed: int
    failed: int  # refused, reverted, withheld or silent
    bytes_acked: int  # image bytes the neighbour acknowledged
    elapsed: float  # seconds since the first tick
    rate: float  # image bytes per second delivered to modules (staged ones count whole)


#: Outcomes that stop a commit: the robot would be split between two programs.
_BLOCKING = frozenset({Outcome.REFUSED, Outcome.REVERTED, Outcome.WITHHELD})
#: Outcomes after which a module's report will not change on its own.
_FINAL = frozenset({*COMMITTED, Outcome.REFUSED, Outcome.REVERTED, Outcome.WITHHELD})


class Flasher(Node):
    """The entry point of a rollout: it holds the image, offers it through ``connector``
    (the cable), decides the switch instant once the robot is staged, and collects every
    module's report (see :mod:`dh2rt.flash`).

    ``period``: the robot's cycle period in seconds (the commit margin is counted in
    cycles). ``settle_ticks``: after the switch instant, how long to wait for modules still
    staged or silent. ``confirm``: wait for CONFIRMED reports too. ``latency``: as for
    :class:`Rollout` (unused here; the first module re-anchors the instant). ``expect``: how
    many modules the robot has, when the caller knows (the rollout is not settled, and did
    not succeed, until that many reported). ``quiet_ticks``: how long no report may change
    before the settled reports are taken as the whole robot (None: long enough for a report
    re-sent after its longest back-off to arrive). ``connector_name``: how connectors are
    named in :attr:`failure` (the profile's names: one name for a module in every output)."""

    def __init__(
        self,
        image: bytes,
        *,
        pacing: Pacing,
        period: float,
        connector: int = 1,
        timing: Timing | None = None,
        segment_size: int = 128,
        settle_ticks: int = 250,
        quiet_ticks: int | None = None,
        confirm: bool = False,
        expect: int | None = None,
        connector_name: Callable[[int], str] = str,
    ) -> None:
        super().__init__([connector], pacing, timing or Timing(), segment_size=segment_size, cut_through=True)
        if period <= 0:
            raise ValueError(f"period {period!r} must be positive")
        self.program = Program.from_image(image)
        info = ImageInfo(image_id(image), self.program.version, len(image), segment_size)
        self.info = info
        self.period = period
        self.connector = connector
        self.settle_ticks = settle_ticks
        # with no module count to wait for, a report lost on a hop (re-sent after rto, 2, 4, 8 x
        # rto ticks) must not be taken for a module that is not there: wait out the longest
        quiet = 5 if expect is not None else (self.timing.rto_ticks << 3) + 1
        self.quiet_ticks = quiet_ticks if quiet_ticks is not None else quiet
        self.expect = expect
        self.connector_name = connector_name
        self.confirm = confirm
        self.phase = FlasherPhase.SENDING
        self._store = Store(info, image, released=True)
        self._modules: dict[Path, ModuleReport] = {}
        self._started: float | None = None
        self._heard_at = 0  # tick a report last changed something
        self._decided_at: int | None = None  # tick the switch instant passed, or the rollout failed
        self._failure: str | None = None
        port = self._ports[connector]
        port.linked = True

    # -- read-only -----------------------------------------------------------------------------

    @property
    def done(self) -> bool:
        return self.phase is FlasherPhase.DONE

    @property
    def succeeded(self) -> bool:
        """Done, and every module heard of runs the image (confirmed, with ``confirm``)."""
        wanted = {Outcome.CONFIRMED, Outcome.CURRENT} if self.confirm else COMMITTED
        everyone = len(self._modules) >= (self.expect or 1)
        return self.done and everyone and all(m.outcome in wanted for m in self._modules.values())

    @property
    def failure(self) -> str | None:
        """Why the rollout stopped before a commit (None: it did not)."""
        return self._failure

    @property
    def switch_at(self) -> float | None:
        flood = self._floods.get(self.info.image)
        return None if flood is None else flood.at

    def report(self) -> list[ModuleReport]:
        """Every module heard of, by path from the entry point."""
        return [self._modules[p] for p in sorted(self._modules, key=lambda p: (len(p), p))]

    def progress(self) -> Progress:
        modules = self._modules.values()
        staged = sum(m.outcome in COMMITTED or m.outcome in (Outcome.STAGED, Outcome.REVERTED) for m in modules)
        committed = sum(m.committed for m in modules)
        failed = sum(
            m.outcome in (Outcome.REFUSED, Outcome.REVERTED, Outcome.WITHHELD, Outcome.SILENT) for m in modules
        )
        sender = self._ports[self.connector].sender
        acked = 0 if sender is None else self.info.span(sender.base - 1)[1] if sender.base else 0
        elapsed = 0.0 if self._started is None else self._now - self._started
        # image bytes delivered per second: the staged modules' images, or, before the first
        # module staged, what the module at the cable acknowledged
        rate = max(staged * self.info.length, acked) / elapsed if elapsed > 0 else 0.0
        return Progress(self.phase, len(self._modules), staged, committed, failed, acked, elapsed, rate)

    # -- inputs --------------------------------------------------------------------------------

    def hello(self, connector: int, remote: int, version: int | None, digest: bytes, now: float) -> list[Action]:
        """A Hello through the cable (the module there is alive): a stalled offer starts again."""
        self._now = now
        port = self._port(connector)
        self._link(port, remote)
        sender = port.sender
        if self.phase is FlasherPhase.SENDING and sender is not None and sender.state is SenderState.STALLED:
            self._start_sender(port, self._store, running=False)
        return self._flush()

    def attach(self, connector: int, now: float) -> list[Action]:
        """The cable is plugged in (again): offers go out through it."""
        self._now = now
        self._port(connector).linked = True
        return self._flush()

    def detach(self, connector: int, now: float) -> list[Action]:
        """The cable was unplugged: nothing goes out until it is plugged in again."""
        return self.link_down(connector, now)

    def link_down(self, connector: int, now: float) -> list[Action]:
        """The module at the cable fell silent; a stalled offer starts again at its next Hello."""
        self._now = now
        self._unlink(self._port(connector))
        return self._flush()

    def tick(self, now: float) -> list[Action]:
        self._begin_tick(now)
        if self._started is None:
            self._started = now
        port = self._ports[self.connector]
        if port.sender is None:
            self._start_sender(port, self._store, running=False)
        self._tick_senders()
        self._tick_phase(port)
        self._tick_floods()
        return self._flush()

    # -- the phases ----------------------------------------------------------------------------

    def _tick_phase(self, port: Port) -> None:
        sender = port.sender
        if self.phase is FlasherPhase.SENDING and sender is not None and sender.state is SenderState.STALLED:
            self._fail("the module at the cable fell silent")
        elif self.phase is FlasherPhase.COMMITTING and self._now >= self._floods[self.info.image].at:
            self.phase = FlasherPhase.SETTLING
            self._decided_at = self._tick
        if self.phase is FlasherPhase.SETTLING and self._settled():
            self.phase = FlasherPhase.DONE

    def _settled(self) -> bool:
        """Past the settle time, or every module's report is final and none changed lately."""
        if self._decided_at is not None and self._tick - self._decided_at >= self.settle_ticks:
            return True
        final = _FINAL - ({Outcome.COMMITTED} if self.confirm else set())
        quiet = self._tick - self._heard_at >= self.quiet_ticks
        everyone = self.expect is None or len(self._modules) >= self.expect
        return quiet and everyone and all(m.outcome in final for m in self._modules.values())

    def _fail(self, why: str) -> None:
        self._failure = why
        self.phase = FlasherPhase.SETTLING
        self._decided_at = self._tick

    def _commit(self) -> None:
        depth = max((len(p) for p in self._modules), default=1)
        at = self._now + (depth + COMMIT_SLACK) * self.period
        self._floods[self.info.image] = Flood(at, 0)
        self.phase = FlasherPhase.COMMITTING

    # -- messages ------------------------------------------------------------------------------

    def _dispatch(self, port: Port, sender: int, message: Message) -> None:
        match message:
            case Ack():
                self._on_ack(port, message)
            case Decline():
                self._on_decline(port, message)
            case Request():
                self._on_request(port, message)
            case CommitAck():
                self._on_commit_ack(port, message)
            case Report():
                self._on_report(port, sender, message)
            case _:
                self.counters.unwanted += 1

    def _port(self, connector: int) -> Port:
        if connector != self.connector:
            raise ValueError(f"connector {connector!r}: the flasher has only connector {self.connector}")
        return self._ports[connector]

    def _store_for(self, image: bytes) -> Store | None:
        return self._store if image == self.info.image else None

    def _path_of(self, store: Store) -> Path:
        return ()

    def _on_request(self, port: Port, request: Request) -> None:
        if request.image != self.info.image:
            self.counters.unwanted += 1
            return
        sender = port.sender
        if sender is None or sender.state is SenderState.STALLED:
            sender = self._start_sender(port, self._store, running=False)
        elif request.probe:
            self._offer(port, sender, self._store)
        if not request.probe:
            sender.on_request(request.next, request.window, self._tick)

    def _on_report(self, port: Port, sender: int, report: Report) -> None:
        self._send(port.connector, ReportAck(report.seq))
        if report.left != 1 or report.path[0] != (port.connector, sender) or report.tag != self.info.tag:
            self.counters.reports_dropped += 1
            return
        self._record(report)
        if len(report.path) == 1 and self.phase is FlasherPhase.SENDING:
            self._on_neighbour(report.outcome)

    def _record(self, report: Report) -> None:
        old = self._modules.get(report.path)
        if old is not None and RANK[old.outcome] > RANK[report.outcome]:
            return
        if old is None or old.outcome is not report.outcome:
            self._heard_at = self._tick
        self._modules[report.path] = ModuleReport(
            report.path, report.outcome, report.version, report.verdict, report.reason
        )

    def _on_neighbour(self, outcome: Outcome) -> None:
        """The module at the cable reported on itself, after its whole subtree: commit,
        unless a module refused the image (a robot half on each program would fall apart;
        silent modules catch up later)."""
        sender = self._ports[self.connector].sender
        if sender is not None:
            sender.reported = True
        refusals = [m for m in self.report() if m.outcome in _BLOCKING]
        if refusals:
            first = refusals[0]
            where = describe_path(first.path, self.connector_name)
            self._fail(f"not committed: {where} {first.outcome.name.lower()} the image")
        elif outcome in (Outcome.STAGED, Outcome.CURRENT, Outcome.COMMITTED, Outcome.CONFIRMED):
            self._commit()
