"""A module's flash: two program slots and a state record, written so that a power cut at any
step leaves a program to boot.

The flash is a directory (``[program] flash`` in ``module.toml``)::

    a.img, b.img    signed images (dh2rt.signed_image); one holds the confirmed program
    state.json      which slot is confirmed (its version and digest), and the trial, if any
    program.img     today's single image: read once to fill an empty flash, then ignored
    partial.img     an image being received over the links, and what it is (partial.json),
    partial.json    written by the rollout's host (firmware.flash.module_host)

Every file is replaced whole: written to ``NAME.tmp``, flushed and fsynced, renamed over
``NAME``, and the directory fsynced. A rename is atomic, so after a power cut each file is
either its old or its new self. A new image goes to the slot that is *not* confirmed, and
only then does the state record name it, so the confirmed slot is never written while it is
confirmed.

Trial boot: a staged image is booted once on trial (the state record counts the boot before
the program runs). The module confirms it (:meth:`Flash.confirm`) once it has run the
stated number of cycles with no fault and with its neighbours verified; a fault rejects it
(:meth:`Flash.reject`), and a boot that finds the trial already booted once (a crash or a
restart before confirmation) reverts to the confirmed slot. The first image of an empty
flash is confirmed at once: there is nothing to revert to.

Only images signed by a key of the trust store are accepted (unsigned ones only when the
configuration allows them, for development), and never one of a lower version than the
confirmed program. Refusals are counted by verdict, logged with their reason, and change
nothing on the flash. See docs/flashing.md.
"""

from __future__ import annotations

import json
import logging
import os
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

from dh2rt.errors import FlashError
from dh2rt.signed_image import Examination, SignedImage, Verdict, examine

log = logging.getLogger(__name__)

SLOTS = ("a", "b")
STATE_FILE = "state.json"
#: The single image a flash held before it had slots (``dh2rt image PROGRAM -o program.img``).
LEGACY_IMAGE = "program.img"
#: Files beside the slots: the image being received over the links, and what it is.
PARTIAL_IMAGE = "partial.img"
PARTIAL_INFO = "partial.json"
STATE_FORMAT = 1
#: Clean cycles a trial program runs before it is confirmed, unless the stage says otherwise.
DEFAULT_TRIAL_CYCLES = 100


def slot_file(slot: str) -> str:
    return f"{slot}.img"


# ---------------------------------------------------------------- files


class FlashFiles(Protocol):
    """The file operations the flash uses, one write step each, so that tests can cut the
    power between any two of them."""

    def read(self, name: str) -> bytes | None:
        """The file's bytes, or None if there is no such file."""

    def write(self, name: str, data: bytes) -> None:
        """Create or truncate the file and write ``data`` (not yet durable)."""

    def sync(self, name: str) -> None:
        """Flush the file's data to the medium (fsync)."""

    def rename(self, source: str, target: str) -> None:
        """Rename atomically, replacing ``target``."""

    def sync_dir(self) -> None:
        """Make the directory's entries durable (fsync on the directory)."""


class DirectoryFiles:
    """:class:`FlashFiles` on a real directory."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory

    def read(self, name: str) -> bytes | None:
        try:
            return (self.directory / name).read_bytes()
        except FileNotFoundError:
            return None

    def write(self, name: str, data: bytes) -> None:
        with (self.directory / name).open("wb") as f:
            f.write(data)
            f.flush()

    def sync(self, name: str) -> None:
        fd = os.open(self.directory / name, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    def rename(self, source: str, target: str) -> None:
        os.replace(self.directory / source, self.directory / target)

    def sync_dir(self) -> None:
        fd = os.open(self.directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def replace_file(files: FlashFiles, name: str, data: bytes) -> None:
    """Replace ``name`` with ``data`` so that a power cut leaves the old or the new file."""
    temporary = name + ".tmp"
    files.write(temporary, data)
    files.sync(temporary)
    files.rename(temporary, name)
    files.sync_dir()


# ---------------------------------------------------------------- the state record


@dataclass(frozen=True, slots=True)
class SlotRecord:
    """A program in a slot, as the state record names it."""

    slot: str
    version: int
    digest: bytes


@dataclass(frozen=True, slots=True)
class TrialRecord:
    """A program on trial: its slot, the clean cycles it must run, and how often it booted.
    ``hold``: staged by a rollout, it waits for the robot's agreed switch (a boot runs the
    confirmed program meanwhile; :meth:`Flash.start_trial` boots it at the switch)."""

    program: SlotRecord
    cycles: int
    boots: int = 0
    hold: bool = False


@dataclass(frozen=True, slots=True)
class FlashState:
    """What ``state.json`` holds: the confirmed program and the trial, if any."""

    confirmed: SlotRecord
    trial: TrialRecord | None = None

    def to_json(self) -> bytes:
        trial = None
        if self.trial is not None:
            trial = {**_record_json(self.trial.program), "cycles": self.trial.cycles, "boots": self.trial.boots}
            if self.trial.hold:
                trial["hold"] = True
        doc = {"format": STATE_FORMAT, "confirmed": _record_json(self.confirmed), "trial": trial}
        return json.dumps(doc, indent=1, sort_keys=True).encode() + b"\n"

    @classmethod
    def from_json(cls, data: bytes) -> FlashState:
        """Raises ValueError (or KeyError, TypeError) naming what is wrong."""
        doc = json.loads(data)
        if doc.get("format") != STATE_FORMAT:
            raise ValueError(f"format {doc.get('format')!r}, this dh2rt reads {STATE_FORMAT}")
        confirmed, trial = _record(doc["confirmed"]), doc["trial"]
        if trial is None:
            return cls(confirmed)
        hold = trial.get("hold", False)
        if type(hold) is not bool:
            raise ValueError(f"hold {hold!r} is not true or false")
        return cls(confirmed, TrialRecord(_record(trial), _count(trial, "cycles"), _count(trial, "boots"), hold))


def _record_json(record: SlotRecord) -> dict[str, Any]:
    return {"slot": record.slot, "version": record.version, "digest": record.digest.hex()}


def _record(doc: dict[str, Any]) -> SlotRecord:
    if doc["slot"] not in SLOTS:
        raise ValueError(f"slot {doc['slot']!r} is none of {', '.join(SLOTS)}")
    return SlotRecord(doc["slot"], _count(doc, "version"), bytes.fromhex(doc["digest"]))


def _count(doc: dict[str, Any], key: str) -> int:
    value = doc[key]
    if type(value) is not int or value < 0:
        raise ValueError(f"{key} {value!r} is not a count")
    return value


# ---------------------------------------------------------------- the flash


@dataclass(frozen=True, slots=True)
class Boot:
    """The program to run: its program image (for ``load_image``), where it came from, and
    whether it runs on trial (then confirm it after ``trial_cycles`` clean cycles)."""

    program: bytes
    slot: str
    version: int
    digest: bytes
    trial: bool = False
    trial_cycles: int = 0


@dataclass(frozen=True, slots=True)
class Staged:
    """What :meth:`Flash.stage` made of an image: accepted into ``slot``, or refused."""

    accepted: bool
    verdict: Verdict
    reason: str
    slot: str | None = None


class Flash:
    """The flash of one module: boots, stages, confirms and reverts programs. It owns the
    slots' life cycle: *confirmed* (one program), *trial pending* (a staged image not yet
    booted), *on trial* (this process booted the staged image), and back to *confirmed*
    by :meth:`confirm`, :meth:`reject`, or a boot that finds the trial booted before.

    ``trust`` holds the raw public keys whose images are accepted; ``allow_unsigned``
    accepts unsigned images too (development only). ``files`` replaces the directory's
    file operations (tests cut the power with it)."""

    def __init__(
        self,
        directory: Path,
        trust: Sequence[bytes] = (),
        *,
        allow_unsigned: bool = False,
        trial_cycles: int = DEFAULT_TRIAL_CYCLES,
        files: FlashFiles | None = None,
    ) -> None:
        if trial_cycles < 0:
            raise FlashError(f"trial_cycles {trial_cycles}: must be 0 or more")
        self.directory = directory
        self.trust = tuple(trust)
        self.allow_unsigned = allow_unsigned
        self.trial_cycles = trial_cycles
        self.files: FlashFiles = files if files is not None else DirectoryFiles(directory)
        #: Refused images by verdict, since this Flash was made.
        self.refused: Counter[Verdict] = Counter()
        #: The last refusal's reason.
        self.last_refusal: str | None = None
        #: Trials reverted (by a fault, a crash or a restart) since this Flash was made.
        self.reverts = 0
        #: signed images of the trials reverted since this Flash was made (a rollout never
        #: takes them again)
        self.reverted: list[bytes] = []
        #: a rollout's staged image that waits for the switch (found by :meth:`boot`), else None
        self.held: bytes | None = None
        self._running: Boot | None = None

    @property
    def running(self) -> Boot | None:
        """What the last :meth:`boot` (or :meth:`reject`) returned."""
        return self._running

    @property
    def on_trial(self) -> bool:
        return self._running is not None and self._running.trial

    # -------------------------------------------------------- boot

    def peek(self) -> tuple[str, bytes | None]:
        """What the flash would boot, without booting it (nothing is written): a line that
        says so, and the program image when it passes its checks (``--check-config``)."""
        state = self._read_state()
        if state is None:
            legacy = self.files.read(LEGACY_IMAGE)
            if legacy is None:
                return "empty: no program to boot", None
            exam = examine(legacy, self.trust)
            if not self._acceptable(exam):
                return f"{LEGACY_IMAGE} would be refused ({exam.verdict}: {exam.reason})", None
            version = exam.image.version if exam.image is not None else 0
            return f"{LEGACY_IMAGE} (version {version}, {exam.verdict}), installed at the first boot", exam.program
        checked = self._check_slot(state.confirmed)
        trial = "" if state.trial is None else f"; slot {state.trial.program.slot} waits for a trial boot"
        if isinstance(checked, str):
            return f"the confirmed program cannot boot: {checked}{trial}", None
        return f"slot {state.confirmed.slot}, version {state.confirmed.version}, confirmed{trial}", checked

    def boot(self) -> Boot:
        """The program to run now: a pending trial (its boot counted first), else the
        confirmed program. A trial booted before and never confirmed is reverted. Raises
        FlashError when no confirmed program passes its checks."""
        state = self._state()
        if state is None:
            legacy = self.files.read(LEGACY_IMAGE) is not None
            why = f"{LEGACY_IMAGE} refused ({self.last_refusal})" if legacy else "the flash is empty"
            raise FlashError(
                f"{self.directory}: no program to boot: {why}; "
                "stage a signed image (dh2rt image PROGRAM --sign KEY --version N)"
            )
        trial = state.trial
        self.held = None
        if trial is not None:
            checked = self._check_slot(trial.program) if trial.boots == 0 else "restarted before it was confirmed"
            if trial.hold and isinstance(checked, bytes):
                # staged by a rollout before its switch: the old program runs until then
                self.held = self.files.read(slot_file(trial.program.slot))
                log.info("%s: slot %s waits for the rollout's switch", self.directory, trial.program.slot)
                return self._boot_confirmed(state)
            if isinstance(checked, bytes):
                self._write_state(replace(state, trial=replace(trial, boots=trial.boots + 1)))
                log.info("%s: slot %s boots on trial", self.directory, trial.program.slot)
                self._running = _boot(trial.program, checked, trial=True, cycles=trial.cycles)
                return self._running
            state = self._revert(state, checked)
        return self._boot_confirmed(state)

    def _boot_confirmed(self, state: FlashState) -> Boot:
        checked = self._check_slot(state.confirmed)
        if isinstance(checked, str):
            raise FlashError(f"{self.directory}: the confirmed program cannot boot: {checked}")
        self._running = _boot(state.confirmed, checked)
        return self._running

    def _check_slot(self, record: SlotRecord) -> bytes | str:
        """The program image in ``record``'s slot, or why it may not boot."""
        data = self.files.read(slot_file(record.slot))
        if data is None:
            return f"slot {record.slot} is empty"
        exam = examine(data, self.trust)
        if not self._acceptable(exam) or exam.image is None or exam.program is None:
            return f"slot {record.slot}: {exam.verdict}: {exam.reason}"
        if (exam.image.version, exam.image.digest) != (record.version, record.digest):
            return (
                f"slot {record.slot} holds version {exam.image.version} ({exam.image.digest.hex()}), "
                f"not the version {record.version} ({record.digest.hex()}) the state record names"
            )
        return exam.program

    # -------------------------------------------------------- stage

    def start_trial(self) -> Boot:
        """The rollout's switch: boot the held image on trial, its boot counted on the flash
        before this returns (two fsyncs, on the switch cycle's path: a new program that kills
        its process in its first cycle must find its boot counted, and revert, not be switched
        to again after a restart). Raises FlashError when none is held."""
        state = self._read_state()
        trial = None if state is None else state.trial
        if state is None or trial is None or not trial.hold or trial.boots:
            raise FlashError(f"{self.directory}: no staged image waits for a switch")
        checked = self._check_slot(trial.program)
        if isinstance(checked, str):
            self._boot_confirmed(self._revert(state, checked))
            raise FlashError(f"{self.directory}: the staged image cannot boot: {checked}")
        self._write_state(replace(state, trial=replace(trial, boots=1, hold=False)))
        log.info("%s: slot %s boots on trial at the switch", self.directory, trial.program.slot)
        self.held = None
        self._running = _boot(trial.program, checked, trial=True, cycles=trial.cycles)
        return self._running

    def image(self, slot: str) -> bytes | None:
        """The signed image in ``slot`` as stored (a rollout offers the running one)."""
        return self.files.read(slot_file(slot))

    def stage(self, data: bytes, trial_cycles: int | None = None, *, hold: bool = False) -> Staged:
        """Check ``data`` (signature, trust, version) and write it to the slot that is not
        confirmed, to boot on trial at the next :meth:`boot` (after ``trial_cycles`` clean
        cycles, the Flash's default when None, it may be confirmed). An empty flash confirms
        its first image at once. Refused images change nothing. Raises FlashError while a
        trial runs (confirm or reject it first)."""
        if self.on_trial:
            raise FlashError(f"{self.directory}: a trial is running; confirm or reject it before staging another image")
        cycles = self.trial_cycles if trial_cycles is None else trial_cycles
        if cycles < 0:
            raise FlashError(f"trial_cycles {cycles}: must be 0 or more")
        return self._install(data, self._state(), cycles, hold)

    def acceptable(self, data: bytes) -> bool:
        """Whether :meth:`stage` would take ``data`` now (its checks, without writing or
        counting anything): a rollout passes an image on once this holds, while the flash
        writes it."""
        return not self.on_trial and self._refusal(examine(data, self.trust), self._state()) is None

    def _install(self, data: bytes, state: FlashState | None, cycles: int, hold: bool = False) -> Staged:
        """Write an image that passes its checks: on trial beside ``state``'s confirmed
        program, or confirmed at once into an empty flash (``state`` None)."""
        exam = examine(data, self.trust)
        refusal = self._refusal(exam, state)
        if refusal is not None:
            return self._refuse(*refusal)
        assert exam.image is not None  # an acceptable examination has its image
        image = exam.image
        slot = SLOTS[0] if state is None else _other(state.confirmed.slot)
        replace_file(self.files, slot_file(slot), data)
        record = SlotRecord(slot, image.version, image.digest)
        if state is None:
            self._write_state(FlashState(record))
            log.info("%s: slot %s (version %d) confirmed: the first program", self.directory, slot, image.version)
        else:
            self._write_state(replace(state, trial=TrialRecord(record, cycles, hold=hold)))
            log.info("%s: slot %s (version %d) staged for a trial boot", self.directory, slot, image.version)
        return Staged(True, exam.verdict, exam.reason, slot)

    def _acceptable(self, exam: Examination) -> bool:
        return exam.verdict is Verdict.OK or (exam.verdict is Verdict.UNSIGNED and self.allow_unsigned)

    def _refusal(self, exam: Examination, state: FlashState | None) -> tuple[Verdict, str] | None:
        if exam.verdict is Verdict.UNSIGNED and not self.allow_unsigned:
            return Verdict.UNSIGNED, "unsigned image, and this module accepts only signed ones"
        if not self._acceptable(exam):
            return exam.verdict, exam.reason
        image: SignedImage | None = exam.image
        if state is not None and image is not None and image.version < state.confirmed.version:
            return Verdict.ROLLBACK, f"version {image.version} is lower than the confirmed {state.confirmed.version}"
        return None

    def _refuse(self, verdict: Verdict, reason: str) -> Staged:
        self.refused[verdict] += 1
        self.last_refusal = f"{verdict}: {reason}"
        log.warning("%s: image refused (%s): %s", self.directory, verdict, reason)
        return Staged(False, verdict, reason)

    # -------------------------------------------------------- confirm and reject

    def confirm(self) -> None:
        """Make the program on trial the confirmed one (after its clean cycles)."""
        running = self._running_trial("confirm")
        self._trial_state(running)
        self._write_state(FlashState(SlotRecord(running.slot, running.version, running.digest)))
        self._running = replace(running, trial=False, trial_cycles=0)
        log.info("%s: slot %s (version %d) confirmed", self.directory, running.slot, running.version)

    def reject(self, reason: str) -> Boot:
        """Give up the program on trial (it faulted): the confirmed program is what the
        flash boots from now on, and what this returns to run in its place."""
        running = self._running_trial("reject")
        return self._boot_confirmed(self._revert(self._trial_state(running), reason))

    def _running_trial(self, what: str) -> Boot:
        if self._running is None or not self._running.trial:
            raise FlashError(f"{self.directory}: nothing runs on trial to {what}")
        return self._running

    def _trial_state(self, running: Boot) -> FlashState:
        """The state record, which must still name ``running`` as on trial."""
        state = self._read_state()
        trial = None if state is None else state.trial
        if state is None or trial is None or trial.program != SlotRecord(running.slot, running.version, running.digest):
            raise FlashError(f"{self.directory}: the state record no longer names slot {running.slot} as on trial")
        return state

    def _revert(self, state: FlashState, reason: str) -> FlashState:
        assert state.trial is not None
        trial = state.trial.program
        image = self.files.read(slot_file(trial.slot))
        if image is not None:
            self.reverted.append(image)
        reverted = FlashState(state.confirmed)
        self._write_state(reverted)
        self.reverts += 1
        log.warning(
            "%s: trial of slot %s (version %d) reverted to slot %s (version %d): %s",
            self.directory,
            trial.slot,
            trial.version,
            state.confirmed.slot,
            state.confirmed.version,
            reason,
        )
        return reverted

    # -------------------------------------------------------- the state record

    def _state(self) -> FlashState | None:
        """The state record; an empty flash is first filled from ``program.img`` (None
        when there is none, or it is refused)."""
        state = self._read_state()
        return self._migrate() if state is None else state

    def _read_state(self) -> FlashState | None:
        data = self.files.read(STATE_FILE)
        if data is None:
            return None
        try:
            return FlashState.from_json(data)
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise FlashError(f"{self.directory}/{STATE_FILE} is corrupt ({exc})") from None

    def _migrate(self) -> FlashState | None:
        """Fill an empty flash with today's ``program.img``, checked like any staged image
        (an unsigned one passes only with ``allow_unsigned``)."""
        legacy = self.files.read(LEGACY_IMAGE)
        if legacy is None:
            return None
        log.info("%s: an empty flash: installing %s", self.directory, LEGACY_IMAGE)
        return self._read_state() if self._install(legacy, None, 0).accepted else None

    def _write_state(self, state: FlashState) -> None:
        replace_file(self.files, STATE_FILE, state.to_json())


def _boot(record: SlotRecord, program: bytes, *, trial: bool = False, cycles: int = 0) -> Boot:
    return Boot(program, record.slot, record.version, record.digest, trial, cycles)


def _other(slot: str) -> str:
    return SLOTS[1] if slot == SLOTS[0] else SLOTS[0]
