"""The program a module runs, from power-up to power-off: ``dh2rt module --config module.toml``.

Three layers make up a module's main loop; each names the others: :meth:`dh2rt.engine.Engine.step`
is one cycle of the paper's Fig. 3 over the module's state (no I/O); :class:`dh2rt.runtime.ModuleRuntime`
runs those cycles on a real transport at the module's period, with liveness, sensors and servos;
``firmware/main_loop.py`` is the program a module boots (``dh2rt module --config module.toml``):
config, links, flash, control channel, then the runtime's cycles until power-off or a signal.

A physical module boots it (``docs/firmware.md``: a systemd unit on a Raspberry Pi-class
processor), and the HIL world starts the very same program for each of its modules, with a
config file of the same form plus a ``[hil]`` table (:mod:`firmware.module_toml`); for the
in-process transports the world runs :class:`ModuleHost` in a thread. The config is checked
before anything starts (every error names the key; ``--check-config`` checks and exits).

On its own (no ``[hil]`` control), the module exchanges Hellos with its neighbours for the
handshake time, then cycles at its period until SIGTERM or SIGINT, which end it cleanly with a
final status line. Its log is JSON Lines (one object a line: ``time``, ``module`` (its name,
for people), ``event`` (``status``, ``log``, ``error``, ``effect``, ``final``) and the
event's fields) on standard error or in ``[log] file``; ``[log] status_file`` holds the last
status, rewritten atomically. Under systemd it says READY once cycling, pings the watchdog
with each status and says STOPPING at the end (``sd_notify``).

Actuators: with ``servo_port`` the module drives its DOF1/DOF2 Dynamixel servos (ids
``servo_ids``) through dynamixel-sdk; without one it takes the stand-in (``driver``:
``recording`` records the commanded angles, ``none`` drives nothing). Servos that cannot be
opened (missing, wrong model, a bad bus) are reported as an actuator fault, and the module
runs its program without actuators rather than not at all.

Sensors (``S.name``; :mod:`firmware.sensors`): the servos' present position and load when
the program reads them, fixed stand-in readings for sensors with no device (``[sensors]``),
readings the world pushes, and values ``sense`` commands force.

Control channel: the typed commands of :mod:`firmware.control` arrive as JSON lines on stdin
(``go``: start cycling, at a CLOCK_MONOTONIC instant after exchanging Hellos until then, for
a number of cycles; ``attach``, ``detach``, ``inject``, ``sense`` (a sensor forced from then on),
``readings`` (what the world's physics measured for the module), ``hold`` (joint targets a
docking motion holds on its servos), ``status``, ``stop``); reports go out
as JSON lines on stdout (``ready``, ``status`` every ``status_every`` cycles, ``trace``,
``effect`` (at the end of the cycle a native asked it in), ``log``, ``error``, and ``final``
at exit). A malformed command is refused with
a log report naming the field. SIGTERM and SIGINT end the loop cleanly with a final report.
Exit codes: 0 after a clean stop (SIGTERM, or the end of a run of ``[hil] cycles``), 1
after a failure while running, 2 for a config that is wrong or names something that is not
there (a program image, a bus, a port, a device: ``--check-config`` names each one), 130 after
Ctrl-C (SIGINT), once the module has wound down as it does for SIGTERM.
"""

from __future__ import annotations

import contextlib
import gc
import json
import os
import queue
import signal
import socket
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import IO, TYPE_CHECKING, Any

from dh2rt.compiler import load_image
from dh2rt.errors import ControlProtocolError, DH2Error, ModuleConfigError
from dh2rt.profile import CONRO, Profile
from dh2rt.program import CompiledProgram
from dh2rt.runtime import HEALTH_EVERY, ModuleRuntime
from dh2rt.transport.base import FrameFamily, Inbound, PortEnd
from dh2rt.transport.registry import open_transport
from dh2rt.transport.registry import parse_spec as parse_transport_spec
from dh2rt.wire.frame import FrameCodec
from dh2rt.wire.motion import is_motion
from drivers.base import ModuleDriver
from drivers.recording import RecordingDriver
from firmware.config import ModuleConfig
from firmware.motion.host import NATIVES, MotionHost
from firmware.operator import OperatorChannel
from firmware.sensors import attach_sensors

if TYPE_CHECKING:
    import argparse

    from firmware.flash.door import RolloutDoor
    from firmware.flash.slots import Boot, Flash
    from firmware.motion.asking import SelfReach
    from firmware.motion.assimilating import SelfAssimilate
    from firmware.motion.floor_filter import FloorFilter
    from firmware.motion.foot import Foot
    from firmware.motion.member import Member
    from firmware.motion.readings import FloorPoses
    from firmware.negotiated_links import NegotiatedLinks
    from firmware.tracker_feed import TrackerFeed
from drivers.latch import Latch, LatchState
from firmware.control import (
    Attach,
    Command,
    Detach,
    Effect,
    Failure,
    Floor,
    Go,
    Hold,
    Inject,
    LatchAnswer,
    Log,
    OwnMotions,
    Readings,
    Ready,
    Report,
    Sense,
    Status,
    StatusRequest,
    Stop,
    TraceRecord,
    command_from_json,
    report_to_json,
)
from firmware.latch import open_latch

Reporter = Callable[[Report], None]
#: After its last cycle a module keeps reading until nothing came for this many cycle
#: periods, and for at most DRAIN_MOST_PERIODS (see ModuleRuntime.drain).
DRAIN_QUIET_PERIODS = 3
DRAIN_MOST_PERIODS = 50
#: Seconds a module under the HIL world may take to link its contacts before it is ready.
NEGOTIATE_S = 10.0
#: Periods the links must stay settled before a module counts its contacts linked.
SETTLED_PERIODS = 5


def open_driver(config: ModuleConfig) -> tuple[ModuleDriver | None, str | None]:
    """The module's driver: Dynamixel servos when ``servo_port`` is set, else the stand-in.

    Returns (driver, fault): a servo bus that cannot be opened gives (None, why).
    """
    if not config.servo_port:
        return (RecordingDriver() if config.driver == "recording" else None), None
    from drivers.dynamixel import DynamixelDriver

    dof1, dof2 = config.servo_ids
    try:
        driver = DynamixelDriver(
            config.servo_port, dof1_id=dof1, dof2_id=dof2, baudrate=config.servo_baud,
            expected_model=config.servo_model, latency_timer_ms=config.servo_latency_ms,
        )  # fmt: skip
        return driver, None
    except DH2Error as exc:
        return None, str(exc)


class ModuleHost:
    """Runs one module from a config, reading commands from a queue and reporting through
    a callback: the body of a module process, also run in a thread for in-process buses.

    ``on_cycle``, if given, is called with the runtime at the end of every cycle, after the
    host's own work (:meth:`end_cycle`): a place to watch a module cycle by cycle or to act on
    it at a chosen cycle (queue a command, stop it) without racing its loop. A caller that
    steps the runtime itself instead of :meth:`serve` calls :meth:`end_cycle` after each step
    and :meth:`flush` when it wants the reports out.
    """

    def __init__(
        self,
        config: ModuleConfig,
        commands: queue.Queue[Command],
        report: Reporter,
        on_cycle: Callable[[ModuleRuntime], None] | None = None,
        self_motion: bool | None = None,
        cpu_clock: Callable[[], float] = time.process_time,
    ) -> None:
        self.config = config
        self.commands = commands
        self.report = report
        self.on_cycle = on_cycle
        self.stop_event = threading.Event()
        self.failed = False
        #: the flash the program was booted from (None: the config's image), and what it booted
        self.flash: Flash | None = None
        self.boot: Boot | None = None
        self.program = self._load_program(config)
        self._trial = TrialWatch()
        #: a clean trial's confirmation handed to the flash's writer thread, not yet written
        self._confirming = False
        self.module = config.module
        self.cycles = config.cycles
        self.driver, driver_fault = open_driver(config)
        codec = FrameCodec(self.program.vocabulary, self.program.profile.connector_count)
        transport = open_transport(config.transport, codec, **config.bus_options)
        self.runtime = ModuleRuntime(
            self.program,
            transport,
            timer_phase=config.timer_phase,
            driver=self.driver,
            cycle_period=config.cycle_period,
            silence_cycles=config.silence_cycles,
            record=config.trace,
            module=self.module,
            name=config.label,
            cpu_clock=cpu_clock,
        )
        #: links negotiated over the connectors' local channels (on a bus), or None
        self.links: NegotiatedLinks | None = None
        if config.connector_channels:
            from firmware.channels import open_channels
            from firmware.negotiated_links import NegotiatedLinks

            rt = self.runtime
            try:
                self.links = NegotiatedLinks(
                    open_channels(config.connector_channels), transport, sorted(config.connector_channels),
                    rt.clock(), rt.attach, rt.detach, rt.log.append,
                )  # fmt: skip
            except BaseException:
                rt.close()
                raise
        try:
            attach_sensors(self.runtime, config, lambda: self.driver)
        except BaseException:
            self.runtime.close()
            raise
        #: the rollout of new programs over the links (a module booted from its flash)
        self.rollout: RolloutDoor | None = self._start_rollout()
        #: the operator's commands (dh2rt console): trusted keys as the flash's, the last
        #: counter accepted kept in the flash directory (docs/console.md)
        self.operator = OperatorChannel(self.runtime, config.trust, Path(config.flash) if config.flash else None)
        self._split_control()
        #: whether this module carries out its program's ``reach_dock`` itself
        #: (firmware.motion.asking); under the HIL world (control on stdio) the world still
        #: does (hil.reach_loop) unless told otherwise
        self.self_motion = config.control != "stdio" if self_motion is None else self_motion
        #: the last value of every reading the world pushed (the motion reads its infrared)
        self.own_readings: dict[str, float] = {}
        #: the overhead tracker's last report for this module's reach (the world fills it)
        self.floor_report: Floor | None = None
        #: the overhead tracker the module hears itself (module.toml [tracker]), or None
        self.tracker: TrackerFeed | None = self._open_tracker(config)
        #: whether the first floor built from the feed was logged
        self.tracker_floor_said = False
        #: the feed's reports smoothed ([tracker] alpha), or None: raw
        self.floor_filter: FloorFilter | None = None
        if config.tracker is not None and config.tracker.alpha is not None:
            from firmware.motion.floor_filter import FloorFilter

            self.floor_filter = FloorFilter(config.tracker.alpha)
        #: the joints as last read for a motion's ASK (a read that fails sends these), and
        #: how many reads failed
        self.last_angles: tuple[float, float] | None = None
        self.unread_angles = 0
        self.latch: _WorldLatch | _ModuleLatch = _module_latch(self)
        #: this module's docking motions (firmware.motion.host): the chains it is a member of,
        #: the reach it runs, its own trip once it is a released foot; what they hold on the
        #: joints was last sent to the servos as ``_own_held``
        self.motion = MotionHost(
            config.module, self.program.profile, _ServoBody(self), _OwnSenses(self), self.latch, self._log_line
        )
        self._own_held: dict[int, float] = {}
        if driver_fault is not None:
            self.runtime.actuator_fault = driver_fault
            self.runtime.stats.actuator_faults += 1
            self.runtime.log.append(f"actuator fault: {driver_fault}")
        self._logged = 0

    def _open_tracker(self, config: ModuleConfig) -> TrackerFeed | None:
        """The ``[tracker]`` feed, bound (a port that cannot be bound fails the start)."""
        spec = config.tracker
        if spec is None:
            return None
        from firmware.tracker_floor import open_feed

        try:
            feed = open_feed(spec, config.module)
        except OSError as exc:
            self.runtime.close()
            raise ModuleConfigError(
                f"[tracker] port: cannot listen on {spec.bind or '*'}:{spec.port} ({exc.strerror or exc})"
            ) from None
        except BaseException:
            self.runtime.close()
            raise
        host, port = feed.address
        smoothing = "raw" if spec.alpha is None else f"smoothed, alpha {spec.alpha:g}"
        self.runtime.log.append(
            f"tracker: the floor from UDP {host}:{port} (markers 0..{3 * spec.modules - 1}, "
            f"poses within {spec.max_age_s:g} s, {smoothing})"
        )
        return feed

    def serve(self) -> int:
        """Attach, report ready, wait for ``go``, cycle until done or stopped; 0 or 1."""
        rt = self.runtime
        try:
            for c, end in self.config.attach.items():
                rt.attach(c, end)
            if self.links is not None:
                self._negotiate_first_links()
            self.report(Ready())
            start_at: float | None = None
            while not self.stop_event.is_set():
                try:
                    cmd = self.commands.get(timeout=0.05)
                except queue.Empty:
                    continue
                if isinstance(cmd, Go):
                    start_at = cmd.at
                    if cmd.cycles is not ...:
                        self.cycles = cmd.cycles
                    break
                self._command(cmd)
            if not self.stop_event.is_set():
                linked = rt.handshake(self.config.handshake, until=start_at)
                if not linked:
                    self.report(Log("handshake: a peer is silent"))
                if start_at is not None and self.cycles is not None:
                    # started at an agreed instant: stop at one too, so that no module runs on
                    # after its neighbours stopped and takes their silence for a lost link
                    until = start_at + self.cycles * self.config.cycle_period
                    rt.run(
                        None, self.stop_event, self._cycled,
                        until=until, before_cycle=self._take_commands, start=start_at,
                    )  # fmt: skip
                    # what the neighbours sent in their last cycles is counted, not lost
                    period = self.config.cycle_period
                    rt.drain(DRAIN_QUIET_PERIODS * period, DRAIN_MOST_PERIODS * period)
                else:
                    rt.run(self.cycles, self.stop_event, self._cycled, before_cycle=self._take_commands)
        except Exception as exc:  # report it to the world rather than die silently
            self.failed = True
            self.report(Failure(f"{type(exc).__name__}: {exc} ({_where(exc)})"))
        finally:
            self.flush()
            # what was last commanded: the servos themselves may be gone by now
            targets = self.runtime.commanded if self.driver is not None else None
            final = Status(self._status(rt), final=True, failed=self.failed, targets=targets)
            if self.links is not None:
                self.links.close()
            if self.tracker is not None:
                self.tracker.close()
            rt.close()
            self.report(final)
        return 1 if self.failed else 0

    def _negotiate_first_links(self) -> None:
        """Before Ready: link every connector found in contact at power-up (the HIL world
        starts the robot when all are), for up to NEGOTIATE_S, or the handshake time on
        its own (links that come later are negotiated while it cycles)."""
        assert self.links is not None
        rt = self.runtime
        limit = NEGOTIATE_S if self.config.control == "stdio" else self.config.handshake
        start = rt.clock()
        steady = 0
        while not self.stop_event.is_set() and rt.clock() - start < limit:
            self.links.step(rt.clock())
            rt.listen(self.config.cycle_period)
            # settled for a few periods in a row: contacts have had time to be sensed
            steady = steady + 1 if self.links.settled else 0
            if steady >= SETTLED_PERIODS:
                return
        if not self.stop_event.is_set():
            self.report(Log(f"links: not every contact linked after {limit:g} s"))

    def _load_program(self, config: ModuleConfig) -> CompiledProgram:
        """The program to run: booted from the flash (its confirmed program, or a new one on
        trial), or the config's image. A trial program that does not even compile is
        rejected at once and the confirmed one runs."""
        if not config.flash:
            return load_image(config.image)
        from firmware.flash.slots import Flash

        self.flash = Flash(
            Path(config.flash), config.trust, allow_unsigned=config.allow_unsigned, trial_cycles=config.trial_cycles
        )
        self.boot = self.flash.boot()
        try:
            return load_image(self.boot.program)
        except DH2Error as exc:
            if not self.boot.trial:
                raise
            self.boot = self.flash.reject(f"the program does not load: {exc}")
            return load_image(self.boot.program)

    def _start_rollout(self) -> RolloutDoor | None:
        """Take part in rollouts (docs/flashing.md) when booted from a flash; the rollout's
        machinery loads when one concerns this module (:mod:`firmware.flash.door`)."""
        if self.flash is None or self.boot is None:
            return None
        from firmware.flash.door import RolloutDoor

        bitrate = int(self.config.bus_options.get("bitrate", 1_000_000))
        try:
            return RolloutDoor(self.runtime, self.flash, self.boot, self._switched, self.config.transport, bitrate)
        except ValueError as exc:  # a line too slow for the cycle: the program runs, no rollouts
            self.runtime.log.append(f"rollouts off: {exc}")
            return None

    def _switched(self, program: CompiledProgram, boot: Boot) -> None:
        """The rollout switched the running program (at a cycle start): it runs on trial."""
        self.program, self.boot = program, boot
        self._trial = TrialWatch()
        self._confirming = False

    def _check_trial(self, rt: ModuleRuntime) -> None:
        """A program on trial is confirmed after its clean cycles (no receptor or actuator
        fault, every neighbour verified); a fault rejects it, and the module stops so that
        its next start (systemd restarts it) boots the confirmed program."""
        if self.flash is None or self.boot is None or not self.boot.trial or self._confirming:
            return
        verdict = self._trial.cycle(rt, self.boot.trial_cycles)
        if verdict is not None and self.rollout is not None:
            self.rollout.settle()  # what the host queued (a partial image's drop) lands before the verdict's write
        if verdict == "clean":
            # the state record's write (two fsyncs) off the cycle's path where a rollout host
            # has its writer thread; the module says confirmed once it is on the flash
            if self.rollout is not None and self.rollout.write(
                self.flash.confirm, lambda _, error: self._confirmed(rt, error)
            ):
                self._confirming = True
            else:
                self.flash.confirm()
                self._confirmed(rt, None)
        elif verdict is not None and self.rollout is not None and self.rollout.switched:
            # switched to by a rollout: back to the confirmed program in the running loop,
            # and the entry point is told (its neighbours offer it again; it declines for good)
            boot = self.flash.reject(verdict)
            program = load_image(boot.program)
            note = f"program on trial rejected ({verdict}): back to version {boot.version}"
            rt.switch_program(program, boot.version, note)
            self.program, self.boot = program, boot
            self.rollout.reverted(verdict)
        elif verdict is not None:
            self.flash.reject(verdict)
            rt.log.append(f"program on trial rejected ({verdict}): the next start boots the confirmed one")
            self.failed = True
            self.stop_event.set()

    def _confirmed(self, rt: ModuleRuntime, error: BaseException | None) -> None:
        """The trial's confirmation is on the flash (or its write failed: raised here, on the
        module's thread, as a write done at once would raise; the next boot reverts)."""
        self._confirming = False
        if error is not None:
            raise error
        assert self.flash is not None
        self.boot = self.flash.running
        rt.log.append(f"program version {self.boot.version if self.boot else '?'} confirmed after its trial")
        if self.rollout is not None:
            self.rollout.confirmed()

    def program_status(self) -> dict[str, Any] | None:
        """Where the running program came from, for the status line."""
        if self.boot is None or self.flash is None:
            return None
        return {
            "slot": self.boot.slot,
            "version": self.boot.version,
            "digest": self.boot.digest.hex(),
            "trial": self.boot.trial,
            "sha256": self.program.hash,
            "refused": self._refused(),
            "reverts": self.flash.reverts,
        }

    def _refused(self) -> dict[str, int]:
        """Images refused, by verdict: by the flash (checked), and by the rollout at their
        offer (a rollback, before a byte crossed)."""
        assert self.flash is not None
        out = {str(k): v for k, v in self.flash.refused.items()}
        if self.rollout is not None:
            for verdict, n in self.rollout.declined.items():
                out[verdict] = out.get(verdict, 0) + n
        return out

    def _status(self, rt: ModuleRuntime) -> dict[str, Any]:
        status = rt.status()
        ends = rt.transport.held_ends()
        if ends:  # on a shared bus: the world's witness tells frames sent to nobody (hil.bus_witness)
            status["link_ends"] = [[e.link_id, e.side, e.since, e.until] for e in ends]
            status["link_ends_at"] = time.time()
        program = self.program_status()
        if program is not None:
            status["program"] = program
        status["operator"] = self.operator.core.counters
        if self.member.counts:
            status["motion"] = dict(self.member.counts)
        if self.tracker is not None:
            feed = self.tracker
            status["tracker"] = {"datagrams": feed.datagrams, "rejected": feed.rejected, "stale": feed.stale}
        return status

    def _split_control(self) -> None:
        """The control family has one handler a transport: the operator channel's, which
        registered first, keeps the operator's frames; motion frames (types 64..127) go to
        this module's motion member."""
        listening = self.operator.listening
        operator_frame = listening.handler
        listening.close()

        def on_control(frame: Inbound) -> None:
            if is_motion(frame.payload):
                self._on_motion(frame)
            else:
                operator_frame(frame)

        self.operator.listening = self.runtime.transport.listen(FrameFamily.CONTROL, on_control)

    @property
    def member(self) -> Member:
        """The docking chains this module is a member of (dh2rt.wire.motion): it answers for
        its joints, holds the targets it is sent and passes frames on along their route."""
        return self.motion.member

    @property
    def reach(self) -> SelfReach | SelfAssimilate | None:
        """The reach this module runs (the last one, done or not)."""
        return self.motion.reach

    @property
    def foot(self) -> Foot | None:
        """This module's own trip and creep once it is the released foot of a reach_and_dock."""
        return self.motion.foot

    def _on_motion(self, frame: Inbound) -> None:
        """A motion frame: send what the member answers or passes on; the targets it holds
        are written to the servos before the next cycle (or the joints are the program's)."""
        rt = self.runtime
        for out in self.motion.received(frame.connector, frame.payload, rt.cycle):
            rt.transport.send_raw(out.connector, out.frame)
        self._hold(rt)

    def _hold(self, rt: ModuleRuntime) -> None:
        """What the motions hold on the joints, to the servos if it changed."""
        joints = self.motion.joints
        if joints == self._own_held:
            return
        try:
            rt.hold(joints)
            self._own_held = dict(joints)
        except DH2Error as exc:  # a joint this body does not have
            self._log_line(f"motion: targets refused: {exc}")
            self.motion.member.held, self.motion.member.holding = {}, None

    def _start_reaches(self, rt: ModuleRuntime) -> None:
        """The program asked ``reach_dock`` or ``reach_and_dock`` this cycle: this module
        carries it out (firmware.motion.host), one at a time."""
        for kind, args in rt.effects:
            if kind in NATIVES:
                self.motion.start(kind, args, rt.engine.status, rt.cycle)

    def _step_motions(self, rt: ModuleRuntime) -> None:
        """Before each cycle: the motions make their steps (firmware.motion.host.MotionHost):
        their frames go out, what they hold goes to the servos, what they tell the world is
        reported."""
        for out in self.motion.before_cycle(rt.cycle):
            rt.transport.send_raw(out.connector, out.frame)
        self._hold(rt)
        effects, self.motion.effects = self.motion.effects, []
        for kind, args in effects:
            if kind == "release":  # a foot letting go: its own latch opens first
                self._release(int(args[0]))
            else:
                self.report(Effect(kind, args))

    def _log_line(self, line: str) -> None:
        self.runtime.log.append(f"cycle {self.runtime.cycle}: {line}")

    def _take_commands(self, rt: ModuleRuntime) -> None:
        """Just before each cycle: carry out the commands that came meanwhile (a ``sense``
        or pushed readings count in this very cycle); a motion gone silent gives the joints
        back (firmware.motion.member). The tracker's datagrams that came are taken."""
        if self.tracker is not None:
            self.tracker.poll()
        self._step_motions(rt)
        while True:
            try:
                cmd = self.commands.get_nowait()
            except queue.Empty:
                break
            self._command(cmd)

    def _cycled(self, rt: ModuleRuntime) -> None:
        self.end_cycle(rt)
        if self.on_cycle is not None:
            self.on_cycle(rt)

    def end_cycle(self, rt: ModuleRuntime) -> None:
        """The host's work at the end of a cycle: step the links' negotiation, watch a program
        on trial, retry servos that were not there, and report a status every
        ``status_every`` cycles (and what a native asked of the body at once)."""
        if self.links is not None:
            self.links.step(rt.clock())
        if self.self_motion and rt.effects:
            self._start_reaches(rt)
        self._check_trial(rt)
        if self.driver is None and self.config.servo_port and rt.cycle % HEALTH_EVERY == rt.health_offset:
            self._reopen_servos(rt)
        if rt.cycle % self.config.status_every == 0:
            self.flush()
            self.report(Status(self._status(rt)))
        elif rt.effects:  # what a native asks of the body goes out in the cycle it was asked
            self.flush()

    def _reopen_servos(self, rt: ModuleRuntime) -> None:
        """Servos that could not be opened are tried again (a bus that was busy or
        unpowered at boot); the module says so when its body comes back."""
        driver, fault = open_driver(self.config)
        if driver is None:
            rt.actuator_fault = fault
            return
        self.driver = driver
        rt.attach_driver(driver, f"servos opened on {self.config.servo_port}")

    def flush(self) -> None:
        """Report what the runtime gathered since the last flush: trace records, effects, log lines."""
        rt = self.runtime
        for rec in rt.records:
            rec["life"] = self.config.life
            self.report(TraceRecord(rec))
        rt.records.clear()
        for kind, args in rt.effects:
            if kind == "release" and isinstance(self.latch, _ModuleLatch) and args:
                self.latch.release(int(args[0]))  # the module's own latch opens; the link goes as before
            self.report(Effect(kind, list(args)))
        rt.effects.clear()
        log = rt.log
        if self._logged > len(log):
            self._logged = 0
        for line in log[self._logged :]:
            self.report(Log(line))
        self._logged = len(log)

    def _release(self, connector: int) -> None:
        """A foot lets go of ``connector`` (as a program's ``release`` does in :meth:`flush`): the
        module's own latch there opens; the effect goes to the world as before (which cuts the
        link, or with a latch it emulates, waits for the horn to open)."""
        if isinstance(self.latch, _ModuleLatch):
            self.latch.release(connector)
        self.report(Effect("release", [connector]))

    def _command(self, cmd: Command) -> None:
        rt = self.runtime
        try:
            if isinstance(cmd, Stop):
                self.stop_event.set()
            elif isinstance(cmd, Attach):
                rt.attach(cmd.connector, cmd.end)
            elif isinstance(cmd, Detach):
                rt.detach(cmd.connector)
            elif isinstance(cmd, Inject):
                from dh2rt.events import parse_hormone  # the HIL world's commands only

                rt.inject(parse_hormone(cmd.hormone, self.program.vocabulary, "inject command"))
            elif isinstance(cmd, Readings):
                rt.push_readings(cmd.values)
                self.own_readings.update(cmd.values)
            elif isinstance(cmd, LatchAnswer):
                self.latch.answered(cmd)
            elif isinstance(cmd, OwnMotions):
                self.self_motion = True
            elif isinstance(cmd, Floor):
                self.floor_report = cmd
            elif isinstance(cmd, Hold):
                rt.hold(cmd.targets)
            elif isinstance(cmd, Sense):
                rt.sense(cmd.sensor, cmd.value)
                rt.log.append(f"cycle {rt.cycle}: sense: S.{cmd.sensor} = {cmd.value} from now on")
            elif isinstance(cmd, StatusRequest):
                self.report(Status(self._status(rt)))
        except DH2Error as exc:
            self.report(Log(f"command {cmd!r} refused: {exc}"))


class _ServoBody:
    """What a module reports of itself to a motion's ASK (firmware.motion.member.Body)."""

    def __init__(self, host: ModuleHost) -> None:
        self.host = host

    def links(self) -> tuple[int, ...]:
        """For each connector, the peer's connector linked there, 0 for none."""
        return tuple(self.host.runtime.engine.status)

    def angles(self) -> tuple[float, ...]:
        """DOF1 and DOF2 as the servos measure them; when a read fails (the emulated servo
        bus is busy with the runtime's own traffic), as last read, or as last commanded."""
        host = self.host
        rt = host.runtime
        if host.driver is not None:
            try:
                host.last_angles = host.driver.read_positions()
                return host.last_angles
            except DH2Error as exc:
                host.unread_angles += 1
                if host.unread_angles == 1 or host.unread_angles % 100 == 0:
                    rt.log.append(f"cycle {rt.cycle}: motion: servos unreadable ({host.unread_angles}: {exc})")
        return host.last_angles or rt.commanded


class _OwnSenses:
    """What the asking module senses of itself for its reach (firmware.motion.asking.OwnSenses)."""

    def __init__(self, host: ModuleHost) -> None:
        self.host = host

    def angles(self) -> tuple[float, ...]:
        return _ServoBody(self.host).angles()

    def infrared(self) -> dict[str, float]:
        """Each connector's pair as last measured; one never measured sees nothing (0 mm,
        180 degrees off square), as a pair with nothing in view reads."""
        readings = self.host.own_readings
        out = {}
        for c in self.host.program.profile.connectors:
            out[f"ir_{c}"] = readings.get(f"ir_{c}", 0.0)
            out[f"ir_{c}_align"] = readings.get(f"ir_{c}_align", 180.0)
        return out

    def floor(self) -> FloorPoses:
        """The tracker's poses: with a ``[tracker]``, those the module heard itself
        (firmware.tracker_floor: every module whose three parts are fresh); else the world's
        last report (firmware.control.Floor); none yet: empty, and the reach closes on its
        joints and infrared alone."""
        from firmware.motion.readings import FloorPoses, ModulePose, PartPose

        host = self.host
        if host.tracker is not None and host.config.tracker is not None:
            from firmware.tracker_floor import floor_from_feed

            floor = floor_from_feed(host.tracker, host.config.tracker.modules, host.config.cycle_period)
            if host.floor_filter is not None:
                floor = host.floor_filter.update(host.runtime.cycle, floor)
            if floor.modules and not host.tracker_floor_said:
                host.tracker_floor_said = True
                host._log_line(
                    f"tracker: the floor from the feed: modules {sorted(floor.modules)} fresh "
                    f"({host.tracker.datagrams} datagrams taken)"
                )
            return floor
        report = self.host.floor_report
        if report is None:
            return FloorPoses()
        modules = {}
        for m, parts in report.parts.items():
            centre, front, back = (PartPose(*p) for p in parts)
            modules[m] = ModulePose(centre, front, back)
        return FloorPoses(modules)

    def attitude(self) -> dict[int, tuple[float, float]]:
        """Its own IMU (roll, pitch) as the world last measured it; another module's tilt comes
        in that module's ANGLES."""
        report, me = self.host.floor_report, self.host.module
        own = None if report is None else report.attitude.get(me)
        return {} if own is None else {me: (own[0], own[1])}


class _WorldLatch:
    """The latch of a reach this module runs, asked of the world (firmware.motion.asking.LatchAsk):
    an ``latch`` effect asks it to close now, a :class:`firmware.control.LatchAnswer` says
    whether it did (in physics, with the link made); one question at a time a connector."""

    def __init__(self, host: ModuleHost) -> None:
        self.host = host
        self.asked: set[int] = set()
        self.closed: set[int] = set()

    def aligned(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        if a_conn in self.closed:
            return True
        if a_conn not in self.asked:
            self.asked.add(a_conn)
            self.host.report(Effect("latch", [a_conn, b, b_conn]))
        return False

    def latch(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        closed = a_conn in self.closed
        self.closed.discard(a_conn)
        return closed

    def answered(self, answer: LatchAnswer) -> None:
        self.asked.discard(answer.connector)
        if answer.closed:
            self.closed.add(answer.connector)


#: cycles a closed latch waits for its connector's link to be verified before the dock is refused:
#: a Hello each way is one cycle, a lost one is beaconed again the next; 10 cycles is the
#: member's silence bound (docs/hil.md), past which a link that came would be taken as lost anyway
LATCH_LINK_CYCLES = 10


def _module_latch(host: ModuleHost) -> _WorldLatch | _ModuleLatch:
    """The module's own latch when its config has a ``[latch]`` that opens, else the world's
    (said once in the log)."""
    spec = host.config.latch
    driver, fault = open_latch(host.config, host.driver)
    if driver is None or spec is None:
        why = fault or "no [latch] in module.toml"
        host.runtime.log.append(f"latch: {why}; a reach's latch is asked of the world")
        return _WorldLatch(host)
    host.runtime.log.append(f"latch: the module's own ({spec.kind}) on connector {spec.connector}")
    return _ModuleLatch(host, driver, spec.connector)


class _ModuleLatch:
    """The latch of a reach this module runs, its own (firmware.motion.asking.LatchAsk): when the
    motion asks, the latch closes; the dock is aligned once the latch reports ``closed`` and the
    connector's link is verified (a Hello heard on it). A latch that faults or jams, or a link
    that does not come within :data:`LATCH_LINK_CYCLES`, refuses this try: the latch opens
    again and the dock is not aligned yet, so the motion goes on and asks again, as it does
    when the world refuses its latch (a refused ``LatchAnswer``); its own budget bounds it.
    A dock on another connector (a male face, held by the other module's latch) is asked of
    the world, as without a latch."""

    def __init__(self, host: ModuleHost, driver: Latch, connector: int) -> None:
        self.host = host
        self.driver = driver
        self.connector = connector
        self.world = _WorldLatch(host)
        #: connector -> cycles waited since the latch was told to close
        self.waiting: dict[int, int] = {}
        #: connector -> docked (True) or refused (False), until the motion reads it
        self.verdict: dict[int, bool] = {}

    def aligned(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        if a_conn != self.connector:
            return self.world.aligned(a, a_conn, b, b_conn)
        if a_conn in self.verdict:
            return True
        if a_conn not in self.waiting:
            state = self.driver.state().state
            if state is not LatchState.OPEN:
                # closed on no link (the male face that held its pins was released by the other
                # module, which cannot open this latch), or still opening after a refusal: a
                # close now would move nothing, and the pins of the face in front would never
                # be taken. Open it, and close once it reads open.
                if state is not LatchState.MOVING:
                    self.driver.open()
                return False
            self.waiting[a_conn] = 0
            self.driver.close()
            return False
        self.waiting[a_conn] += 1
        status = self.driver.state()
        if status.state is LatchState.CLOSED and self.host.runtime.verified(a_conn):
            return self._decide(a_conn, True, "closed and linked")
        if status.state is LatchState.FAULT:
            return self._decide(a_conn, False, f"latch {status}")
        if self.waiting[a_conn] > LATCH_LINK_CYCLES:
            return self._decide(a_conn, False, f"latch {status}, link not verified in {LATCH_LINK_CYCLES} cycles")
        return False

    def _decide(self, conn: int, docked: bool, why: str) -> bool:
        """Docked (aligned: the motion reads the verdict), or refused: opened, not aligned yet."""
        del self.waiting[conn]
        log = self.host.runtime.log
        if docked:
            self.verdict[conn] = True
            log.append(f"latch on connector {conn}: docked ({why})")
            return True
        log.append(f"latch on connector {conn}: refused ({why}); opened, asked again when the motion next asks")
        self.driver.open()
        return False

    def latch(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        if a_conn != self.connector:
            return self.world.latch(a, a_conn, b, b_conn)
        return self.verdict.pop(a_conn, False)

    def answered(self, answer: LatchAnswer) -> None:
        """The world's answer for a dock on another connector."""
        self.world.answered(answer)

    def release(self, connector: int) -> None:
        """``release`` of the latch's connector: the latch opens (the link goes as before)."""
        if connector == self.connector:
            self.driver.open()


class TrialWatch:
    """Counts a trial program's clean cycles: ``cycle`` returns "clean" once it has run
    ``needed`` cycles with no fault and every attached neighbour verified, the reason when a
    fault ends the trial, else None."""

    def __init__(self) -> None:
        self.clean = 0
        self._faults: int | None = None

    def cycle(self, rt: ModuleRuntime, needed: int) -> str | None:
        faults = rt.engine.counters["faults"]
        if self._faults is None:
            self._faults = faults
        if faults > self._faults:
            return f"{faults - self._faults} receptor fault(s) on trial: {rt.last_fault}"
        if rt.actuator_fault:
            return f"an actuator fault on trial: {rt.actuator_fault}"
        self.clean = self.clean + 1 if rt.liveness.settled else 0
        return "clean" if self.clean >= needed else None


def _stdout_report(stream: IO[str]) -> Reporter:
    lock = threading.Lock()

    def report(rep: Report) -> None:
        line = json.dumps(report_to_json(rep), separators=(",", ":"))
        with lock:
            try:
                stream.write(line + "\n")
                stream.flush()
            except (BrokenPipeError, ValueError):
                pass  # the world has gone; nothing left to tell

    return report


class JsonLog:
    """A module on its own: reports as JSON log lines, the last status in a file, and
    systemd told how it goes (see the module docs)."""

    def __init__(self, config: ModuleConfig, stream: IO[str]) -> None:
        self.name = config.label
        self.stream = stream
        self.status_file = Path(config.status_file) if config.status_file else None
        self.notify = SystemdNotify.from_environment()
        self._lock = threading.Lock()
        self._cycling = False

    def __call__(self, rep: Report) -> None:
        body = report_to_json(rep)
        if body.get("event") == "trace":
            return  # a module on its own keeps no trace; the HIL world asks for one
        now = time.time()
        stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(now)) + f"{now % 1:.3f}Z"[1:]
        body.pop("module", None)  # the world's index: a module on its own has none, only a name
        body.pop("name", None)
        line = json.dumps({"time": stamp, "module": self.name, **body}, separators=(",", ":"))
        with self._lock:
            try:
                self.stream.write(line + "\n")
                self.stream.flush()
            except (BrokenPipeError, ValueError, OSError):
                pass  # a closed log must not stop the module
        if isinstance(rep, Status):
            self._status(rep, body)

    def _status(self, rep: Status, body: dict[str, Any]) -> None:
        if self.status_file is not None:
            write_atomically(self.status_file, json.dumps({**body, "module": self.name}, indent=1) + "\n")
        if rep.final:
            self.notify.send("STOPPING=1")
            return
        if not self._cycling:
            self._cycling = True
            self.notify.send("READY=1")
        cycle = rep.status.get("cycle")
        self.notify.send(f"WATCHDOG=1\nSTATUS=cycle {cycle}, type {rep.status.get('type')}")


def write_atomically(path: Path, text: str) -> None:
    """Replace ``path`` with ``text`` so that a reader never sees half of it."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)


class SystemdNotify:
    """``sd_notify`` without libsystemd: datagrams to ``$NOTIFY_SOCKET`` (nothing without it)."""

    def __init__(self, address: str | None) -> None:
        self.address = address
        self._sock: socket.socket | None = None
        if address:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)

    @classmethod
    def from_environment(cls) -> SystemdNotify:
        return cls(os.environ.get("NOTIFY_SOCKET"))

    def send(self, state: str) -> None:
        if self._sock is None or self.address is None:
            return
        target = "\0" + self.address[1:] if self.address.startswith("@") else self.address
        with contextlib.suppress(OSError):  # systemd gone (or never there): the module runs on
            self._sock.sendto(state.encode(), target)


def _read_commands(stream: IO[str], commands: queue.Queue[Command], report: Reporter) -> None:
    for line in stream:
        line = line.strip()
        if not line:
            continue
        try:
            commands.put(command_from_json(json.loads(line)))
        except (json.JSONDecodeError, ControlProtocolError) as exc:
            report(Log(f"command refused ({exc}): {line[:200]!r}"))
    commands.put(Stop())  # the world closed the channel


def build_parser() -> argparse.ArgumentParser:
    import argparse

    p = argparse.ArgumentParser(
        prog="dh2rt module",
        description="Run one dh2rt module: its program over its links, driving its servos, until stopped.",
        epilog="Example: dh2rt module --config /etc/dh2rt/module.toml   (see docs/firmware.md)",
    )
    p.add_argument("--config", required=True, help="module.toml (or, from the HIL world, a JSON object or @FILE.json)")
    p.add_argument("--check-config", action="store_true", help="check the config, print what it sets up, and exit")
    return p


@dataclass(frozen=True)
class Arguments:
    """``dh2rt module``'s options (what :func:`build_parser` parses)."""

    config: str
    check_config: bool = False


def plain_arguments(argv: Sequence[str]) -> Arguments | None:
    """The arguments a module processor starts with, read without argparse: ``--config
    PATH`` or ``--config=PATH``, and ``--check-config``, each once. Anything else (``--help``,
    a mistake) goes to :func:`build_parser`, so its help and errors are argparse's; argparse
    and gettext cost a module 0.4 MB resident that it would carry while cycling."""
    config: str | None = None
    check = False
    rest = list(argv)
    while rest:
        arg = rest.pop(0)
        if arg == "--check-config" and not check:
            check = True
        elif arg == "--config" and config is None and rest and not rest[0].startswith("-"):
            config = rest.pop(0)
        elif arg.startswith("--config=") and config is None and len(arg) > len("--config="):
            config = arg[len("--config=") :]
        else:
            return None
    return None if config is None else Arguments(config, check)


def load_config(text: str) -> ModuleConfig:
    """The config named on the command line: a TOML file, a JSON object, or @FILE.json."""
    from firmware.module_toml import load_toml

    if text.startswith("{"):
        return ModuleConfig.from_json(json.loads(text))
    if text.startswith("@"):
        return ModuleConfig.from_json(json.loads(Path(text[1:]).read_text(encoding="utf-8")))
    return load_toml(Path(text))


def missing_devices(config: ModuleConfig, profile: Profile = CONRO) -> list[str]:
    """Every device file the config needs that is not there, each named by its module.toml
    key: the serial ports of the links, the servo port, the connectors' channels (UART and
    contact pin) and a SocketCAN interface. Empty: all there (whether they work is the run's
    to find out). ``--check-config`` and a module on its own refuse a config with any."""
    wanted: list[tuple[str, str]] = []
    for c, end in sorted(config.attach.items()):
        if isinstance(end, PortEnd):
            wanted.append((f"[transport.connectors] {profile.connector_name(c)}", end.url))
    if config.servo_port:
        wanted.append(("[servos] port", config.servo_port))
    for c, spec in sorted(config.connector_channels.items()):
        wanted.append((f"[connectors] {profile.connector_name(c)} device", spec.device))
        if spec.contact is not None:
            wanted.append((f"[connectors] {profile.connector_name(c)} contact", spec.contact))
    if config.latch is not None and config.latch.settings.get("port"):
        wanted.append(("[latch] port", config.latch.settings["port"]))
    if config.latch is not None and config.latch.kind == "gpio":
        wanted.append(("[latch] chip", config.latch.settings["chip"]))
    kind, options = parse_transport_spec(config.transport)
    interface = config.bus_options.get("interface")
    channel = config.bus_options.get("channel") if kind == "can" else options.get("channel")
    if (kind == "socketcan" or interface == "socketcan") and channel:
        wanted.append(("[transport] channel", f"/sys/class/net/{channel}"))
    elif kind == "can" and channel and channel.startswith("/"):  # slcan and the like: a serial adapter
        wanted.append(("[transport] channel", channel))
    # a pyserial URL (loop://, socket://...) is no file: only paths are looked for
    return [
        f"{where}: {path}: no such device" for where, path in wanted if "://" not in path and not Path(path).exists()
    ]


def describe(config: ModuleConfig) -> str:
    """What a config sets up, one line each (``--check-config``); nothing is written."""
    source = "image"
    image = config.image
    if config.flash:
        from firmware.flash.slots import Flash

        peeked, program_image = Flash(Path(config.flash), config.trust, allow_unsigned=config.allow_unsigned).peek()
        source = f"flash {config.flash}: {peeked}; trusts {len(config.trust)} key(s)"
        if program_image is None:
            raise ModuleConfigError(f"[program] flash: {config.flash}: {peeked}")
        image = program_image
    program = load_image(image)
    links = ", ".join(f"{program.profile.connector_name(c)}: {e}" for c, e in sorted(config.attach.items()))
    channels = ", ".join(program.profile.connector_name(c) for c in sorted(config.connector_channels))
    if config.servo_port:
        body = f"Dynamixel servos on {config.servo_port} at {config.servo_baud} baud, ids {config.servo_ids}"
    else:
        body = f"stand-in {config.driver}"
    bus = ", ".join(f"{k}={v}" for k, v in config.bus_options.items())
    return "\n".join(
        [
            f"module {config.label}: program {program.name} (sha256 {program.hash[:16]}) from the {source}",
            f"transport {config.transport}"
            + (f" ({bus})" if bus else "")
            + (f"; links {links}" if links else "")
            + (f"; links negotiated over the channels of {channels}" if channels else ""),
            f"cycle {config.cycle_period * 1000:g} ms, liveness bound {config.silence_cycles} cycles",
            f"body: {body}",
            f"latch: {describe_latch(config, program.profile)}",
            f"tracker: {describe_tracker(config)}",
            f"log: {config.log_file or 'standard error'}"
            + (f", status in {config.status_file}" if config.status_file else ""),
        ]
    )


def describe_tracker(config: ModuleConfig) -> str:
    """The ``[tracker]`` in a line (``--check-config``)."""
    spec = config.tracker
    if spec is None:
        return "none (the floor as the world reports it, if any)"
    return (
        f"UDP {spec.bind or '*'}:{spec.port}, markers 0..{3 * spec.modules - 1} of {spec.modules} modules, "
        f"poses within {spec.max_age_s:g} s, " + ("raw" if spec.alpha is None else f"smoothed (alpha {spec.alpha:g})")
    )


def describe_latch(config: ModuleConfig, profile: Profile) -> str:
    """The ``[latch]`` in a line (``--check-config``)."""
    spec = config.latch
    if spec is None:
        return "none"
    s = spec.settings
    where = f"on {profile.connector_name(spec.connector)}, moves within {s['timeout_s']:g} s"
    if spec.kind == "servo":
        port = s["port"] or f"{config.servo_port} (shared with the joints)"
        return (
            f"Dynamixel servo id {s['id']} on {port}, open {s['open_deg']:g} / closed {s['closed_deg']:g} degrees "
            f"within {s['tolerance_deg']:g}, {where}"
        )
    if spec.kind == "gpio":
        lows = [n for n in ("output", "input") if s[f"{n}_active_low"]]
        low = f" ({' and '.join(lows)} active low)" if lows else ""
        return (
            f"GPIO {s['chip']}, output line {s['output_line']}, closed switch on line {s['input_line']}{low}, {where}"
        )
    return f"stand-in {spec.kind}, {where}"


def lean_process() -> None:
    """What a module process leaves out, being small (docs/firmware.md, "Footprint"): no
    OpenSSL (python-can imports asyncio, which loads the ssl module if it can; a module never
    speaks TLS, and the library costs about 1 MB resident)."""
    sys.modules.setdefault("ssl", None)  # type: ignore[arg-type]


def settle_heap() -> None:
    """Just before cycling: what start-up allocated (modules, the program, the ports) goes to
    the collector's permanent generation, so that a collection during a cycle does not walk
    it again (shorter, rarer pauses in the cycle loop)."""
    gc.collect()
    gc.freeze()


def main(argv: Sequence[str] | None = None) -> int:
    try:
        return _main(argv)
    except KeyboardInterrupt:  # Ctrl-C before the module's own handler is in place
        print("dh2rt module: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


def _main(argv: Sequence[str] | None) -> int:
    lean_process()
    args = list(sys.argv[1:] if argv is None else argv)
    ns = plain_arguments(args) or build_parser().parse_args(args)
    try:
        config = load_config(ns.config)
        if ns.check_config or config.control == "none":
            # on its own, a module refuses what is not there before it starts anything
            missing = missing_devices(config)
            if missing:
                for line in missing:
                    print(f"dh2rt module: {ns.config}: {line}", file=sys.stderr)
                return 2
        if ns.check_config:
            print(f"{ns.config}: ok\n" + describe(config))
            return 0
    except (OSError, ValueError, DH2Error) as exc:
        print(f"dh2rt module: {exc}", file=sys.stderr)
        return 2
    if config.control == "stdio":
        return _run_controlled(config)
    return _run_alone(config)


def _run_controlled(config: ModuleConfig) -> int:
    """Under the HIL world: commands on stdin, reports on stdout."""
    report = _stdout_report(sys.stdout)
    try:
        commands: queue.Queue[Command] = queue.Queue()
        host = ModuleHost(config, commands, report)
    except (OSError, ValueError, DH2Error) as exc:
        report(Failure(f"bad config: {exc}"))
        print(f"dh2rt module: {exc}", file=sys.stderr)
        return 2
    threading.Thread(target=_read_commands, args=(sys.stdin, commands, report), daemon=True).start()
    return _serve_until_signalled(host)


def _run_alone(config: ModuleConfig) -> int:
    """On a robot: start cycling after the handshake, stop on SIGTERM or SIGINT."""
    try:
        stream: IO[str] = open(config.log_file, "a", encoding="utf-8") if config.log_file else sys.stderr  # noqa: SIM115
    except OSError as exc:
        print(f"dh2rt module: [log] file {config.log_file}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    log = JsonLog(config, stream)
    try:
        commands: queue.Queue[Command] = queue.Queue()
        commands.put(Go(at=None))
        host = ModuleHost(config, commands, log)
    except (OSError, ValueError, DH2Error) as exc:
        log(Failure(f"cannot start: {exc}"))
        print(f"dh2rt module: {exc}", file=sys.stderr)
        return 2
    origin = host.program_status()
    where = (
        f" from slot {origin['slot']} (version {origin['version']}{', on trial' if origin['trial'] else ''})"
        if origin
        else ""
    )
    log(Log(f"started: module {config.label}: program {host.program.name} (sha256 {host.program.hash[:16]}){where}"))
    try:
        return _serve_until_signalled(host)
    finally:
        if stream is not sys.stderr:
            stream.close()


#: The exit code after Ctrl-C (SIGINT), as every dh2rt command's; SIGTERM is a clean stop (0).
EXIT_INTERRUPTED = 130


def _serve_until_signalled(host: ModuleHost) -> int:
    """Serve until done, SIGTERM (a clean stop: the host's code) or SIGINT (Ctrl-C: 130
    once the module has wound down, unless it failed)."""
    interrupted: list[int] = []

    def on_signal(sig: int, _frame: FrameType | None) -> None:
        if sig == signal.SIGINT:
            interrupted.append(sig)
        host.stop_event.set()
        # one stop request is enough: a second signal while the module winds down (closing its
        # links, writing its final status) must not kill it with its work half done
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        signal.signal(signal.SIGINT, signal.SIG_IGN)

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    settle_heap()
    code = host.serve()
    return EXIT_INTERRUPTED if interrupted and code == 0 else code


if __name__ == "__main__":
    sys.exit(main())


def _where(exc: BaseException) -> str:
    """Where ``exc`` was raised, innermost frame first, for a failure report: a module's
    crash names the line (the world's log has no traceback)."""
    frames = traceback.extract_tb(exc.__traceback__)[-3:]
    return "; ".join(f"{Path(f.filename).name}:{f.lineno} in {f.name}" for f in reversed(frames)) or "no traceback"
