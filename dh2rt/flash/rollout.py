"""A module's state machine: one image's rollout through one module (:class:`Rollout`).

It takes the image from a neighbour (its source), passes it on to the others as it arrives,
has the host stage it, reports back along its name, and switches at the agreed instant; see
:mod:`dh2rt.flash` for the rules and ``docs/flashing.md`` for the message tables.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from dh2rt.errors import SignedImageError
from dh2rt.flash.node import Flood, Node, Port
from dh2rt.flash.pacing import Pacing
from dh2rt.flash.reports import RANK, describe_path
from dh2rt.flash.sender import Sender, SenderState
from dh2rt.flash.store import Store
from dh2rt.flash.values import (
    Action,
    Declined,
    DropPartial,
    ImageInfo,
    Partial,
    Persist,
    Program,
    Stage,
    Switch,
    Timing,
)
from dh2rt.wire.transfer import (
    MAX_PATH,
    MAX_VERDICT,
    Ack,
    Cancel,
    Commit,
    CommitAck,
    Decline,
    DeclineReason,
    Message,
    Offer,
    Outcome,
    Path,
    Report,
    ReportAck,
    Request,
    Segment,
    cut_reason,
    image_id,
)

# ---------------------------------------------------------------------------------------------
# A module


class Role(enum.Enum):
    """Where a module stands with the image being rolled out through it."""

    RECEIVING = "receiving"
    STAGING = "staging"  # every byte in; the host is staging it
    STAGED = "staged"  # in the flash; waiting for the switch
    SWITCHED = "switched"  # running it (on trial until confirmed or reverted)
    CURRENT = "current"  # it ran this image already when it was offered
    REFUSED = "refused"  # its flash refused it, or it would be a rollback
    WITHDRAWN = "withdrawn"  # the neighbour it came from refused it


#: Roles in which the module holds the image's bytes and passes them on.
_HOLDING = frozenset({Role.RECEIVING, Role.STAGING, Role.STAGED, Role.CURRENT, Role.SWITCHED})
#: Roles in which the module holds an image it does not run yet (a switched image is the
#: running program: an offer is judged against ``running`` then, so that an image of the same
#: version reaches the flash and is judged there, tampered or not).
_INCOMING = frozenset({Role.RECEIVING, Role.STAGING, Role.STAGED})
#: Roles in which a module unnamed (restarted mid-transfer) asks its source for its name
_NAMED_BY_SOURCE = _INCOMING | {Role.SWITCHED}
#: Roles that report themselves once every neighbour offered the image has, and as what.
_RESOLVED_OUTCOME = {Role.STAGED: Outcome.STAGED, Role.CURRENT: Outcome.CURRENT, Role.SWITCHED: Outcome.COMMITTED}


@dataclass(slots=True)
class _Refusal:
    """An image this module will not take: why, and (when it was offered under a name) which
    neighbours it has reported as withheld, so that neighbours linked later are too."""

    verdict: str
    reason: str
    tag: int
    name: Path | None = None
    exclude: int | None = None  # the neighbour it came from
    told: set[int] = field(default_factory=set)  # connectors reported withheld (or that report themselves)


@dataclass(slots=True)
class _Job:
    """The image being rolled out through this module."""

    store: Store
    role: Role
    name: Path | None  # the path from the entry point (known from an OFFER)
    source: int | None  # the connector bytes come from
    running_offer: bool  # a neighbour runs it: switch once staged
    progress: int  # tick the store last grew
    score: tuple[int, int] = (-1, 0)  # the source's OFFER: segments held, minus its depth
    program: Program | None = None  # once staged
    reported: int = -1  # rank of the last outcome reported about itself
    requested: int | None = None  # tick a REQUEST last went out without a source

    @property
    def info(self) -> ImageInfo:
        return self.store.info

    @property
    def parent(self) -> int | None:
        """The connector this module is named through (its name's last hop ends there): the
        neighbour nearer the entry point, which never reports to it. Kept when the source is
        lost (a link drop), unlike ``source``."""
        return None if not self.name else self.name[-1][1]

    def serves(self, connector: int) -> bool:
        """Whether the neighbour on ``connector`` is (or was) this module's source."""
        return connector == self.source or connector == self.parent


class Rollout(Node):
    """The rollout state machine of one module (see :mod:`dh2rt.flash`).

    ``connectors``: the module's connector numbers. ``running``: the program it runs (with
    its signed image, so that it can offer it). ``partial``: an image received in part
    before a restart (what :class:`Persist` wrote); ``staged``: an image staged before a
    restart and not yet switched to (boot the confirmed program then, not the trial).
    ``reverted``: ids of images reverted here (never taken again). ``latency``: the
    transit time of a COMMIT frame on this module's links, in seconds (its bytes at the
    link's rate), subtracted from the commit's remaining time. ``cut_through``: forward
    segments while later ones arrive (False: store and forward). ``connector_name``: how
    the reasons it reports name connectors."""

    def __init__(
        self,
        connectors: Iterable[int],
        running: Program,
        *,
        pacing: Pacing,
        timing: Timing | None = None,
        segment_size: int = 128,
        partial: Partial | None = None,
        staged: bytes | None = None,
        reverted: Iterable[bytes] = (),
        latency: float = 0.0,
        cut_through: bool = True,
        connector_name: Callable[[int], str] = str,
    ) -> None:
        super().__init__(connectors, pacing, timing or Timing(), segment_size=segment_size, cut_through=cut_through)
        self.running = running
        self.latency = latency
        #: how the reasons it reports name connectors (the profile's names, as every output does)
        self.connector_name = connector_name
        self._previous: Program | None = None
        self._switched_at: int | None = None
        self._on_trial = False
        self._running_store = self._whole(running)
        self._refused: dict[bytes, _Refusal] = {}
        self._reverted = set(reverted)
        self._job: _Job | None = None
        if staged is not None:
            self._resume_staged(staged)
        elif partial is not None:
            self._job = _Job(Store(partial.info, partial.data), Role.RECEIVING, None, None, False, 0)

    def _whole(self, program: Program) -> Store | None:
        if program.image is None:
            return None
        info = ImageInfo(image_id(program.image), program.version, len(program.image), self.segment_size)
        store = Store(info, program.image, released=True)
        return store

    def _resume_staged(self, data: bytes) -> None:
        program = Program.from_image(data)
        store = self._whole(program)
        assert store is not None
        self._job = _Job(store, Role.STAGED, None, None, False, 0, program=program)

    # -- read-only -----------------------------------------------------------------------------

    @property
    def role(self) -> Role | None:
        """This module's role in the image being rolled out through it (None: none)."""
        return None if self._job is None else self._job.role

    @property
    def name(self) -> Path | None:
        """This module's path from the entry point, once an OFFER told it."""
        return None if self._job is None else self._job.name

    @property
    def switch_at(self) -> float | None:
        """The switch instant on this module's clock, once a commit of its image is known."""
        if self._job is None or self._job.info.image not in self._floods:
            return None
        return self._floods[self._job.info.image].at

    @property
    def received(self) -> int:
        """Bytes of the incoming image held from the first (the whole image once complete)."""
        if self._job is None:
            return 0
        store = self._job.store
        return store.info.span(store.contiguous - 1)[1] if store.contiguous else 0

    def tolerated(self) -> frozenset[bytes]:
        """Program digests besides its own that this module's liveness machine should accept
        from a neighbour now: the staged program's while staged, the previous program's for
        ``tolerate_ticks`` cycles after the switch."""
        out: set[bytes] = set()
        job = self._job
        if job is not None and job.role is Role.STAGED and job.program is not None:
            out.add(job.program.digest)
        recent = self._switched_at is not None and self._tick - self._switched_at <= self.timing.tolerate_ticks
        if recent and self._previous is not None:
            out.add(self._previous.digest)
        return frozenset(out)

    # -- inputs --------------------------------------------------------------------------------

    def hello(self, connector: int, remote: int, version: int | None, digest: bytes, now: float) -> list[Action]:
        """A Hello from the neighbour on ``connector`` (sent through its ``remote``): its
        program's version (None: a Hello without one) and digest. Call it for every Hello,
        verified or refused."""
        self._now = now
        port = self._port(connector)
        self._link(port, remote)
        port.version, port.digest = version, digest
        job = self._job
        staged = job.program if job is not None and job.role is Role.STAGED else None
        if job is not None and staged is not None and staged.runs(version, digest):
            job.running_offer = True  # the neighbour switched: so do we
        self._offer_job(port)
        self._offer_running(port)
        if self._job is not None and self._job.role is Role.RECEIVING and self._job.source is None:
            self._request(port)
        for refusal in self._refused.values():
            self._withhold(refusal)
        return self._finish()

    def attach(self, connector: int, now: float) -> list[Action]:
        """``connector`` is attached (docked, or its port opened): a neighbour may be there.
        Until its Hello comes (at most ``stall_ticks`` cycles), this module does not report
        the image staged: that neighbour may still need it."""
        self._now = now
        port = self._port(connector)
        if not port.linked:
            port.attached_at = self._tick
        return self._finish()

    def detach(self, connector: int, now: float) -> list[Action]:
        """``connector`` was undocked: nobody is there."""
        self._now = now
        port = self._port(connector)
        port.attached_at = None
        self._lose(port)
        return self._finish()

    def link_down(self, connector: int, now: float) -> list[Action]:
        """The link on ``connector`` fell silent (liveness): the neighbour may come back."""
        self._now = now
        port = self._port(connector)
        self._lose(port)
        port.attached_at = self._tick
        return self._finish()

    def _lose(self, port: Port) -> None:
        self._unlink(port)
        job = self._job
        if job is not None and job.source == port.connector:
            job.source = None

    def staged(self, accepted: bool, verdict: str, reason: str, now: float) -> list[Action]:
        """The host's answer to :class:`Stage`: ``Flash.stage``'s accepted, verdict and reason."""
        self._now = now
        job = self._job
        if job is None or job.role is not Role.STAGING:
            raise ValueError("staged() answers a Stage action, and none is outstanding")
        self._actions.append(DropPartial())
        if accepted:
            self._accept(job)
        else:
            self._refuse(job, verdict, reason)
        return self._finish()

    def verified(self, now: float) -> list[Action]:
        """The host's flash found the image of the outstanding :class:`Stage` acceptable
        (signature, trust, version) and is writing it; :meth:`staged` follows once it is
        written. The last segment may go on meanwhile: the neighbours need the verdict, not
        this module's fsyncs (which took 1 to 2 cycles a hop in the loop)."""
        self._now = now
        job = self._job
        if job is not None and job.role is Role.STAGING:
            job.store.released = True
        return self._finish()

    def tick(self, now: float) -> list[Action]:
        """Once per cycle, at its start: the switch (first), retransmissions, stalls,
        commits, reports; then whatever this cycle's budget lets out."""
        self._begin_tick(now)
        self._maybe_switch()
        self._tick_senders()
        self._report_silent()
        self._tick_job()
        self._tick_floods()
        return self._finish()

    def confirmed(self, now: float) -> list[Action]:
        """The program on trial was confirmed (``Flash.confirm``)."""
        self._now = now
        self._on_trial = False
        job = self._job
        if job is not None and job.role is Role.SWITCHED:
            self._report_self(job, Outcome.CONFIRMED)
        return self._finish()

    def reverted(self, reason: str, now: float) -> list[Action]:
        """The program on trial was given up (``Flash.reject``): the previous one runs again."""
        self._now = now
        self._on_trial = False
        job = self._job
        if job is None or job.role is not Role.SWITCHED or self._previous is None:
            raise ValueError("reverted() without a switched program")
        self._reverted.add(job.info.image)
        self.running, self._previous = self._previous, None
        self._running_store = self._whole(self.running)
        job.role = Role.REFUSED
        self._refused[job.info.image] = _Refusal("reverted", cut_reason(reason), job.info.tag)
        self._report_self(job, Outcome.REVERTED, "reverted", reason)
        return self._finish()

    # -- dispatch ------------------------------------------------------------------------------

    def _dispatch(self, port: Port, sender: int, m: Message) -> None:
        match m:
            case Offer():
                self._on_offer(port, sender, m)
            case Request():
                self._on_request(port, m)
            case Segment():
                self._on_segment(port, m)
            case Ack():
                self._on_ack(port, m)
            case Decline():
                self._on_decline(port, m)
            case Cancel():
                self._on_cancel(port, m)
            case Commit():
                self._on_commit(port, m)
            case CommitAck():
                self._on_commit_ack(port, m)
            case Report():
                self._on_report(port, sender, m)
            case ReportAck():
                port.outbox.ack(m.seq)

    def _port(self, connector: int) -> Port:
        try:
            return self._ports[connector]
        except KeyError:
            raise ValueError(f"connector {connector!r} is not one of {sorted(self._ports)}") from None

    def _path_of(self, store: Store) -> Path:
        job = self._job
        if job is not None and job.info.image == store.info.image and job.name is not None:
            return job.name
        return ()

    def _store_for(self, image: bytes) -> Store | None:
        job = self._job
        if job is not None and job.info.image == image and job.role in _HOLDING:
            return job.store
        store = self._running_store
        return store if store is not None and store.info.image == image else None

    # -- offers --------------------------------------------------------------------------------

    def _on_offer(self, port: Port, sender: int, offer: Offer) -> None:
        info = ImageInfo(offer.image, offer.version, offer.length, offer.segment_size)
        name = (*offer.path, (sender, port.connector))
        if offer.path and offer.path[-1] == (port.connector, sender):
            # split horizon: the offerer took the image (and its name) through this very link,
            # from this module before a restart. Its name runs through this module, so taking
            # it would name this module after itself: reports would wait on each other for ever
            # (and the entry point would hear of this module twice). Another neighbour serves it.
            self.counters.looped += 1
            self._send(port.connector, Decline(info.image, DeclineReason.HAVE, self.running.version))
            return
        if self._job is not None and self._from_parent(self._job, info, port.connector):
            self._offered_again(port, self._job, name)
            return
        reason = self._judge(info, offer, port.connector, name)
        if reason is not None or len(name) > MAX_PATH:
            self._decline(port, info, name, reason or DeclineReason.HAVE)
            return
        job = self._job
        if job is not None and job.info.image == info.image and job.role is Role.RECEIVING:
            self._change_source(job, port, offer, name)
        else:
            if job is not None:
                self._drop(job)
            job = _Job(Store(info), Role.RECEIVING, name, port.connector, offer.running, self._tick, _score(offer))
            self._job = job
            for other in self._ports.values():
                self._offer_job(other)
        self._send(port.connector, Request(info.image, job.store.contiguous, self.timing.window))

    def _change_source(self, job: _Job, port: Port, offer: Offer, name: Path) -> None:
        """Take the rest of the image from ``port``; the neighbour left (if any) is told, so
        that it does not wait for this module. The name follows the source until this
        module has reported under one."""
        old = job.source
        if old is not None and old != port.connector:
            self._send(old, Decline(job.info.image, DeclineReason.HAVE, self.running.version))
        if offer.segment_size != job.info.segment_size:  # the bytes held, cut as this source cuts them
            job.store = job.store.resized(offer.segment_size)
            self._actions.append(Persist(job.info, 0, job.store.prefix()))
        job.source = port.connector
        job.score = _score(offer)
        job.progress = self._tick
        job.running_offer |= offer.running
        if job.name is None or (job.reported < 0 and offer.path):
            named = job.name is None
            job.name = name
            if named:  # its offers until now named nobody: offer again, naming them
                for other in self._ports.values():
                    self._offer_job(other, again=True)

    def _judge(self, info: ImageInfo, offer: Offer, connector: int, name: Path) -> DeclineReason | None:
        """Why this module does not take ``info`` from ``connector`` now (None: it does)."""
        job = self._job
        if job is not None and job.info.image == info.image and job.role is not Role.WITHDRAWN:
            if job.role is Role.RECEIVING and self._better_source(job, offer, connector, name):
                return None
            return DeclineReason.REFUSED if job.role is Role.REFUSED else DeclineReason.HAVE
        if info.image == self.running.ident:
            return DeclineReason.CURRENT
        if info.image in self._reverted:
            return DeclineReason.REVERTED
        if info.image in self._refused:
            return DeclineReason.REFUSED
        if info.version < self.running.version:
            return DeclineReason.NEWER
        if self._on_trial:
            return DeclineReason.BUSY
        if job is not None and job.role in _INCOMING:
            return DeclineReason.NEWER if info.version <= job.info.version else None
        return None

    def _from_parent(self, job: _Job, info: ImageInfo, connector: int) -> bool:
        """An OFFER of the job's image from its source (or, without one, anyone) to a module
        that holds it whole: the same image flashed again, or the offer repeated."""
        return (
            job.info.image == info.image
            and job.role in (Role.STAGED, Role.CURRENT, Role.SWITCHED)
            and (job.source is None or connector == job.source)
        )

    def _offered_again(self, port: Port, job: _Job, name: Path) -> None:
        """Answer with what it holds (the sender finishes at once), offer the neighbours
        again, and report once they have: a new entry point hears of the whole robot."""
        job.source = port.connector
        job.name = job.name or name
        job.reported = -1
        self._send(port.connector, Request(job.info.image, job.store.contiguous, self.timing.window))
        for other in self._ports.values():
            self._offer_job(other, again=True)

    def _better_source(self, job: _Job, offer: Offer, connector: int, name: Path) -> bool:
        """Whether to take the image from ``connector``: it is the source, or the neighbour
        this module is named after (its parent, back after a restart or a link drop); or it
        holds more than this module and there is no source, or the source made no progress
        for ``stall_ticks``, or it holds more than the source held when it offered (nearer
        the entry point on a tie)."""
        if connector == job.source or name == job.name:
            return True
        if offer.held <= job.store.contiguous:
            return False  # nothing to give yet (a REQUEST wakes it once it has)
        if job.source is None:
            return True
        stale = self._tick - job.progress >= self.timing.stall_ticks
        return stale or _score(offer) > job.score

    def _decline(self, port: Port, info: ImageInfo, name: Path, reason: DeclineReason) -> None:
        """Decline an offer, and answer the offerer's wait for a report: every decline but
        HAVE (another neighbour serves this module) is reported under the offer's name."""
        self._send(port.connector, Decline(info.image, reason, self.running.version))
        if reason is DeclineReason.HAVE:
            return
        if reason is DeclineReason.CURRENT:
            self._join_current(port, info, name)
            return
        verdict, why = self._refusal(info, reason)
        if reason in (DeclineReason.NEWER, DeclineReason.BUSY) and info.image not in self._declined:
            self._declined.add(info.image)
            self._actions.append(Declined(info.version, verdict, why))
        outcome = Outcome.REVERTED if reason is DeclineReason.REVERTED else Outcome.REFUSED
        self._report(outcome, name, len(name), info.tag, verdict, why)
        if reason is DeclineReason.NEWER and info.image not in self._refused and not self._holds_newer(info):
            refusal = _Refusal(verdict, why, info.tag, name, port.connector)  # a rollback: refused for good
            self._refused[info.image] = refusal
            self._withhold(refusal)

    def _refusal(self, info: ImageInfo, reason: DeclineReason) -> tuple[str, str]:
        """The verdict and reason a refusal of ``info`` reports."""
        if reason is DeclineReason.NEWER:
            job = self._job
            held = job.info.version if job is not None and self._holds_newer(info) else self.running.version
            return "rollback", f"version {info.version} is lower than version {held} here"
        if reason is DeclineReason.BUSY:
            return "busy", "another program runs on trial"
        refusal = self._refused.get(info.image)
        if refusal is not None:
            return refusal.verdict, refusal.reason
        return ("reverted", "reverted on trial here") if reason is DeclineReason.REVERTED else ("refused", "")

    def _holds_newer(self, info: ImageInfo) -> bool:
        job = self._job
        return job is not None and job.role in _INCOMING and job.info.image != info.image

    def _join_current(self, port: Port, info: ImageInfo, name: Path) -> None:
        """Offered the image it runs: it takes part as a holder (offers it on, and reports
        itself current once its neighbours have), unless it takes part already. Without the
        image's bytes it cannot pass it on, and reports itself current at once."""
        store = self._running_store
        if self._job is not None and self._job.info.image == info.image:
            return
        if store is None:
            self._report(Outcome.CURRENT, name, len(name), info.tag)
            return
        self._job = _Job(store, Role.CURRENT, name, port.connector, False, self._tick, program=self.running)
        for other in self._ports.values():
            self._offer_job(other)

    def _offer_job(self, port: Port, *, again: bool = False) -> None:
        """Offer the image being rolled out through this module to the neighbour on ``port``
        (not to its source, nor to the neighbour it is named after: that one holds it, and a
        cable there answers no offer), unless that neighbour has it in hand already
        (``again``: unless it is taking it now). A neighbour that lost the image asks for it
        (a probing REQUEST), and is offered it then."""
        job = self._job
        if job is None or job.role not in _HOLDING or not port.linked or job.serves(port.connector):
            return
        if job.name is None:
            return  # unnamed (resuming after a restart): it cannot name the modules it would serve
        sender = port.sender
        if sender is not None and sender.info.image == job.info.image and sender.state is SenderState.OFFERING:
            if again:
                self._offer(port, sender, job.store)  # at once, with this module's name now
            return
        if sender is not None and _keeps(sender, job.info, again=again):
            return
        self._start_sender(port, job.store, running=job.role in (Role.CURRENT, Role.SWITCHED))

    def _offer_running(self, port: Port) -> None:
        """Offer the running image to a neighbour whose Hello states a lower version."""
        store = self._running_store
        if store is None or port.version is None or port.version >= self.running.version:
            return
        sender = port.sender
        if sender is not None and sender.info.version >= self.running.version:
            recent = sender.ended_at is not None and self._tick - sender.ended_at < self.timing.stall_ticks
            if sender.active or recent or sender.state is SenderState.DONE:
                return
        self._start_sender(port, store, running=True)

    def _on_request(self, port: Port, request: Request) -> None:
        store = self._store_for(request.image)
        if store is None:
            self.counters.unwanted += 1
            return
        sender = port.sender
        if sender is None or sender.info.image != request.image:
            sender = self._start_sender(port, store, running=store is self._running_store)
            if request.probe:
                sender.reopen(request.next, self._tick)
        elif request.probe:
            if sender.state is not SenderState.SENDING:
                sender.reopen(request.next, self._tick)
            self._offer(port, sender, store)
        if not request.probe:
            sender.on_request(request.next, request.window, self._tick)

    # -- segments ------------------------------------------------------------------------------

    def _on_segment(self, port: Port, segment: Segment) -> None:
        job = self._job
        if job is None or job.info.tag != segment.tag:
            self.counters.unwanted += 1
            return
        store = job.store
        if job.role is not Role.RECEIVING:
            if job.role in _HOLDING and not job.serves(port.connector):
                # a neighbour pushing what this module took from another (its DECLINE was
                # lost): an ACK of every segment would leave it waiting for a report that
                # goes the other way for ever (issue 28: a flash after every link fell silent)
                self._send(port.connector, Decline(job.info.image, DeclineReason.HAVE, self.running.version))
            else:
                self._send(port.connector, Ack(segment.tag, store.contiguous, 0))
            return
        before = store.contiguous
        try:
            new = store.add(segment.index, segment.data)
        except ValueError:
            self.counters.garbage += 1
            return
        if new:
            job.progress = self._tick
            if job.source is None:
                job.source = port.connector
                job.score = (-1, 0)
        if store.contiguous > before:
            start = job.info.span(before)[0]
            self._actions.append(Persist(job.info, start, store.run(before, store.contiguous)))
        self._send(port.connector, Ack(segment.tag, store.contiguous, store.sack()))
        if store.complete:
            self._complete(job)

    def _complete(self, job: _Job) -> None:
        data = job.store.assemble()
        if image_id(data) != job.info.image:
            self.counters.corrupt_images += 1
            job.store = Store(job.info)
            self._actions.append(DropPartial())
            if job.source is not None:
                self._send(job.source, Request(job.info.image, 0, self.timing.window))
            return
        job.role = Role.STAGING
        self._actions.append(Stage(job.info, data))

    def _accept(self, job: _Job) -> None:
        job.role = Role.STAGED
        job.store.released = True
        try:
            job.program = Program.from_image(job.store.assemble())
        except SignedImageError:
            job.program = Program(job.info.version, b"", job.store.assemble())
        program = job.program
        if any(p.linked and p.digest is not None and program.runs(p.version, p.digest) for p in self._ports.values()):
            job.running_offer = True  # a neighbour runs it already

    def _refuse(self, job: _Job, verdict: str, reason: str) -> None:
        """The flash refused the image: withdraw what was passed on (a neighbour that took
        it reports itself when the CANCEL reaches it), and report the others withheld."""
        job.role = Role.REFUSED
        verdict = verdict[:MAX_VERDICT]
        refusal = _Refusal(verdict, cut_reason(reason), job.info.tag, job.name, job.source)
        self._refused[job.info.image] = refusal
        for port in self._ports.values():
            sender = port.sender
            if sender is not None and sender.info.image == job.info.image and sender.state is not SenderState.STALLED:
                if sender.state is SenderState.SENDING:
                    refusal.told.add(port.connector)
                sender.end(SenderState.CANCELLED, self._tick)
                self._send(port.connector, Cancel(job.info.image, verdict))
        if job.name is not None:
            self._report_self(job, Outcome.REFUSED, verdict, reason)
            self._withhold(refusal)

    def _withhold(self, refusal: _Refusal) -> None:
        """Report, by name, the linked neighbours this module does not pass a refused image
        on to (once each; called again when a neighbour links)."""
        name = refusal.name
        if name is None:
            return
        for port in self._ports.values():
            if port.connector in refusal.told or port.connector == refusal.exclude:
                continue
            if not port.linked or port.remote is None:
                continue
            refusal.told.add(port.connector)
            path = (*name, (port.connector, port.remote))
            why = f"not passed on: refused at {describe_path(name, self.connector_name)}"
            self._report(Outcome.WITHHELD, path, len(name), refusal.tag, refusal.verdict, why, port.version or 0)

    def _on_cancel(self, port: Port, cancel: Cancel) -> None:
        job = self._job
        if job is None or job.info.image != cancel.image or job.role is not Role.RECEIVING:
            self.counters.unwanted += 1
            return
        if job.source not in (None, port.connector):
            return  # another neighbour may still complete it
        job.role = Role.WITHDRAWN
        self._actions.append(DropPartial())
        self._refuse_onwards(job, cancel.verdict)
        if job.name is not None:
            why = f"withdrawn upstream ({cancel.verdict})"
            self._report_self(job, Outcome.WITHHELD, cancel.verdict, why)

    def _refuse_onwards(self, job: _Job, verdict: str) -> None:
        for port in self._ports.values():
            sender = port.sender
            if sender is not None and sender.info.image == job.info.image and sender.active:
                sender.end(SenderState.CANCELLED, self._tick)
                self._send(port.connector, Cancel(job.info.image, verdict))

    def _drop(self, job: _Job) -> None:
        """Give up the job's image for a newer one (its neighbours will be offered that)."""
        if job.role in (Role.RECEIVING, Role.STAGING):
            self._actions.append(DropPartial())

    # -- the commit and the switch -------------------------------------------------------------

    def _on_commit(self, port: Port, commit: Commit) -> None:
        self._send(port.connector, CommitAck(commit.image))
        port.acked.add(commit.image)
        port.commits.discard(commit.image)
        if commit.image in self._floods:
            return
        at = self._now + commit.remaining_us / 1e6 - self.latency
        if commit.hops == 0:
            at = self._mid_cycle(at)
        flood = self._floods[commit.image] = Flood(at, min(255, commit.hops + 1))
        self._spread(commit.image, flood)

    def _mid_cycle(self, at: float) -> float:
        """The middle of this module's cycle at or after ``at``, on its cycle grid (``at``
        itself until three ticks have measured it)."""
        grid = self._grid()
        if grid is None:
            return at
        start, period = grid
        k = max(0, math.ceil((at - start) / period - 0.5))
        return start + (k + 0.5) * period

    def _maybe_switch(self) -> None:
        job = self._job
        if job is None or job.role is not Role.STAGED or job.program is None:
            return
        flood = self._floods.get(job.info.image)
        if not job.running_offer and (flood is None or self._now < flood.at):
            return
        self._previous, self.running = self.running, job.program
        self._running_store = job.store
        self._switched_at = self._tick
        self._on_trial = True
        job.role = Role.SWITCHED
        self._actions.append(Switch(job.program))
        self._report_self(job, Outcome.COMMITTED)

    # -- reports -------------------------------------------------------------------------------

    def _on_report(self, port: Port, sender: int, report: Report) -> None:
        self._send(port.connector, ReportAck(report.seq))
        hop = report.path[report.left - 1]
        if hop != (port.connector, sender) or report.left < 2:
            self.counters.reports_dropped += 1
            return
        if report.left == len(report.path) and port.sender is not None and port.sender.info.tag == report.tag:
            port.sender.reported = True
        left = report.left - 1
        self.counters.reports_forwarded += 1
        self._route(
            Report(report.tag, 0, report.outcome, report.version, left, report.path, report.verdict, report.reason)
        )

    def _route(self, report: Report) -> None:
        """Queue ``report`` on the hop towards the entry point: out through the receiving
        connector of hop ``left`` of its path."""
        connector = report.path[report.left - 1][1]
        port = self._ports.get(connector)
        if port is None:
            self.counters.reports_dropped += 1
            return
        port.outbox.put(report)

    def _report(
        self,
        outcome: Outcome,
        path: Path,
        depth: int,
        tag: int,
        verdict: str = "",
        reason: str = "",
        version: int | None = None,
    ) -> None:
        """Originate a report about the module named ``path``, from this module at ``depth``."""
        if depth < 1:
            self.counters.reports_dropped += 1  # no entry point to send it to
            return
        version = self.running.version if version is None else version
        self._route(Report(tag, 0, outcome, version, depth, path, verdict[:MAX_VERDICT], cut_reason(reason)))

    def _report_self(self, job: _Job, outcome: Outcome, verdict: str = "", reason: str = "") -> None:
        if job.name is None:
            return
        job.reported = max(job.reported, RANK[outcome])
        self._report(outcome, job.name, len(job.name), job.info.tag, verdict, reason)

    def _report_resolved(self) -> None:
        """Staged (or current, or switched), and every neighbour offered the image has
        reported: say so."""
        job = self._job
        if job is None or job.role not in _RESOLVED_OUTCOME or job.name is None:
            return
        outcome = _RESOLVED_OUTCOME[job.role]
        if outcome is Outcome.COMMITTED and not self._on_trial:
            outcome = Outcome.CONFIRMED
        if job.reported >= RANK[outcome]:
            return
        for port in self._ports.values():
            sender = port.sender
            # the source is never a child, nor the neighbour this module is named after (the
            # source lost in a link drop, it may have been offered the image back and taken
            # none: it reports to its own parent, never to this module)
            child = not job.serves(port.connector)
            if child and sender is not None and sender.info.image == job.info.image and not sender.resolved:
                return
            if port.attached_at is not None and self._tick - port.attached_at < self.timing.stall_ticks:
                return  # a neighbour may be there, not yet heard
        self._report_self(job, outcome)

    def _report_silent(self) -> None:
        job = self._job
        if job is None or job.name is None:
            return
        for port in self._ports.values():
            sender = port.sender
            silent = sender is not None and sender.state is SenderState.STALLED and not sender.reported
            if not silent or sender is None or sender.silent_reported or sender.info.image != job.info.image:
                continue
            sender.silent_reported = True
            if sender.remote is not None:
                path = (*job.name, (port.connector, sender.remote))
                self._report(Outcome.SILENT, path, len(job.name), job.info.tag, "", "no answer", port.version or 0)

    # -- once a cycle --------------------------------------------------------------------------

    def _tick_job(self) -> None:
        job = self._job
        if job is not None and job.name is None and job.source is not None and job.role in _NAMED_BY_SOURCE:
            self._ask_name(job, self._ports[job.source])
        if job is None or job.role is not Role.RECEIVING:
            return
        source = None if job.source is None else self._ports[job.source]
        if source is not None and (not source.linked or self._tick - job.progress >= self.timing.stall_ticks):
            job.source = None
        if job.source is not None:
            return
        if job.requested is None or self._tick - job.requested >= self.timing.rto_ticks:
            job.requested = self._tick
            for port in self._ports.values():
                self._request(port)

    def _ask_name(self, job: _Job, port: Port) -> None:
        """A module restarted with part of the image takes the rest from whoever sends it
        segments, with or without an OFFER; unnamed, it could never report. Probe the source
        every ``rto_ticks`` until its OFFER names this module."""
        if job.requested is None or self._tick - job.requested >= self.timing.rto_ticks:
            job.requested = self._tick
            self._request(port)

    def _request(self, port: Port) -> None:
        """Probe the neighbour on ``port``: what does it hold of the image? (Its OFFER says,
        and names this module.)"""
        job = self._job
        if job is not None and port.linked:
            self._send(port.connector, Request(job.info.image, job.store.contiguous, self.timing.window, probe=True))

    def _finish(self) -> list[Action]:
        self._report_resolved()
        return self._flush()


def _score(offer: Offer) -> tuple[int, int]:
    """How good a source an offerer is: segments it holds, then nearness to the entry point."""
    return offer.held, -len(offer.path)


def _keeps(sender: Sender, info: ImageInfo, *, again: bool) -> bool:
    """Whether a port's sender stays rather than make way for an offer of ``info``: it is
    offering or sending ``info`` (or a newer image), or it offered ``info`` already and the
    peer did not fall silent (unless ``again``)."""
    if sender.info.image != info.image:
        return sender.active and sender.info.version > info.version
    return sender.active or (not again and sender.state is not SenderState.STALLED)
