"""The module's flash: trial boots, confirmation, reverts, refusals, and a power cut at every
write step."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from dh2rt import signed_image as si
from dh2rt.compiler import compile_file
from dh2rt.errors import FlashError
from dh2rt.signed_image import Verdict
from firmware.flash import slots as flash_slots
from firmware.flash.slots import Boot, DirectoryFiles, Flash, FlashFiles

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@dataclass(frozen=True)
class Programs:
    """Three program images and a trusted key to sign them with."""

    key: bytes
    old: bytes
    new: bytes
    newer: bytes

    @property
    def trust(self) -> list[bytes]:
        return [si.public_key(self.key)]

    def sign(self, program: bytes, version: int) -> bytes:
        return si.pack(program, version, self.key)


@pytest.fixture(scope="module")
def programs() -> Programs:
    images = [compile_file(str(EXAMPLES / f"{n}.dh2")).image for n in ("caterpillar", "locomotion", "legs_to_snake")]
    return Programs(si.new_private_key(), *images)


def _flash(
    directory: Path,
    programs: Programs,
    *,
    allow_unsigned: bool = False,
    trial_cycles: int = flash_slots.DEFAULT_TRIAL_CYCLES,
) -> Flash:
    return Flash(directory, programs.trust, allow_unsigned=allow_unsigned, trial_cycles=trial_cycles)


@pytest.fixture
def running(tmp_path: Path, programs: Programs) -> Path:
    """A flash whose confirmed program is ``old``, version 1."""
    assert _flash(tmp_path, programs).stage(programs.sign(programs.old, 1)).accepted
    return tmp_path


def _snapshot(directory: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir())}


def _state(directory: Path) -> dict[str, object]:
    doc: dict[str, object] = json.loads((directory / "state.json").read_text())
    return doc


# ---------------------------------------------------------------- the life cycle


def test_the_first_image_is_confirmed_at_once(tmp_path: Path, programs: Programs) -> None:
    staged = _flash(tmp_path, programs).stage(programs.sign(programs.old, 1))
    assert (staged.accepted, staged.verdict, staged.slot) == (True, Verdict.OK, "a")
    boot = _flash(tmp_path, programs).boot()
    assert (boot.program, boot.slot, boot.version, boot.trial) == (programs.old, "a", 1, False)


def test_a_staged_image_boots_on_trial_and_is_confirmed(running: Path, programs: Programs) -> None:
    flash = _flash(running, programs, trial_cycles=40)
    assert flash.boot().program == programs.old
    staged = flash.stage(programs.sign(programs.new, 2))
    assert (staged.accepted, staged.slot) == (True, "b")
    assert flash.running is not None and flash.running.program == programs.old  # still runs until restart
    after_restart = _flash(running, programs)
    boot = after_restart.boot()
    assert (boot.program, boot.slot, boot.version, boot.trial, boot.trial_cycles) == (programs.new, "b", 2, True, 40)
    assert after_restart.on_trial
    after_restart.confirm()
    assert not after_restart.on_trial
    assert _state(running)["trial"] is None
    again = _flash(running, programs).boot()
    assert (again.program, again.slot, again.trial) == (programs.new, "b", False)


def test_a_restart_before_confirmation_reverts(
    running: Path, programs: Programs, caplog: pytest.LogCaptureFixture
) -> None:
    _flash(running, programs).stage(programs.sign(programs.new, 2))
    assert _flash(running, programs).boot().trial  # ... and the module crashes or restarts
    flash = _flash(running, programs)
    with caplog.at_level(logging.WARNING, logger=flash_slots.__name__):
        boot = flash.boot()
    assert (boot.program, boot.slot, boot.trial, flash.reverts) == (programs.old, "a", False, 1)
    assert "restarted before it was confirmed" in caplog.text
    assert _flash(running, programs).boot().program == programs.old


def test_a_switch_counts_the_held_images_boot_before_it_runs(running: Path, programs: Programs) -> None:
    """A rollout's switch boots the held image on trial with its boot counted on the flash
    before it returns: a new program that kills its process at once reverts at the restart,
    rather than being held and switched to again (tests/hil/test_flash_recovery.py kills a
    module at its switch)."""
    flash = _flash(running, programs)
    flash.boot()
    image = programs.sign(programs.new, 2)
    assert flash.stage(image, hold=True).accepted
    restarted = _flash(running, programs)  # a restart before the switch: the image is still held
    assert (restarted.boot().program, restarted.held, restarted.reverts) == (programs.old, image, 0)
    boot = flash.start_trial()
    assert (boot.program, boot.version, boot.trial) == (programs.new, 2, True)
    restarted = _flash(running, programs)  # counted: a restart before confirmation reverts
    assert (restarted.boot().program, restarted.held, restarted.reverts) == (programs.old, None, 1)


def test_a_fault_on_trial_reverts_at_once(running: Path, programs: Programs, caplog: pytest.LogCaptureFixture) -> None:
    _flash(running, programs).stage(programs.sign(programs.new, 2))
    flash = _flash(running, programs)
    assert flash.boot().trial
    with caplog.at_level(logging.WARNING, logger=flash_slots.__name__):
        back = flash.reject("receptor fault in cycle 12")
    assert (back.program, back.trial, flash.reverts) == (programs.old, False, 1)
    assert "receptor fault in cycle 12" in caplog.text
    assert _flash(running, programs).boot().program == programs.old
    with pytest.raises(FlashError, match="nothing runs on trial"):
        flash.confirm()


def test_the_next_image_goes_to_the_other_slot(running: Path, programs: Programs) -> None:
    for version, program, slot in ((2, programs.new, "b"), (3, programs.newer, "a"), (4, programs.old, "b")):
        _flash(running, programs).stage(programs.sign(program, version))
        flash = _flash(running, programs)
        assert (flash.boot().slot, flash.on_trial) == (slot, True)
        flash.confirm()
    assert _flash(running, programs).boot() == Boot(programs.old, "b", 4, si.parse(programs.old).digest)


def test_a_new_image_replaces_a_pending_trial(running: Path, programs: Programs) -> None:
    _flash(running, programs).stage(programs.sign(programs.new, 2))
    _flash(running, programs).stage(programs.sign(programs.newer, 3))
    boot = _flash(running, programs).boot()
    assert (boot.program, boot.version, boot.trial) == (programs.newer, 3, True)


def test_no_image_is_staged_while_a_trial_runs(running: Path, programs: Programs) -> None:
    _flash(running, programs).stage(programs.sign(programs.new, 2))
    flash = _flash(running, programs)
    flash.boot()
    with pytest.raises(FlashError, match="a trial is running"):
        flash.stage(programs.sign(programs.newer, 3))


def test_a_trial_of_zero_cycles_is_a_trial_still(running: Path, programs: Programs) -> None:
    _flash(running, programs).stage(programs.sign(programs.new, 2), trial_cycles=0)
    boot = _flash(running, programs).boot()
    assert (boot.trial, boot.trial_cycles) == (True, 0)
    with pytest.raises(FlashError, match="must be 0 or more"):
        _flash(running, programs).stage(programs.sign(programs.new, 2), trial_cycles=-1)


# ---------------------------------------------------------------- refusals


def _one_bit_changed(data: bytes, offset: int) -> bytes:
    changed = bytearray(data)
    changed[offset] ^= 0x01
    return bytes(changed)


def test_bad_images_are_refused_counted_logged_and_change_nothing(
    running: Path, programs: Programs, caplog: pytest.LogCaptureFixture
) -> None:
    flash = _flash(running, programs)
    flash.boot()
    good = programs.sign(programs.newer, 3)
    cases = [
        (programs.newer, Verdict.UNSIGNED, "only signed ones"),
        (_one_bit_changed(good, 100), Verdict.TAMPERED, "altered after signing"),
        (_one_bit_changed(good, len(good) - 1), Verdict.TAMPERED, "altered after signing"),
        (si.pack(programs.newer, 3, si.new_private_key()), Verdict.WRONG_KEY, "not in the trust store"),
        (programs.sign(programs.newer, 0), Verdict.ROLLBACK, "version 0 is lower than the confirmed 1"),
        (b"\x00" * 50, Verdict.MALFORMED, "not a DH2 program image"),
        (good[:200], Verdict.MALFORMED, "cut short"),
    ]
    before = _snapshot(running)
    for data, verdict, reason in cases:
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger=flash_slots.__name__):
            staged = flash.stage(data)
        assert (staged.accepted, staged.verdict, staged.slot) == (False, verdict, None)
        assert reason in staged.reason and reason in caplog.text and verdict in caplog.text
        assert flash.last_refusal == f"{verdict}: {staged.reason}"
        assert _snapshot(running) == before
        assert flash.running is not None and flash.running.program == programs.old
    assert flash.refused == {
        Verdict.UNSIGNED: 1,
        Verdict.TAMPERED: 2,
        Verdict.WRONG_KEY: 1,
        Verdict.ROLLBACK: 1,
        Verdict.MALFORMED: 2,
    }
    assert _flash(running, programs).boot().program == programs.old


def test_a_lower_version_than_a_confirmed_trial_is_refused(running: Path, programs: Programs) -> None:
    _flash(running, programs).stage(programs.sign(programs.new, 7))
    trial = _flash(running, programs)
    trial.boot()
    trial.confirm()
    assert _flash(running, programs).stage(programs.sign(programs.newer, 6)).verdict is Verdict.ROLLBACK
    assert _flash(running, programs).stage(programs.sign(programs.newer, 7)).accepted  # equal is no rollback


def test_unsigned_images_pass_only_when_allowed(tmp_path: Path, programs: Programs) -> None:
    assert _flash(tmp_path, programs).stage(programs.old).verdict is Verdict.UNSIGNED
    staged = _flash(tmp_path, programs, allow_unsigned=True).stage(programs.old)
    assert (staged.accepted, staged.verdict, staged.slot) == (True, Verdict.UNSIGNED, "a")
    staged = _flash(tmp_path, programs, allow_unsigned=True).stage(programs.new)
    assert (staged.accepted, staged.slot) == (True, "b")  # version 0 again: on trial
    flash = _flash(tmp_path, programs, allow_unsigned=True)
    assert flash.boot().program == programs.new
    flash.confirm()
    assert _flash(tmp_path, programs, allow_unsigned=True).stage(programs.sign(programs.newer, 1)).accepted


def test_unsigned_images_cannot_replace_a_signed_version(running: Path, programs: Programs) -> None:
    staged = _flash(running, programs, allow_unsigned=True).stage(programs.new)
    assert (staged.verdict, staged.reason) == (Verdict.ROLLBACK, "version 0 is lower than the confirmed 1")


# ---------------------------------------------------------------- today's program.img


def test_todays_unsigned_program_img_needs_allow_unsigned(tmp_path: Path, programs: Programs) -> None:
    (tmp_path / "program.img").write_bytes(programs.old)
    with pytest.raises(FlashError, match=r"program.img refused \(unsigned"):
        _flash(tmp_path, programs).boot()
    assert not (tmp_path / "state.json").exists()
    boot = _flash(tmp_path, programs, allow_unsigned=True).boot()
    assert (boot.program, boot.slot, boot.version, boot.trial) == (programs.old, "a", 0, False)
    assert (tmp_path / "a.img").read_bytes() == programs.old
    with pytest.raises(FlashError, match="confirmed program cannot boot: slot a: unsigned"):
        _flash(tmp_path, programs).boot()  # unsigned no longer allowed
    # from now on the slots rule: a signed version 1 goes on trial, and then unsigned may go
    assert _flash(tmp_path, programs, allow_unsigned=True).stage(programs.sign(programs.new, 1)).slot == "b"
    flash = _flash(tmp_path, programs)
    assert flash.boot().program == programs.new
    flash.confirm()
    assert _flash(tmp_path, programs).boot().program == programs.new


def test_a_signed_program_img_is_installed(tmp_path: Path, programs: Programs) -> None:
    (tmp_path / "program.img").write_bytes(programs.sign(programs.old, 4))
    boot = _flash(tmp_path, programs).boot()
    assert (boot.program, boot.version) == (programs.old, 4)


def test_an_empty_flash_has_nothing_to_boot(tmp_path: Path, programs: Programs) -> None:
    with pytest.raises(FlashError, match="no program to boot: the flash is empty"):
        _flash(tmp_path, programs).boot()


# ---------------------------------------------------------------- damage


def test_a_corrupt_state_record_is_named(running: Path, programs: Programs) -> None:
    (running / "state.json").write_text('{"format": 1, "confirmed": {"slot": "c"}}')
    with pytest.raises(FlashError, match=r"state.json is corrupt \(slot 'c'"):
        _flash(running, programs).boot()


def test_a_damaged_confirmed_slot_is_named(running: Path, programs: Programs) -> None:
    data = (running / "a.img").read_bytes()
    (running / "a.img").write_bytes(_one_bit_changed(data, 50))
    with pytest.raises(FlashError, match="the confirmed program cannot boot: slot a: tampered"):
        _flash(running, programs).boot()


def test_a_trial_slot_that_is_not_the_staged_image_reverts(running: Path, programs: Programs) -> None:
    _flash(running, programs).stage(programs.sign(programs.new, 2))
    (running / "b.img").write_bytes(programs.sign(programs.newer, 2))  # another image than recorded
    flash = _flash(running, programs)
    assert flash.boot().program == programs.old and flash.reverts == 1


# ---------------------------------------------------------------- power cuts


class PowerCut(BaseException):
    """The power fails (BaseException: nothing in the flash may catch it)."""


class _Inode:
    def __init__(self) -> None:
        self.data = b""
        self.durable = b""


class CrashFiles:
    """An in-memory directory that models what a power cut keeps. Writes land in the page
    cache (``data``) until ``sync`` makes them durable; renames change the directory until
    ``sync_dir`` makes its entries durable. ``cut_at`` fails the power at that step (a write
    cut halfway leaves half its bytes); :meth:`crash` then gives the medium as one of the
    ways a power cut may leave it."""

    MODES = ("lost", "torn", "kept")

    def __init__(self, files: dict[str, bytes] | None = None) -> None:
        self.entries: dict[str, _Inode] = {}
        for name, data in (files or {}).items():
            inode = self.entries[name] = _Inode()
            inode.data = inode.durable = data
        self.durable_entries = dict(self.entries)
        self.steps = 0
        self.cut_at: int | None = None

    def _step(self) -> None:
        if self.steps == self.cut_at:
            raise PowerCut
        self.steps += 1

    def read(self, name: str) -> bytes | None:
        inode = self.entries.get(name)
        return None if inode is None else inode.data

    def write(self, name: str, data: bytes) -> None:
        inode = self.entries.setdefault(name, _Inode())
        if self.steps == self.cut_at:
            inode.data = data[: len(data) // 2]
        self._step()
        inode.data = data

    def sync(self, name: str) -> None:
        self._step()
        self.entries[name].durable = self.entries[name].data

    def rename(self, source: str, target: str) -> None:
        self._step()
        self.entries[target] = self.entries.pop(source)

    def sync_dir(self) -> None:
        self._step()
        self.durable_entries = dict(self.entries)

    def crash(self, mode: str) -> CrashFiles:
        """The medium after the power came back: ``lost``: only what was synced survives;
        ``torn``: every rename survives but unsynced data is cut in half; ``kept``:
        everything survives (the process died, the power did not)."""
        if mode == "lost":
            return CrashFiles({name: inode.durable for name, inode in self.durable_entries.items()})
        if mode == "torn":
            return CrashFiles(
                {
                    name: inode.data if inode.data == inode.durable else inode.data[: len(inode.data) // 2]
                    for name, inode in self.entries.items()
                }
            )
        return CrashFiles({name: inode.data for name, inode in self.entries.items()})

    def snapshot(self) -> dict[str, bytes]:
        return {name: inode.data for name, inode in self.entries.items()}


Scenario = Callable[[Flash], object]


def _cut_everywhere(
    start: dict[str, bytes], scenario: Scenario, programs: Programs, bootable: set[bytes]
) -> list[tuple[int, str, str]]:
    """Run ``scenario`` on a flash holding ``start``, cutting the power at each of its
    write steps, in each crash mode; after each cut the flash must boot one of ``bootable``
    (twice: the first boot may be a trial that the second reverts). Returns the failures."""
    dry = CrashFiles(start)
    scenario(Flash(Path("flash"), programs.trust, files=dry))
    assert dry.steps > 0
    failures = []
    for cut in range(dry.steps):
        for mode in CrashFiles.MODES:
            files = CrashFiles(start)
            files.cut_at = cut
            with pytest.raises(PowerCut):
                scenario(Flash(Path("flash"), programs.trust, files=files))
            after = files.crash(mode)
            try:
                for _ in range(2):
                    boot = Flash(Path("flash"), programs.trust, files=after).boot()
                    if boot.program not in bootable:
                        failures.append((cut, mode, f"booted an unexpected program in slot {boot.slot}"))
            except FlashError as exc:
                failures.append((cut, mode, str(exc)))
    return failures


def _setup(programs: Programs, *steps: Scenario) -> dict[str, bytes]:
    files = CrashFiles()
    for step in steps:
        step(Flash(Path("flash"), programs.trust, files=files))
    return files.snapshot()


def _stage(data: bytes) -> Scenario:
    return lambda flash: flash.stage(data)


def _boot_and(then: str) -> Scenario:
    def scenario(flash: Flash) -> None:
        flash.boot()
        if then == "confirm":
            flash.confirm()
        elif then == "reject":
            flash.reject("fault")

    return scenario


def test_a_power_cut_at_every_step_of_staging_leaves_the_old_program(programs: Programs) -> None:
    start = _setup(programs, _stage(programs.sign(programs.old, 1)))
    scenario = _stage(programs.sign(programs.new, 2))
    assert _cut_everywhere(start, scenario, programs, {programs.old, programs.new}) == []


def test_a_power_cut_at_every_step_of_a_first_install_leaves_an_empty_or_full_flash(programs: Programs) -> None:
    start = {"program.img": programs.sign(programs.old, 1)}  # migration: staged on the first boot
    assert _cut_everywhere(start, lambda flash: flash.boot(), programs, {programs.old}) == []


def test_a_power_cut_at_every_step_of_a_trial_boot_confirm_and_reject(programs: Programs) -> None:
    start = _setup(programs, _stage(programs.sign(programs.old, 1)), _stage(programs.sign(programs.new, 2)))
    for then in ("boot", "confirm", "reject"):
        assert _cut_everywhere(start, _boot_and(then), programs, {programs.old, programs.new}) == [], then


def test_a_power_cut_while_replacing_a_pending_trial(programs: Programs) -> None:
    start = _setup(programs, _stage(programs.sign(programs.old, 1)), _stage(programs.sign(programs.new, 2)))
    scenario = _stage(programs.sign(programs.newer, 3))
    assert _cut_everywhere(start, scenario, programs, {programs.old, programs.new, programs.newer}) == []


def test_what_the_flash_reports_done_survives_a_power_cut(programs: Programs) -> None:
    """Each step is durable when it returns: a staged image boots on trial, a trial booted
    once is never booted again, and a confirmed program stays confirmed."""
    files = CrashFiles(_setup(programs, _stage(programs.sign(programs.old, 1))))
    assert Flash(Path("flash"), programs.trust, files=files).stage(programs.sign(programs.new, 2)).accepted
    files = files.crash("lost")
    assert Flash(Path("flash"), programs.trust, files=files).boot().trial
    files = files.crash("lost")
    flash = Flash(Path("flash"), programs.trust, files=files)
    assert (flash.boot().program, flash.reverts) == (programs.old, 1)
    files = CrashFiles(_setup(programs, _stage(programs.sign(programs.old, 1)), _stage(programs.sign(programs.new, 2))))
    flash = Flash(Path("flash"), programs.trust, files=files)
    flash.boot()
    flash.confirm()
    boot = Flash(Path("flash"), programs.trust, files=files.crash("lost")).boot()
    assert (boot.program, boot.trial) == (programs.new, False)


def test_the_crash_model_catches_a_careless_writer(programs: Programs, monkeypatch: pytest.MonkeyPatch) -> None:
    """Without the temporary file the same cuts break the flash: the test can fail."""

    def in_place(files: FlashFiles, name: str, data: bytes) -> None:
        files.write(name, data)
        files.sync(name)

    monkeypatch.setattr(flash_slots, "replace_file", in_place)
    start = _setup(programs, _stage(programs.sign(programs.old, 1)), _stage(programs.sign(programs.new, 2)))
    failures = _cut_everywhere(start, _boot_and("confirm"), programs, {programs.old, programs.new})
    assert any("corrupt" in reason for _, _, reason in failures)


class CutDirectoryFiles(DirectoryFiles):
    """The real directory, with the power cut before write step ``cut_at``."""

    def __init__(self, directory: Path, cut_at: int) -> None:
        super().__init__(directory)
        self.cut_at = cut_at
        self.steps = 0

    def _step(self) -> None:
        if self.steps == self.cut_at:
            raise PowerCut
        self.steps += 1

    def write(self, name: str, data: bytes) -> None:
        if self.steps == self.cut_at:
            super().write(name, data[: len(data) // 2])
        self._step()
        super().write(name, data)

    def sync(self, name: str) -> None:
        self._step()
        super().sync(name)

    def rename(self, source: str, target: str) -> None:
        self._step()
        super().rename(source, target)

    def sync_dir(self) -> None:
        self._step()
        super().sync_dir()


def test_a_cut_at_every_step_on_a_real_directory(tmp_path: Path, programs: Programs) -> None:
    """Stage, trial boot and confirm, interrupted at each step: the directory boots."""
    old, new = programs.sign(programs.old, 1), programs.sign(programs.new, 2)

    def update(directory: Path, cut_at: int) -> int:
        _flash(directory, programs).stage(old)
        files = CutDirectoryFiles(directory, cut_at)
        Flash(directory, programs.trust, files=files).stage(new)
        flash = Flash(directory, programs.trust, files=files)
        flash.boot()
        flash.confirm()
        return files.steps

    (tmp_path / "dry").mkdir()
    steps = update(tmp_path / "dry", -1)
    assert steps == 16  # stage: an image and the state record; boot and confirm: the state record
    for cut in range(steps):
        directory = tmp_path / f"cut{cut}"
        directory.mkdir()
        with pytest.raises(PowerCut):
            update(directory, cut)
        for _ in range(2):
            assert _flash(directory, programs).boot().program in (programs.old, programs.new), cut
