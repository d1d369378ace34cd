"""A module's rollout in its running loop: the I/O around :class:`dh2rt.flash.rollout.Rollout`.

:class:`RolloutHost` is what ``docs/flashing.md`` ("Driving the state machines") asks of a
host, for :class:`firmware.main_loop.ModuleHost`, which opens it through
:class:`firmware.flash.door.RolloutDoor` once a rollout concerns the module:

* transfer frames reach it as the transport polls them (the door's transfer handler,
  ``Transport.listen``, hands them on: a *prompt* host, between cycles as they arrive),
  Hellos, silent links, attaches and detaches from the runtime (it is the runtime's
  :class:`~dh2rt.runtime.LinkObserver`), and it ticks the Rollout at every cycle start,
  before the engine;
* it carries out the actions: ``Send`` through the transport (from a cycle's start until the
  runtime has sent that cycle's hormones and beacons, ``cycle_sent``, held back and sent
  after them: the line is the hormones' at each cycle start), ``Persist``/``DropPartial``
  into ``partial.img``/``partial.json`` beside the slots of the module's flash (durably,
  so that a module restarted mid-staging resumes), ``Stage`` through ``Flash.stage(hold=
  True)`` (the image waits for the agreed switch; a restart meanwhile boots the old program
  and hands the staged image back to the Rollout), and ``Switch``: ``Flash.start_trial``
  and the new program in the running loop (``ModuleRuntime.switch_program``) at that very
  cycle start;
* the flash's durable writes (``Persist``, ``DropPartial``, ``Stage``: each an fsync or
  four) go to :class:`FlashWriter`, a thread of their own, in order, not on the cycle's path:
  an fsync takes 5 to 50 ms on a shared disk, and eight modules staging within a few cycles
  of each other held their cycles past their neighbours' liveness bound (links lost at the
  staging cycles in ``benchmarks/bench_flash.py``). The image is checked first
  (``Flash.acceptable``, no write) and the Rollout told ``verified``, so the last segment goes
  on while the flash writes; the flash's result (``staged``) reaches the Rollout at the
  host's next input (a frame, a Hello, a cycle start); the switch waits for the writes
  queued before it;
* each cycle it gives the runtime's liveness the digests the Rollout tolerates (the switch
  window), and its Hellos state the running program's version.

The trial itself (confirm after clean cycles, reject on a fault) stays the module host's
(``TrialWatch``); it tells this host with :meth:`confirmed` and :meth:`reverted`.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import queue
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable
from typing import Any

from dh2rt.compiler import load_image
from dh2rt.errors import DH2Error, FlashError, SignedImageError
from dh2rt.flash.pacing import Pacing
from dh2rt.flash.reports import describe_path
from dh2rt.flash.rollout import Role, Rollout
from dh2rt.flash.values import Action, Declined, DropPartial, ImageInfo, Partial, Persist, Program, Send, Stage, Switch
from dh2rt.program import CompiledProgram
from dh2rt.runtime import ModuleRuntime
from dh2rt.signed_image import parse as parse_image
from dh2rt.wire.frame import Hello
from dh2rt.wire.transfer import image_id
from firmware.flash.slots import PARTIAL_IMAGE, PARTIAL_INFO, Boot, Flash, Staged, replace_file

#: What the module host does at the switch: run this program (booted from the flash).
OnSwitch = Callable[[CompiledProgram, Boot], None]


class FlashWriter:
    """The flash's writes in a thread of their own, in the order given (see the module docs).

    :meth:`submit` queues ``work``; once it ran, ``then(result, error)`` is kept for
    :meth:`collect`, which the host calls on its own thread: the Rollout is never touched from
    the writer's. :meth:`flush` waits for everything queued (the switch needs the staged image
    on the flash). ``threaded()`` false (a runtime on a virtual clock, which the tests step:
    its time does not pass while the disk works): ``work`` runs at once, in the caller's
    thread, its follow-up at the next :meth:`collect` as with the thread."""

    def __init__(self, threaded: Callable[[], bool] = lambda: True) -> None:
        self.threaded = threaded
        self._jobs: queue.Queue[tuple[Callable[[], Any], Callable[[Any, BaseException | None], None] | None]] = (
            queue.Queue()
        )
        self._done: deque[tuple[Callable[[Any, BaseException | None], None], Any, BaseException | None]] = deque()
        self._thread: threading.Thread | None = None

    def submit(self, work: Callable[[], Any], then: Callable[[Any, BaseException | None], None] | None = None) -> None:
        if not self.threaded() and self._jobs.unfinished_tasks == 0:
            self._finish(work, then)
            return
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="dh2rt-flash-writer", daemon=True)
            self._thread.start()
        self._jobs.put((work, then))

    def collect(self) -> None:
        """Run the follow-ups of the writes done (on the caller's thread)."""
        while self._done:
            then, result, error = self._done.popleft()
            then(result, error)

    def flush(self) -> None:
        """Wait for every write queued, then run their follow-ups."""
        self._jobs.join()
        self.collect()

    def _run(self) -> None:
        while True:
            work, then = self._jobs.get()
            self._finish(work, then)
            self._jobs.task_done()

    def _finish(self, work: Callable[[], Any], then: Callable[[Any, BaseException | None], None] | None) -> None:
        try:
            result, error = work(), None
        except Exception as exc:  # handed to the host's thread, which decides
            result, error = None, exc
        if then is not None:
            self._done.append((then, result, error))


class RolloutHost:
    """The rollout of one running module (see the module docs)."""

    def __init__(
        self,
        rt: ModuleRuntime,
        flash: Flash,
        boot: Boot,
        on_switch: OnSwitch,
        *,
        connectors: Iterable[int],
        pacing: Pacing,
        segment_size: int,
        latency: float,
        cycle_started: float | None = None,
        in_cycle: bool = False,
    ) -> None:
        self.rt = rt
        self.flash = flash
        self.on_switch = on_switch
        self.directory = flash.directory
        signed = flash.image(boot.slot)
        try:
            running = Program.from_image(signed) if signed is not None else Program(boot.version, boot.digest)
        except SignedImageError:
            running = Program(boot.version, boot.digest)
        if running.digest != boot.digest:  # not the image booted: nothing to offer
            running = Program(boot.version, boot.digest)
        self._partial = self._load_partial()
        staged = flash.held
        self.rollout = Rollout(
            connectors,
            running,
            pacing=pacing,
            segment_size=segment_size,
            partial=None if staged is not None else self._partial,
            staged=staged,
            reverted=[image_id(i) for i in flash.reverted],
            latency=latency,
            connector_name=rt.program.profile.connector_name,
        )
        if cycle_started is not None:  # opened between cycles: frames go out before the next tick
            self.rollout.join_cycle(cycle_started, rt.cycle_period)
        self.log: list[str] = []
        self.stages = 0
        #: between a cycle's start and its link frames going out, transfer frames wait here
        self._holding = in_cycle  # opened after a cycle's start, before its link frames went
        self._held: list[Send] = []
        self.writer = FlashWriter(threaded=lambda: rt.clock is time.monotonic)
        #: what the log said last of this module's name and switch instant
        self._said: tuple[object, object] = (None, None)
        #: the staged image's program, loaded when it was staged: (its digest, the program)
        self._prepared: tuple[bytes, CompiledProgram] | None = None
        #: images refused at their offer, before a byte crossed (a rollback, a busy trial), by
        #: verdict: with the flash's refusals, the module's count of refused images
        self.declined: Counter[str] = Counter()
        #: the running program came from a switch of this process (its trial is the rollout's)
        self.switched = False
        rt.liveness.version = boot.version
        rt.observer = self
        for c in rt.transport.links:
            self.attached(c)

    # -- inputs from the runtime (LinkObserver) ---------------------------------------------

    def cycle_start(self, rt: ModuleRuntime, now: float) -> None:
        self.writer.collect()
        self._holding = True  # the cycle's hormones go first: see cycle_sent
        self._do(self.rollout.tick(now))
        rt.liveness.tolerated = self.rollout.tolerated()

    def cycle_sent(self, rt: ModuleRuntime) -> None:
        """The runtime sent the cycle's link frames: the transfer frames held back since its
        start follow them, in order. The pacing keeps the line free for the hormones at each
        cycle start; sent at the tick, before the engine ran, up to a cycle's budget of
        transfer bytes (16 ms at 115,200 baud) went ahead of the cycle's hormones."""
        self._holding = False
        held, self._held = self._held, []
        for send in held:
            self._send(send)

    def hello(self, connector: int, remote: int, hello: Hello, now: float) -> None:
        self.writer.collect()
        self._do(self.rollout.hello(connector, remote, hello.version, hello.digest, now))

    def link_down(self, connector: int, now: float) -> None:
        self.writer.collect()
        self._do(self.rollout.link_down(connector, now))

    def attached(self, connector: int) -> None:
        self.writer.collect()
        self._do(self.rollout.attach(connector, self.rt.clock()))

    def detached(self, connector: int) -> None:
        self.writer.collect()
        self._do(self.rollout.detach(connector, self.rt.clock()))

    def on_transfer(self, connector: int, payload: bytes, arrived: float) -> None:
        self.writer.collect()
        # when it arrived, not when it was read: a COMMIT's remaining time counts from then
        self._do(self.rollout.receive(connector, payload, arrived))

    # -- the trial, from the module host -----------------------------------------------------

    def confirmed(self) -> None:
        self.writer.collect()
        self._do(self.rollout.confirmed(self.rt.clock()))

    def reverted(self, reason: str) -> None:
        self.writer.collect()
        self._do(self.rollout.reverted(reason, self.rt.clock()))

    # -- actions ---------------------------------------------------------------------------

    def _do(self, actions: list[Action]) -> None:
        for action in actions:
            match action:
                case Send():
                    if self._holding:
                        self._held.append(action)
                    else:
                        self._send(action)
                case Persist(info, offset, data):
                    self.writer.submit(functools.partial(self._persist, info, offset, data))
                case DropPartial():
                    self.writer.submit(self._drop_partial)
                case Stage(_, data):
                    self._stage(data)
                case Switch(program):
                    self._switch(program)
                case Declined(version, verdict, reason):
                    self.declined[verdict] += 1
                    self._note(f"offer of version {version} refused ({verdict}): {reason}")
        self._say_name_and_instant()

    def _send(self, send: Send) -> None:
        # stamped as it leaves: a COMMIT states the time left from now
        self.rt.transport.send_raw(send.connector, send.frame(self.rt.clock()))

    def _say_name_and_instant(self) -> None:
        """Log this module's name (its path, as every report prints it) once an OFFER told
        it, and the agreed switch instant (on CLOCK_MONOTONIC, as trace records' ``t``) once
        a COMMIT did: what a reader of the logs needs to check the switch."""
        name, at = self.rollout.name, self.rollout.switch_at
        said_name, said_at = self._said
        if name is not None and name != said_name:
            self._note(f"named {describe_path(name, self.rt.program.profile.connector_name)}")
        if at is not None and at != said_at:
            # how far ahead: a module that learns the instant after it passed switches at once
            self._note(f"switch agreed at t={at:.6f} ({(at - self.rt.clock()) * 1000:+.1f} ms from now)")
        self._said = (name, at)

    def _stage(self, data: bytes) -> None:
        """Check the image here (the Rollout passes it on once it passes), then check and
        write it on the writer's thread (fsyncs: see the module docs); the flash's result goes
        to the Rollout at the next input."""
        self.stages += 1
        if self.flash.acceptable(data):  # checked again as it is written; passed on meanwhile
            self._do(self.rollout.verified(self.rt.clock()))
        self.writer.submit(
            lambda: self.flash.stage(data, hold=True), lambda staged, error: self._staged(data, staged, error)
        )

    def _staged(self, data: bytes, staged: Staged | None, error: BaseException | None) -> None:
        if self.rollout.role is not Role.STAGING:  # a newer image took its place meanwhile
            self._note("an image written to the flash was given up for a newer one meanwhile")
            return
        if error is not None:
            if not isinstance(error, DH2Error):
                raise error
            # a trial runs (the rollout declines BUSY before this)
            self._note(f"image not staged: {error}")
            self._do(self.rollout.staged(False, "busy", str(error), self.rt.clock()))
            return
        assert staged is not None
        verdict = str(staged.verdict)
        if staged.accepted:
            self._note(f"image staged in slot {staged.slot}: waits for the switch")
            # loaded now, not at the switch: every module switches in one cycle, and on a
            # small processor shared by many (the loop) their loads at once hold cycles up
            image = parse_image(data)
            with contextlib.suppress(DH2Error):  # a program that does not load fails its trial at the switch
                self._prepared = (image.digest, load_image(image.program()))
        else:
            self._note(f"image refused ({verdict}): {staged.reason}")
        self._do(self.rollout.staged(staged.accepted, verdict, staged.reason, self.rt.clock()))

    def _switch(self, program: Program) -> None:
        self.writer.flush()  # the partial image dropped before the trial's boot is counted
        # the boot is counted on the flash before the new program runs (Flash.start_trial)
        boot = self.flash.start_trial()
        if boot.digest != program.digest:
            raise FlashError(f"the flash boots {boot.digest.hex()}, the rollout switched to {program.digest.hex()}")
        prepared, self._prepared = self._prepared, None
        compiled = prepared[1] if prepared is not None and prepared[0] == boot.digest else load_image(boot.program)
        self.rt.switch_program(
            compiled, boot.version, f"switched to program {compiled.name} version {boot.version} (slot {boot.slot})"
        )
        self.switched = True
        self.on_switch(compiled, boot)

    def _note(self, message: str) -> None:
        self.rt.log.append(f"cycle {self.rt.cycle}: rollout: {message}")

    # -- the partial image ------------------------------------------------------------------

    def _persist(self, info: ImageInfo, offset: int, data: bytes) -> None:
        files = self.flash.files
        if offset == 0:
            replace_file(files, PARTIAL_IMAGE, data)
            doc = {
                "image": info.image.hex(),
                "version": info.version,
                "length": info.length,
                "segment_size": info.segment_size,
            }
            replace_file(files, PARTIAL_INFO, json.dumps(doc, sort_keys=True).encode() + b"\n")
            return
        path = self.directory / PARTIAL_IMAGE
        with open(path, "r+b") as f:
            f.seek(offset)
            f.write(data)
            f.flush()
            os.fsync(f.fileno())

    def _drop_partial(self) -> None:
        for name in (PARTIAL_INFO, PARTIAL_IMAGE):
            with contextlib.suppress(FileNotFoundError):
                (self.directory / name).unlink()

    def _load_partial(self) -> Partial | None:
        """The image received in part before a restart: whole segments only (a write cut
        short by a power cut is taken again)."""
        try:
            doc = json.loads((self.directory / PARTIAL_INFO).read_text(encoding="utf-8"))
            data = (self.directory / PARTIAL_IMAGE).read_bytes()
            info = ImageInfo(bytes.fromhex(doc["image"]), int(doc["version"]), int(doc["length"]),
                             int(doc["segment_size"]))  # fmt: skip
        except (OSError, ValueError, KeyError, TypeError):
            return None
        if info.segment_size < 1 or info.length < 1:
            return None
        data = data[: info.length]
        if len(data) < info.length:
            data = data[: len(data) // info.segment_size * info.segment_size]
        return Partial(info, data) if data else None
