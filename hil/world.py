"""The hardware-in-the-loop world: the physical layer around module processes.

The :class:`World` plays what the in-process :class:`~dh2rt.robot.Robot` plays in one
process, but for modules that each run their own :class:`~dh2rt.runtime.ModuleRuntime` on
a real link layer. It owns the topology and the link map (:mod:`hil.link_map`: a CAN link
id and sides per docked connector pair over ``vcan0``/``can0``/``udp``/``virtual``/
``inproc``, or a pair of pty ends through the :class:`~hil.link_emulator.LinkEmulator` over
``serial``); it starts the modules through :mod:`hil.supervisor` (one OS process each over
``socketcan``, ``udp`` and ``serial``; one thread each over the in-process buses
``virtual`` and ``inproc``), each from a typed :class:`~firmware.config.ModuleConfig`, talks to
them in the typed control protocol of :mod:`firmware.control`, keeps what they report in
:mod:`hil.status` views, and carries out events at world cycles:

* ``cut``: CAN: both ends are told to detach the link id; serial: the emulator undocks the
  link (the modules notice by liveness, as they would over infrared).
* ``dock``: a new link id (or emulator link) is attached at both ends.
* ``kill``: the module's process is ended by its pid (a thread is told to stop); its
  neighbours notice the silence within the liveness bound.
* ``restart``: the module starts again with a fresh state on the same links.
* ``inject``: the hormone is sent to the module over its control channel.
* ``sense``: the sensor value is sent to the module (:class:`~firmware.control.Sense`), which
  holds it from then on; the world remembers it and sends it again to a restarted module.

Sensors: with the PyBullet stand-in, the world measures each module's IMU, infrared pairs and
ground contact (the sensors the program declares; ``sim.sensors``) every ``sensor_every``
world cycles and pushes them to the module (:class:`~firmware.control.Readings`), once before
``go`` and after each restart too; the joints' present position and load a module reads
from its own (emulated) servos. :attr:`World.push_times` holds what each push cost.

Effects that natives ask of the physical world arrive as reports; ``reach_and_dock``,
``reach_dock`` and ``release`` are carried out by the rules of :mod:`dh2rt.docking`, with
this world as the docking world (DOCK_DELAY world cycles later for the first two: for
``reach_and_dock`` the foot's link is cut and the asking connector docked to it), so
``legs_to_snake`` and ``snake_to_t`` reconfigure in the loop. With the PyBullet stand-in a
``reach_dock`` is carried out by motion instead (:mod:`hil.reach_loop`): the chain's modules
hold the joint targets of a :class:`firmware.motion.reach.Reach` stepped once per world cycle, and the
link is docked only once the faces latched in physics, within the physics runner's tolerance;
and a ``reach_and_dock`` as the physics runner does it
(:meth:`firmware.motion.docking.Docking.assimilate`, the sequence both drive): the foot lets go
of the body, comes to the asking face by its own gaits (:class:`firmware.motion.crawl.Trip`, held on its
own servos) and the two dock by motion while it creeps; the asking module's ``docking``
sensor reads 1 meanwhile (pushed by the world). With :attr:`World.modules_move` a
``reach_dock`` is the asking module's own (firmware.motion.asking): the world sends no
``Hold``, only the sensors it fills and the latch's answer. With ``latch_emulator`` (the
launcher's ``--latch-emulator``) each module has a latch servo on its front face
(hil.physics_stand_in) and a ``[latch]`` in its module.toml: it closes its own latch, and the
world docks the link when the horn gets past the pins (the face aligned with a free one) and
undocks it when the horn opens (:meth:`World.watch_latches`); such a module is sent no
``LatchAnswer`` for that face, and its ``release`` of it waits for the horn. With
``tracker_udp`` (the launcher's ``--tracker-udp``) each module has a ``[tracker]`` in its
module.toml and hears the overhead tracker itself over UDP on loopback (hil.tracker_udp); the
world's ``Floor`` then carries its IMU only.

A world cycle is wall time since ``go`` divided by the cycle period: modules keep their own
clocks and cycle counts. Reports from the modules (status, trace records, logs, effects)
arrive on one queue and are read by :meth:`World.poll`.
"""

from __future__ import annotations

import gc
import os
import queue
import re
import shutil
import tempfile
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dh2rt import docking
from dh2rt.docking import End
from dh2rt.errors import HilWorldError, TopologyError, TransportUnavailable
from dh2rt.events import Event
from dh2rt.hormone import Hormone
from dh2rt.program import CompiledProgram
from dh2rt.robot import PhaseDraw
from dh2rt.runtime import CYCLE_PERIOD_S
from dh2rt.topology import Topology
from dh2rt.transport.base import HeldEnd, LinkCounters, PortEnd
from dh2rt.transport.can_bus import SocketCanTransport, UdpCanTransport, VirtualCanTransport
from dh2rt.transport.inproc import inproc_bus
from dh2rt.transport.registry import parse_spec as parse_transport_spec
from firmware.config import (
    DEFAULT_STAND_IN,
    DEFAULTS,
    EMULATED_SERVO_LATENCY_MS,
    STAND_INS,
    TRACKER_MAX_AGE_S,
    ChannelSpec,
    LatchSpec,
    ModuleConfig,
    TrackerSpec,
)
from firmware.control import (
    Attach,
    Command,
    Detach,
    Effect,
    Exited,
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
    Stop,
    TraceRecord,
)
from hil.bus_witness import SHARED_INTERFACES, BusWitness, EndId, Span, negotiated_end, spans_of
from hil.capture_tap import PYTHON_CAN, BusTap, CaptureSink
from hil.contact_emulator import ContactEmulator
from hil.hardware_map import HardwareMap
from hil.latch_emulator import LATCH_CONNECTOR, LATCH_SETTINGS
from hil.link_emulator import LinkEmulator, LinkStats, SideCounts
from hil.link_map import LinkMap
from hil.status import ModuleView
from hil.status import rows as status_rows
from hil.supervisor import ModuleHandle, ProcessModule, Reports, deferred_interrupts, start_module

#: The connector of a negotiated link in a module's log line (firmware.negotiated_links).
_NEGOTIATED_AT = re.compile(r"link negotiated: connector (\d+) is link \d+ side [01]")

#: Transports whose modules run as threads of the world's process (their bus is in-process).
THREAD_TRANSPORTS = ("inproc", "virtual")
#: Transports on a shared bus: the modules negotiate their link ids (inproc keeps the world's).
NEGOTIATED = ("virtual", "udp", "socketcan", "can")
#: Emulator link ids of programming cables start here (the link map numbers docks from 0).
CABLE_LINK_IDS = 10_000
#: A bus cable's end in the contact emulator is (CABLE_MODULE - module, its connector).
CABLE_MODULE = -1
#: The bus transports' channels when the spec names none.
_DEFAULT_CHANNELS = {
    cls.name: cls.default_channel for cls in (VirtualCanTransport, UdpCanTransport, SocketCanTransport)
}

if TYPE_CHECKING:
    from hil.physics_stand_in import PhysicsStandIn
    from hil.reach_loop import LoopReaches
    from hil.tracker_udp import TrackerPublisher


#: How long before the next world cycle begins the world's tick steps the docking motions (s):
#: the joint targets a step computes from the body as it is then reach the modules before
#: they take their commands for that cycle (firmware.main_loop: just before each cycle), so
#: the motion's feedback is a few milliseconds old when the servos get it, not a cycle.
STEP_LEAD_S = 0.008
#: The infrared links' line rate in the loop (bytes cross at 10 bits each): the modules' ports'.
LINE_BAUD = 115_200


class World:
    """Modules of ``topology`` running ``program`` over ``transport`` (see module docs)."""

    #: With the PyBullet stand-in: the modules carry out their ``reach_dock`` themselves
    #: (firmware.motion.asking; told by :class:`firmware.control.OwnMotions`), the world only
    #: pushes the asking module its infrared pairs and answers its latch
    #: (:meth:`hil.reach_loop.LoopReaches.own_started`); off: the world runs the motion and
    #: sends ``Hold`` s. Off by default (``reach_and_dock`` is still the world's); the launcher's
    #: ``--motions-in-modules`` turns it on (docs/hil.md, "The motion in the module").
    modules_move: bool = False

    def __init__(
        self,
        program: CompiledProgram,
        topology: Topology,
        transport: str,
        *,
        seed: int = 0,
        cycle_period: float = CYCLE_PERIOD_S,
        cycles: int | None = None,
        trace: bool = False,
        silence_cycles: int = DEFAULTS.silence_cycles,
        status_every: int = DEFAULTS.status_every,
        frame_loss: float = 0.0,
        bit_error: float = 0.0,
        emulator_seed: int | None = None,
        handshake: float = DEFAULTS.handshake,
        start_delay: float = 0.3,
        stand_in: str = DEFAULT_STAND_IN,
        capture: CaptureSink | None = None,
        hardware: HardwareMap | None = None,
        bus_options: Mapping[str, Any] | None = None,
        gui: bool = False,
        signer: bytes | None = None,
        trial_cycles: int = DEFAULTS.trial_cycles,
        line_baud: int = LINE_BAUD,
        sensor_every: int = 1,
        modules_move: bool | None = None,
        latch_emulator: bool = False,
        tracker_udp: bool = False,
    ) -> None:
        if sensor_every < 1:
            raise HilWorldError(f"sensor readings pushed every {sensor_every} cycles: must be 1 or more")
        self.program = program
        self.topology = topology
        if modules_move is not None:
            self.modules_move = modules_move
        self.profile = topology.profile
        self.spec = transport
        self.kind, options = parse_transport_spec(transport)
        self.seed = seed
        # the same LocalTimer phases as the in-process Robot with this seed
        self.phase_draw = PhaseDraw(seed)
        self.phases = [self.phase_draw.next(program.clock_cycle) for _ in topology.names]
        self.cycle_period = cycle_period
        self.cycles = cycles
        #: modules report their cycles for --trace, and for --capture's cycle marks
        self.trace = trace or capture is not None
        #: the records kept for --trace (sorted_records); with --capture alone they go to the
        #: capture's cycle marks as they come and are not kept: 8 modules' records held for
        #: a whole run weigh on the world process's garbage collector, whose pauses hold
        #: the link emulator's relay (every link fell silent at once in a CI run)
        self.keep_records = trace
        self.silence_cycles = silence_cycles
        self.status_every = status_every
        self.handshake = handshake
        self.start_delay = start_delay
        #: clean cycles a module runs a new program on trial before it confirms it
        self.trial_cycles = trial_cycles
        #: programming cables plugged in so far: frames to and from a cable are the flasher's,
        #: and those in flight when it is pulled out are lost, so such a run's links changed
        self.cables_plugged = 0
        #: the contact emulator's connectors of bus cables, and their paths
        self._cable_ends: dict[tuple[int, int], str] = {}
        # python-can's virtual bus reaches only its own process: its modules are threads
        in_process = self.kind == "can" and (bus_options or {}).get("interface") == "virtual"
        self.threads = self.kind in THREAD_TRANSPORTS or in_process
        if self.threads and not in_process:
            channel = options.get("channel") or f"dh2rt-hil-{os.getpid()}-{id(self):x}"
            self.transport_spec = f"{self.kind}:{channel}"
        else:
            self.transport_spec = transport
        #: where ``--capture`` writes the robot's frames (see hil.capture_tap), and the tap on a bus
        self.capture = capture
        self.bus_tap: BusTap | None = None
        self._bus_channel = options.get("channel") or _DEFAULT_CHANNELS.get(self.kind)
        if self.threads and not in_process:
            self._bus_channel = self.transport_spec.partition(":")[2]
        #: real ports per module (--hardware-map), and the python-can options of --transport can
        self.hardware = hardware
        self.bus_options = dict(bus_options or {})
        if self.kind == "can":
            self._bus_channel = self.bus_options.get("channel")
        self.emulator: LinkEmulator | None = None
        if self.kind == "serial" and not (hardware is not None and hardware.has_connectors):
            tap = None
            if capture is not None:
                sink = capture

                def tap(t: float, link: int, side: int, wire: bytes, lost: bool) -> None:
                    sink.serial_frame(t, link, side, wire, lost=lost)

            # the infrared links carry bytes at the modules' baud rate (0: at once); a port is
            # read from when its module opened it (opening flushes it: frames before are lost)
            self.emulator = LinkEmulator(
                frame_loss=frame_loss, bit_error=bit_error, baudrate=line_baud, seed=emulator_seed, tap=tap,
                await_open=True,
            )  # fmt: skip
        #: The modules' body: "recording" (each module records its commanded angles),
        #: "pybullet" (the full firmware path: Dynamixel servos emulated on ptys whose joints
        #: are PyBullet joints; see hil.physics_stand_in) or "none".
        self.stand_in = stand_in
        self.physics: PhysicsStandIn | None = None
        #: The docking motions on the PyBullet stand-in (``reach_dock`` by motion), or None.
        self.reaches: LoopReaches | None = None
        if latch_emulator and stand_in != "pybullet":
            raise HilWorldError("the latch emulator needs the PyBullet stand-in")
        if tracker_udp and not (stand_in == "pybullet" and self.modules_move):
            raise HilWorldError("the tracker over UDP needs the PyBullet stand-in and the motions in the modules")
        #: the overhead tracker sent over UDP to each module's own port (``tracker_udp``), or None
        self.tracker: TrackerPublisher | None = None
        #: each module's tracker port on 127.0.0.1
        self.tracker_ports: list[int] = []
        #: LatchAnswers sent (a module with its own latch is sent none for its face)
        self.latch_answers = 0
        #: Holds sent: joint targets the world computed for a module (none when the modules
        #: carry out their motions themselves, ``--motions-in-modules``)
        self.holds_sent = 0
        #: module -> the face its latch's horn docked its front to (the horn's link), or None
        self.horn_links: dict[int, tuple[int, int] | None] = {}
        self._horns_closed: dict[int, bool] = {}
        try:
            if stand_in == "pybullet":
                from hil.physics_stand_in import PhysicsStandIn
                from hil.reach_loop import LoopReaches

                self.physics = PhysicsStandIn(topology, seed=seed, gui=gui, latches=latch_emulator)
                self._horns_closed = {m: self.physics.horn_closed(m) for m in self.physics.latches}
                self.horn_links = dict.fromkeys(self.physics.latches)
                self.reaches = LoopReaches(self, self.physics)
                if tracker_udp:
                    from hil.tracker_udp import TrackerPublisher, free_ports

                    self.tracker_ports = free_ports(topology.size)
                    self.tracker = TrackerPublisher(self.tracker_ports)
            elif stand_in not in STAND_INS:
                raise HilWorldError(f"stand-in {stand_in!r}: expected pybullet, recording or none")
        except BaseException:  # a failed or interrupted start leaves no pty or thread behind
            if self.emulator is not None:
                self.emulator.close()
            if self.physics is not None:
                self.physics.close()
            if self.tracker is not None:
                self.tracker.close()
            raise
        #: the sensors the world's physics measures and pushes (see the module docs)
        self.sensor_every = sensor_every
        self.measured: tuple[str, ...] = ()
        if self.physics is not None:
            self.measured = self.physics.measure(n for n in program.sensor_names if n in self.profile.sensor_names)
        #: values ``sense`` events forced, per module (sent again to a restarted module)
        self.sensed: dict[int, dict[str, int]] = {}
        #: each ``sense`` sent: (module, sensor, value, monotonic s before and after sending it)
        self.sense_times: list[tuple[int, str, int, float, float]] = []
        #: seconds each push of readings took (measure, round, send to every module)
        self.push_times: list[float] = []
        self._next_push = 0
        self.reports: Reports = queue.Queue()
        #: each module process's module.toml and flash (removed by stop())
        self.workdir = Path(tempfile.mkdtemp(prefix="dh2rt-hil-"))
        #: modules (processes and threads) boot from a flash as a robot's modules do: the
        #: program signed with a key of this run's, which their trust stores hold; the run's
        #: signing key signs a rollout's new images too (tests, --event flash)
        self.signer: bytes | None = None
        self.signed_image: bytes | None = None
        self.trust: tuple[bytes, ...] = ()
        try:
            from dh2rt.signed_image import new_private_key, pack, public_key

            self.signer = signer if signer is not None else new_private_key()
            self.signed_image = pack(program.image, 1, self.signer)
            self.trust = (public_key(self.signer),)
        except ModuleNotFoundError as exc:
            # dh2rt installed without its dependencies: threads run the image as it is (no
            # flash, no rollouts); a module process boots only from a flash
            if exc.name != "cryptography" or not self.threads:
                raise
            self.signer = None
        self.views = [ModuleView(m, topology.names[m]) for m in range(topology.size)]
        #: frame counters of each module's earlier lives (a restarted module counts from 0)
        self.earlier_lives: list[dict[str, int]] = [{} for _ in range(topology.size)]
        #: frame counters of the programming cables' transports (the flasher's frames)
        self.cable_frames: dict[str, int] = {}
        #: the emulator ports (pty paths) each module was given, the cables' flasher ends,
        #: and each port's counts when the module's current life began (see frame_accounting)
        self._ports_of: list[set[str]] = [set() for _ in range(topology.size)]
        self._cable_paths: set[str] = set()
        self._life_start: list[dict[str, SideCounts]] = [{} for _ in range(topology.size)]
        #: modules whose current life was killed before it reported its counters: the link
        #: emulator counts that life's frames (sent from its ports, read from them)
        self._unreported = [False] * topology.size
        #: frames of each module's earlier such lives, counted by the emulator: {"sent": n, "read": n}
        self.killed_frames = [{"sent": 0, "read": 0} for _ in range(topology.size)]
        #: on a shared CAN bus, the witness of the frames no module can count (hil.bus_witness;
        #: opened by start()); the spans each module's earlier lives held their link ends in,
        #: each with whether that life reported its counters (else the witness counted its
        #: frames); the ends its current life logged it negotiated; when that life began and
        #: was killed (wall clock, the bus's stamps); the cables' spans
        self.witness: BusWitness | None = None
        self._bus_spans: list[list[tuple[Span, bool]]] = [[] for _ in range(topology.size)]
        self._negotiated: list[set[EndId]] = [set() for _ in range(topology.size)]
        #: link id -> side -> (module, connector), as the modules logged their negotiated links
        self._bus_links: dict[int, dict[int, tuple[int, int]]] = {}
        self._life_wall: list[tuple[float, float | None]] = [(0.0, None)] * topology.size
        self._cable_spans: list[Span] = []
        #: how many times each module was started (a restart starts a new life)
        self.lives = [0] * topology.size
        #: restarts whose new life came up after the run's last cycle, so it ran none:
        #: (module, the world cycle it was ready at); problems() names each
        self.late_restarts: list[tuple[int, int]] = []
        self.handles: list[ModuleHandle | None] = [None] * topology.size
        self.records: list[dict[str, Any]] = []
        self.effects: list[tuple[int, Effect]] = []
        self.log: list[str] = []
        #: (event text, monotonic time it was carried out): CLOCK_MONOTONIC is system-wide,
        #: so these compare with the ``t`` of the modules' trace records.
        self.event_times: list[tuple[str, float]] = []
        ports = {}
        if hardware is not None:
            ports = {(m, c): end for m, h in hardware.modules.items() for c, end in h.connectors.items()}
        self.link_map = LinkMap(self.emulator, ports)
        #: on a bus the world assigns no link ids: it plays the connectors' contacts (their
        #: local channels, like CONRO's infrared pairs) and the modules negotiate their links
        self.contacts: ContactEmulator | None = None
        if self.kind in NEGOTIATED:
            self.contacts = ContactEmulator(seed=seed)
            for m in range(topology.size):
                for c in range(1, self.profile.connector_count + 1):
                    self.contacts.add_connector(m, c)
        self._pending: list[tuple[int, Callable[[], None]]] = []  # (world cycle, effect)
        self._go_at: float | None = None
        self._closed = False
        for lk in topology.links:
            self.link_map.add(lk.a, lk.a_conn, lk.b, lk.b_conn)
            if self.contacts is not None:
                self.contacts.make_contact((lk.a, lk.a_conn), (lk.b, lk.b_conn))

    @property
    def links(self) -> dict[int, Any]:
        """The docked links by link id (see hil.link_map)."""
        return self.link_map.links

    # ------------------------------------------------------------ modules

    def config(self, module: int, cycles: int | None, phase: int) -> ModuleConfig:
        real = self.hardware.get(module) if self.hardware is not None else None
        servo_port = self.physics.port(module) if self.physics is not None else None
        servos: dict[str, Any] = {}
        if servo_port is not None:  # servos this world emulates answer from one of its threads
            servos["servo_latency_ms"] = EMULATED_SERVO_LATENCY_MS
        if servo_port is not None and self.physics is not None and module in self.physics.latches:
            # the emulated latch servo on the same emulated bus (hil.physics_stand_in)
            latch = {**LATCH_SETTINGS, "connector": LATCH_CONNECTOR}
            servos["latch"] = LatchSpec.from_mapping(latch, "the loop's latch", servo_port)
        if real is not None and real.servo_port:
            servo_port = real.servo_port
            servos = {"servo_ids": real.servo_ids, "servo_baud": real.servo_baud, "servo_model": real.servo_model}
        if self.tracker is not None:  # a few of the world's cycles, at least a camera's few frames
            max_age = max(TRACKER_MAX_AGE_S, 5 * self.cycle_period)
            servos["tracker"] = TrackerSpec(self.tracker_ports[module], "127.0.0.1", max_age, self.topology.size)
        bus_options = dict(self.bus_options)
        if real is not None and real.can_channel:
            bus_options["channel"] = real.can_channel
        return ModuleConfig(
            **servos,
            trust=self.trust,
            bus_options=bus_options,
            module=module,
            name=self.topology.names[module],
            image=self.program.image,
            transport=self.transport_spec,
            attach={} if self.contacts is not None else self.link_map.attachments(module),
            connector_channels=self._channels(module),
            timer_phase=phase,
            cycle_period=self.cycle_period,
            cycles=cycles,
            silence_cycles=self.silence_cycles,
            driver="none" if self.stand_in == "none" else "recording",
            servo_port=servo_port,
            trace=self.trace,
            status_every=self.status_every,
            handshake=self.handshake,
            trial_cycles=self.trial_cycles,
        )

    def _channels(self, module: int) -> dict[int, ChannelSpec]:
        """The module's connector-local channels (the contact emulator's ptys) on a bus."""
        if self.contacts is None:
            return {}
        connectors = range(1, self.profile.connector_count + 1)
        return {c: ChannelSpec(self.contacts.path((module, c))) for c in connectors}

    def _spawn(self, module: int, cycles: int | None, phase: int) -> None:
        config = replace(self.config(module, cycles, phase), life=self.lives[module])
        v = self.views[module]
        if self.lives[module] and self.witness is not None:  # the spans of the life that ended
            reported = not self._unreported[module]
            self._bus_spans[module] += [(span, reported) for span in self._life_spans(module)]
        if self.lives[module] and self._unreported[module]:  # its counters died with it
            for key, n in self._life_frames(module).items():
                self.killed_frames[module][key] += n
            v.status = {}
        self._unreported[module] = False
        self._negotiated[module] = set()
        self._life_wall[module] = (time.time(), None)
        if self.emulator is not None:  # a new life's counts begin here
            self._ports_of[module].update(e.url for e in config.attach.values() if isinstance(e, PortEnd))
            for path in self._ports_of[module]:
                self.emulator.new_sender(path)
            self._life_start[module] = {p: self.emulator.side_counts(p) for p in self._ports_of[module]}
        self.lives[module] += 1
        with deferred_interrupts():  # the handle is recorded before a Ctrl-C can land
            self.handles[module] = start_module(
                config, self.reports, thread=self.threads, workdir=self.workdir, flash_image=self.signed_image
            )
        if self.lives[module] > 1:  # a new life counts from 0: keep what the last one counted
            earlier = self.earlier_lives[module]
            for key, n in v.status.get("counters", {}).items():
                if key in FRAME_COUNTERS:
                    earlier[key] = earlier.get(key, 0) + int(n)
            v.status = {}
        v.alive, v.ready, v.finished, v.failed, v.killed = True, False, False, False, False

    def start(self, ready_timeout: float = 30.0) -> None:
        """Start every module, wait until all have attached their links, then say ``go``."""
        if self.capture is not None and self.bus_tap is None and self.kind != "serial":
            self.bus_tap = self._open_bus_tap(self.capture)  # before any module speaks
        if self.witness is None and self.kind in NEGOTIATED:
            self.witness = self._open_witness()
        for m in range(self.topology.size):
            self._spawn(m, self.cycles, self.phases[m])
        deadline = time.monotonic() + ready_timeout
        while not all(v.ready for v in self.views):
            self.poll(0.05)
            if any(v.failed or (not v.ready and self._exited(v.module)) for v in self.views):
                raise HilWorldError(self._failure_text("a module failed to start"))
            if time.monotonic() > deadline:
                late = [v.name for v in self.views if not v.ready]
                raise HilWorldError(f"modules {', '.join(late)} not ready after {ready_timeout:.0f} s")
        # one start instant for all (CLOCK_MONOTONIC is shared by every process here): the
        # modules exchange Hellos until then and start cycling together, like modules powered
        # up at once; afterwards each keeps its own clock
        self.push_readings()  # cycle 0 reads the body as it stands
        if self.modules_move and self.reaches is not None:
            for m in range(self.topology.size):
                self._send(m, OwnMotions())
        # what start-up built (the PyBullet model, the program, the emulators) lives as long
        # as the run: out of the collector's sight, so that its full collections, which hold
        # the link emulator's relay with the rest of this process, stay short (gc.freeze)
        gc.collect()
        gc.freeze()
        self._go_at = time.monotonic() + self.start_delay
        for h in self.handles:
            if h is not None:
                h.send(Go(at=self._go_at))

    def _open_bus_tap(self, sink: CaptureSink) -> BusTap:
        if self.kind == "can":
            options = {k: v for k, v in self.bus_options.items() if k not in ("interface", "channel")}
            return BusTap(str(self.bus_options["interface"]), str(self.bus_options["channel"]), sink, **options)
        assert self._bus_channel is not None
        return BusTap(PYTHON_CAN[self.kind], self._bus_channel, sink)

    def _open_witness(self) -> BusWitness | None:
        """The bus's witness, on a bus every node shares (none on adapters of the modules' own)."""
        interface = str(self.bus_options.get("interface")) if self.kind == "can" else PYTHON_CAN.get(self.kind)
        own_adapters = self.hardware is not None and any(h.can_channel for h in self.hardware.modules.values())
        if interface not in SHARED_INTERFACES or own_adapters or not self._bus_channel:
            return None
        options = {k: v for k, v in self.bus_options.items() if k not in ("interface", "channel")}
        try:
            return BusWitness(str(interface), str(self._bus_channel), **options)
        except TransportUnavailable as exc:
            self.note(f"no witness of the bus's frames: {exc}")
            return None

    def _exited(self, module: int) -> bool:
        h = self.handles[module]
        return h is not None and not h.running()

    def _failure_text(self, what: str) -> str:
        details = [f"{v.name}: {e}" for v in self.views for e in v.errors]
        return what + (": " + "; ".join(details) if details else "")

    @property
    def go_at(self) -> float | None:
        """The CLOCK_MONOTONIC instant every module started cycling at (None before
        :meth:`start`): a trace record's time minus it, over the period, is its world cycle."""
        return self._go_at

    @property
    def cycle(self) -> int:
        """The world cycle: wall time since ``go`` over the cycle period."""
        if self._go_at is None:
            return 0
        return max(0, int((time.monotonic() - self._go_at) / self.cycle_period))

    def idle(self, most: float) -> float:
        """Seconds the caller may sleep before its next :meth:`tick`: ``most``, or while a
        docking motion or a foot's trip is under way, until :data:`STEP_LEAD_S` before the
        next world cycle begins (they are stepped once per world cycle, from then on)."""
        if self.reaches is None or not self.reaches.busy or self._go_at is None:
            return most
        period = self.cycle_period
        lead = min(STEP_LEAD_S, period / 4)
        into = (time.monotonic() - self._go_at) % period
        wait = period - lead - into
        if wait <= 0 and self.reaches.stepped_in(self.cycle):  # this cycle's step is made: the next one's
            wait += period
        return max(0.0, min(most, wait))

    def motions_due(self) -> bool:
        """Whether the docking motions' step of this world cycle is due now: within
        :data:`STEP_LEAD_S` of the next world cycle."""
        if self._go_at is None:
            return False
        period = self.cycle_period
        into = (time.monotonic() - self._go_at) % period
        return into >= period - min(STEP_LEAD_S, period / 4)

    def poll(self, timeout: float = 0.0) -> None:
        """Read the modules' reports (waiting up to ``timeout`` s for the first)."""
        try:
            item = self.reports.get(timeout=timeout) if timeout > 0 else self.reports.get_nowait()
        except queue.Empty:
            return
        while True:
            self._report(*item)
            try:
                item = self.reports.get_nowait()
            except queue.Empty:
                return

    def _report(self, module: int, rep: Report) -> None:
        v = self.views[module]
        if isinstance(rep, Ready):
            v.ready = True
            if self.emulator is not None:  # its ports are open (if their first byte was not seen)
                for path in self._ports_of[module]:
                    self.emulator.reader_back(path)
        elif isinstance(rep, Status):
            status = {**rep.status, "targets": list(rep.targets) if rep.targets else None} if rep.final else rep.status
            v.heard(status, time.monotonic(), sample_rate=not rep.final)
            if rep.final:
                v.finished = True
                if rep.failed:
                    v.failed = True
        elif isinstance(rep, TraceRecord):
            if self.keep_records:
                self.records.append(dict(rep.record))
            if self.capture is not None:  # the cycle marks replay needs (tools.capture_cycles)
                self.capture.cycle_mark(rep.record, self._docked_links())
        elif isinstance(rep, Effect):
            self.effects.append((module, rep))
            self.log.append(f"{v.name}: effect {rep.kind} {rep.args}")
            self._effect(module, rep.kind, rep.args)
        elif isinstance(rep, Log):
            self.log.append(f"{v.name}: {rep.message}")
            end = negotiated_end(rep.message)
            if end is not None:
                self._negotiated[module].add(end)
                found = _NEGOTIATED_AT.search(rep.message)
                if found is not None:  # which connector: for the capture's link marks
                    self._bus_links.setdefault(end[0], {})[end[1]] = (module, int(found.group(1)))
        elif isinstance(rep, Failure):
            v.errors.append(rep.message)
            v.failed = True
        elif isinstance(rep, Exited):
            if rep.life != self.lives[module] - 1:
                return  # a previous life's end, read after this life started
            h = self.handles[module]
            code = h.exit_code() if h is not None else None
            if h is not None and not v.killed and code not in (0, None):
                v.failed = True
                v.errors.append(f"exited with code {code}")
            v.alive = False

    def _effect(self, module: int, kind: str, args: list[Any]) -> None:
        """Carry out what a native asked of the physical world (as the Robot does)."""
        if kind == "foot":  # a released foot's own trip and creep (firmware.motion.foot)
            self.log.append(f"{self.topology.names[module]}: foot {' '.join(map(str, args))}")
            if self.reaches is not None and args:
                self.reaches.foot_event(module, str(args[0]))
            return
        if kind not in ("reach_and_dock", "reach_dock", "release", "latch", "reach_ended"):
            return  # "assist" and the like only move joints, which the module did itself
        try:
            if kind in ("latch", "reach_ended"):  # of a reach the module carries out itself
                if self.reaches is not None:
                    if kind == "latch":
                        closed = self.reaches.own_latch(module, int(args[0]), int(args[1]), int(args[2]))
                        self._send(module, LatchAnswer(int(args[0]), closed))
                        self.latch_answers += 1
                    else:
                        self.reaches.own_ended(module, int(args[0]), str(args[1]))
            elif kind == "release" and self._own_latch(module, int(args[0])):
                self.note(f"release {self.where(module, int(args[0]))}: undocked when its latch opens")
            elif kind == "release":
                docking.release(self, module, int(args[0]))
            elif kind == "reach_dock":
                connector, route, target = int(args[0]), [int(c) for c in args[1]], int(args[2])
                if self.reaches is not None and self.modules_move:  # the module moves its chain itself
                    self.reaches.own_started(module, connector, route, target)
                elif self.reaches is not None:  # by motion, on the stand-in's physics
                    self.reaches.start(module, connector, route, target)
                else:
                    docking.reach_and_dock_to(self, module, connector, route, target)
            else:
                connector, route = int(args[0]), [int(c) for c in args[1]]
                if self.reaches is not None and self.modules_move:  # the modules carry it out themselves
                    self.reaches.own_assimilate(module, connector, route)
                elif self.reaches is not None:  # the foot comes by its own gaits, then they dock by motion
                    self.reaches.assimilate(module, connector, route)
                else:
                    docking.reach_and_dock(self, module, connector, route)
        except (IndexError, TypeError, ValueError):
            self.log.append(f"{self.topology.names[module]}: malformed {kind} {args!r}")

    def _own_latch(self, module: int, connector: int) -> bool:
        """Whether ``module``'s ``connector`` is held by its emulated latch's horn (closed now):
        its ``release`` opens it, and the world undocks when it sees it open."""
        return connector == LATCH_CONNECTOR and self._horns_closed.get(module, False)

    def watch_latches(self) -> None:
        """Each emulated latch's horn (``latch_emulator``): one that got past the pins docks its
        face to the face it mated with (physics, then the link, as :meth:`latch`); one that
        opened undocks what it held (as ``release``)."""
        if self.physics is None:
            return
        for m in self.horn_links:
            closed = self.physics.horn_closed(m)
            if closed == self._horns_closed[m]:
                continue
            self._horns_closed[m] = closed
            mate = self.physics.mated[m]
            if closed and mate is not None:
                self._horn_docks(m, mate)
            elif closed:
                self.note(f"{self.where(m, LATCH_CONNECTOR)}: its latch closed, on no face")
            elif self.link_map.peer_of((m, LATCH_CONNECTOR)) is not None:
                self.horn_links[m] = None
                self.note(f"{self.where(m, LATCH_CONNECTOR)}: its latch opened")
                docking.release(self, m, LATCH_CONNECTOR)

    def _horn_docks(self, module: int, mate: tuple[int, int]) -> None:
        """``module``'s latch got past the pins on ``mate``: dock them (as :meth:`latch`), the
        infrared pair read before the dock (a docked face reads none)."""
        pair = self.reaches.pair(module, LATCH_CONNECTOR) if self.reaches is not None else None
        if not self.latch(module, LATCH_CONNECTOR, *mate):
            return
        self.horn_links[module] = mate
        if self.reaches is not None and pair is not None:
            self.reaches.record_latch(module, LATCH_CONNECTOR, *mate, how="by its latch's horn", pair=pair)

    def push_readings(self, modules: Iterable[int] | None = None) -> None:
        """Measure the sensors of ``modules`` (default: every live one) in physics and send
        each its readings, rounded and clamped to the profile's ranges."""
        if self.physics is None or not self.measured:
            return
        started = time.perf_counter()
        alive = [m for m in (range(self.topology.size) if modules is None else modules) if self.views[m].alive]
        specs = {n: self.profile.sensor(n) for n in self.measured}
        for m, values in self.physics.readings(alive).items():
            # physics measures in pairs (roll with pitch, a distance with its alignment):
            # only what the program declares is sent
            self._send(m, Readings({n: specs[n].reading(v) for n, v in values.items() if n in specs}))
        self.push_times.append(time.perf_counter() - started)

    # ------------------------------------------------------------ the docking world

    def peer_of(self, end: End) -> End | None:
        return self.link_map.peer_of(end)

    def running(self, module: int) -> bool:
        return self.views[module].alive

    def aligned(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        # as sim.runner does: the motions that align two connectors are not modelled
        return self.physics is None or self.physics.aligned(a, a_conn, b, b_conn)

    def schedule(self, cycles_from_now: int, action: Callable[[], None]) -> None:
        self._pending.append((self.cycle + cycles_from_now, action))

    def where(self, module: int, connector: int) -> str:
        return f"{self.topology.names[module]}.{self.profile.connector_name(connector)}"

    def note(self, message: str) -> None:
        self.log.append(f"world cycle {self.cycle}: {message}")

    def tick(self) -> None:
        """Read reports; carry out due effects; notice modules that died on their own; step
        physics up to now (with the PyBullet stand-in)."""
        self.poll()
        if self.physics is not None and self._go_at is not None and time.monotonic() >= self._go_at:
            self.physics.advance()
            if self.measured and self.cycle >= self._next_push:
                self._next_push = self.cycle + self.sensor_every
                self.push_readings()
            if self.reaches is not None:
                self.reaches.step(self.cycle, due=self.motions_due())
            self.watch_latches()
        if self._pending:
            now = self.cycle
            due = [action for when, action in self._pending if when <= now]
            self._pending = [(when, action) for when, action in self._pending if when > now]
            for action in due:
                action()
        for m, h in enumerate(self.handles):
            v = self.views[m]
            if h is not None and v.alive and not h.running():
                code = h.exit_code()
                if code is not None and code != 0 and not v.killed:
                    if not v.failed:
                        v.errors.append(f"exited with code {code}")
                    v.failed = True

    def done(self) -> bool:
        """Every module that was not killed has finished (or died)."""
        return all(v.finished or v.killed or v.failed or not v.alive for v in self.views)

    # ------------------------------------------------------------ events

    def apply(self, event: Event) -> None:
        """Carry out an event now (see the module docs)."""
        started = time.monotonic()
        if event.kind == "cut":
            self.cut(event.module, event.connector)
        elif event.kind == "dock":
            self.dock(event.module, event.connector, event.other, event.other_connector)
        elif event.kind == "kill":
            self.kill(event.module)
        elif event.kind == "restart":
            self.restart(event.module)
        elif event.kind == "inject" and event.hormone is not None:
            self.inject(event.module, event.hormone)
        elif event.kind == "sense":
            self.sense(event.module, event.sensor, event.value)
        self.log.append(f"world cycle {self.cycle}: {event.text or event.kind}")
        self.event_times.append((event.text or event.kind, started))

    def cut(self, module: int, connector: int) -> None:
        """Undock: the latch in physics, the emulated infrared link (its modules notice by
        liveness), or both CAN ends told to detach (what was in flight is dropped there)."""
        docking.check_cut(self.link_map.peer_of((module, connector)), self.where(module, connector))
        link = self.link_map.peer[(module, connector)]
        self.link_map.remove(link)
        gone = {(link.a, link.a_conn), (link.b, link.b_conn)}  # for the capture's marks: no longer docked
        for bus_link in [k for k, ends in self._bus_links.items() if gone & set(ends.values())]:
            del self._bus_links[bus_link]
        if self.capture is not None:
            self.capture.links_now(self._docked_links())
        if self.physics is not None:
            self.physics.undock(module, connector)
        if self.contacts is not None:  # the modules sense it and release their link
            self.contacts.break_contact((link.a, link.a_conn), (link.b, link.b_conn))
        elif self.emulator is None:
            for m, c in ((link.a, link.a_conn), (link.b, link.b_conn)):
                self._send(m, Detach(c))

    def _docked_links(self) -> dict[int, tuple[tuple[int, int], tuple[int, int]]]:
        """The links docked now, for the capture's link marks: link id -> (module, connector)
        at side 0 and side 1: the world's links, or on a bus whose modules negotiate their
        links over contacts, the ids they negotiated (the frames carry those), as both
        modules logged them."""
        if self.contacts is None:
            return {w.link_id: ((w.a, w.a_conn), (w.b, w.b_conn)) for w in self.link_map.peer.values()}
        return {link: (ends[0], ends[1]) for link, ends in self._bus_links.items() if len(ends) == 2}

    def dock(self, a: int, a_conn: int, b: int, b_conn: int) -> None:
        docking.check_dock(self.profile, self.link_map.peer.__contains__, self.where, a, a_conn, b, b_conn)
        link = self.link_map.add(a, a_conn, b, b_conn)
        if self.contacts is not None:  # the modules sense the contact and negotiate a link
            self.contacts.make_contact((a, a_conn), (b, b_conn))
        else:
            for m, c in ((a, a_conn), (b, b_conn)):
                self._send(m, Attach(c, self.link_map.end(link, m, c)))
        if self.physics is not None:
            self.physics.dock(a, a_conn, b, b_conn)  # latches only if aligned within tolerance

    def latch(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        """A docking motion's latch: in physics first (refused unless aligned within the
        tolerance), then the link as for a ``dock``; False (logged) if either refuses."""
        try:
            docking.check_dock(self.profile, self.link_map.peer.__contains__, self.where, a, a_conn, b, b_conn)
        except TopologyError as exc:
            self.note(f"latch {self.where(a, a_conn)} -> {self.where(b, b_conn)} refused: {exc}")
            return False
        if self.physics is not None and not self.physics.dock(a, a_conn, b, b_conn):
            self.note(f"latch {self.where(a, a_conn)} -> {self.where(b, b_conn)} refused by physics: not aligned")
            return False
        link = self.link_map.add(a, a_conn, b, b_conn)
        if self.contacts is not None:
            self.contacts.make_contact((a, a_conn), (b, b_conn))
        else:
            for m, c in ((a, a_conn), (b, b_conn)):
                self._send(m, Attach(c, self.link_map.end(link, m, c)))
        return True

    def send_readings(self, module: int, readings: Readings | Floor) -> None:
        """Send ``module`` sensor readings measured or known outside it (a running module only)."""
        self._send(module, readings)

    def hold(self, module: int, targets: Mapping[int, float]) -> None:
        """Tell ``module`` to hold ``targets`` (degrees by DOF index) on its servos in place of
        its program's (a docking motion owns those joints); empty: they are the program's."""
        self.holds_sent += 1
        self._send(module, Hold(dict(targets)))

    def plug_cable(self, module: int, connector: int) -> tuple[int, str]:
        """A programming cable into ``module``'s free ``connector`` (serial): an emulated
        link whose other end is a pty for the flasher. Returns (link id, the flasher's path)."""
        if self.emulator is None:
            raise HilWorldError("a programming cable needs the serial transport's link emulator")
        if self.link_map.peer_of((module, connector)) is not None:
            raise HilWorldError(f"{self.where(module, connector)} is docked: a cable needs a free connector")
        self.cables_plugged += 1
        link = self.emulator.add_link(max(self.emulator.links, default=0) + CABLE_LINK_IDS)  # apart from the dock's
        self._cable_paths.add(link.paths[1])
        self._send(module, Attach(connector, PortEnd(link.paths[0])))
        return link.link_id, link.paths[1]

    def count_cable(self, counters: LinkCounters, ends: Iterable[HeldEnd] = ()) -> None:
        """Add a programming cable's transport counters (at its end) to the run's frames, and
        on a bus the spans it held its link ends in (those held still: until now)."""
        now = time.time()
        self._cable_spans += [((e.link_id, e.side), e.since, now if e.until is None else e.until) for e in ends]
        for key in _FRAME_TERMS:
            name = f"frames_{key}"
            self.cable_frames[name] = self.cable_frames.get(name, 0) + int(getattr(counters, key))

    def unplug_cable(self, module: int, connector: int, link_id: int) -> None:
        """The cable is pulled out: the module's connector is free again."""
        self._send(module, Detach(connector))
        if self.emulator is not None:
            self.emulator.undock(link_id)

    def touch_cable(self, module: int, connector: int) -> tuple[int, str]:
        """A programming cable against ``module``'s free ``connector`` on a bus: the contact
        emulator gets a connector for the cable (one that may dock to the module's) and makes
        the contact; the module senses it and negotiates a link with whoever is there.
        Returns (the cable's connector, the path of its connector-local channel)."""
        if self.contacts is None:
            raise HilWorldError("a programming cable on a bus needs the contact emulator (--transport can)")
        if self.link_map.peer_of((module, connector)) is not None:
            raise HilWorldError(f"{self.where(module, connector)} is docked: a cable needs a free connector")
        mate = next(c for c in range(1, self.profile.connector_count + 1) if self.profile.can_link(c, connector))
        end = (CABLE_MODULE - module, mate)  # the cable is no module: an id no module has
        if end not in self._cable_ends:
            self._cable_ends[end] = self.contacts.add_connector(*end)
        self.cables_plugged += 1
        self.contacts.make_contact((module, connector), end)
        return mate, self._cable_ends[end]

    def pull_cable(self, module: int, connector: int, mate: int) -> None:
        """The bus cable is taken away: the contact breaks, and the module releases its link."""
        if self.contacts is not None:
            self.contacts.break_contact((module, connector), (CABLE_MODULE - module, mate))

    def kill(self, module: int) -> None:
        h = self.handles[module]
        if h is None or not self.views[module].alive:
            return
        self.views[module].killed = True
        if self.physics is not None:  # its infrared emitters go dark with it
            self.physics.world.unpowered.add(module)
        dying = time.time()
        h.end(grace=0.0 if not self.threads else 1.0)
        if isinstance(h, ProcessModule):
            h.proc.wait(5)
        self.poll()  # what it said last (its final status, its end) is read before any next life
        self.views[module].alive = False
        # a killed process reports nothing more: the emulator (the bus's witness) counts what it read and sent
        self._unreported[module] = self._witnessed_links and not self.views[module].finished
        if self._unreported[module]:
            self._life_wall[module] = (self._life_wall[module][0], dying)
        if self.emulator is not None:
            for path in self._ports_of[module]:
                self.emulator.reader_gone(path)

    def restart(self, module: int) -> None:
        self.kill(module)
        if self.reaches is not None:  # a new life holds nothing: what a motion wants is sent again
            self.reaches.holding.pop(module, None)
            self.reaches.docking_sent.pop(module, None)
        if self.physics is not None:
            self.physics.world.unpowered.discard(module)
        self._spawn(module, self.cycles, self.phase_draw.next(self.program.clock_cycle))
        deadline = time.monotonic() + 30
        while not self.views[module].ready and time.monotonic() < deadline:
            self.poll(0.02)
            if self._exited(module):
                break
        for name, value in self.sensed.get(module, {}).items():  # its surroundings did not restart
            self._send(module, Sense(name, value))
        self.push_readings([module])
        if self.modules_move and self.reaches is not None:
            self._send(module, OwnMotions())
        # it starts on a world cycle boundary a little ahead (Hellos first) and runs the
        # cycles left from there, so it stops with the others
        base = self._go_at if self._go_at is not None else time.monotonic()
        start = self.cycle + 1 + int(self.start_delay / self.cycle_period)
        left = None if self.cycles is None else max(0, self.cycles - start)
        if left == 0:  # it booted too slowly to run any of the cycles left: say so, not pass
            self.late_restarts.append((module, self.cycle))
        self._send(module, Go(at=base + start * self.cycle_period, cycles=left))

    def inject(self, module: int, hormone: Hormone) -> None:
        text = hormone.name if not hormone.args else hormone.content()
        self._send(module, Inject(text))

    def sense(self, module: int, name: str, value: int) -> None:
        """Sensor ``name`` of ``module`` reads ``value`` from now on (a ``sense`` event)."""
        self.sensed.setdefault(module, {})[name] = value
        before = time.monotonic()
        self._send(module, Sense(name, value))
        self.sense_times.append((module, name, value, before, time.monotonic()))

    def _send(self, module: int, cmd: Command) -> None:
        h = self.handles[module]
        if h is not None and self.views[module].alive:
            if self.emulator is not None and isinstance(cmd, Attach) and isinstance(cmd.end, PortEnd):
                self._ports_of[module].add(cmd.end.url)  # a new port's counts begin in this life
                self._life_start[module].setdefault(cmd.end.url, self.emulator.side_counts(cmd.end.url))
            h.send(cmd)

    def run_events(self, events: Iterable[Event], applied: set[int]) -> None:
        """Apply the events whose cycle has come (``applied`` holds indices already done)."""
        now = self.cycle
        for i, ev in enumerate(events):
            if i not in applied and ev.cycle <= now:
                applied.add(i)
                self.apply(ev)

    # ------------------------------------------------------------ reading, stopping

    def rows(self) -> list[dict[str, Any]]:
        """One row per module for the status table and the summary (see hil.status)."""
        return status_rows(self.views)

    def frame_accounting(self) -> dict[str, int]:
        """Where every frame went, each term counted where it happened (docs/hil.md, "Counting
        frames"): ``sent + split = received + corrupted + dropped + unhandled + read_by_killed
        + lost_on_link + unread + merged``. The modules' transports (and the cables') count
        what they sent and what their decoders read: received, corrupted (failed COBS/CRC),
        dropped (over-long, or raced with a detach) and unhandled (no handler listened); on
        serial links the link emulator counts the rest: frames lost on the line (loss, an
        undocked link, in flight at a cut or the end, due for a dead module), chunks left
        unread in a pty when its module died or stopped, frames a bit error merged into the
        next or split in two, and what a killed module sent and read (its own counters die
        with it); on a CAN bus its witness counts the same (frames sent to an end nobody held,
        left unread when an end was let go, a killed process's). ``unaccounted`` is what
        breaks the identity: 0 in every run that went right."""
        totals = dict.fromkeys((*_FRAME_TERMS, "read_by_killed"), 0)
        for m, (v, earlier) in enumerate(zip(self.views, self.earlier_lives, strict=True)):
            counts = self._module_counts(m, v, earlier)
            for key in _FRAME_TERMS:
                totals[key] += counts[key]
            totals["read_by_killed"] += counts["read_by_killed"]
        for key in _FRAME_TERMS:
            totals[key] += self.cable_frames.get(f"frames_{key}", 0)
        link = self.emulator.totals() if self.emulator is not None else LinkStats()
        if self.kind == "inproc" and self._bus_channel:  # the in-process bus counts the same
            bus = inproc_bus(self._bus_channel)
            link.frames_lost, link.frames_unread = bus.lost, bus.unread
        if self.witness is not None:  # the CAN bus's witness counts the same
            link.frames_lost = self.witness.total() - self._read_in(self._held_spans())
            link.frames_unread = sum(max(0, given - read) for _who, _s, _c, read, given in self._bus_tallies())
        totals["lost_on_link"] = link.frames_lost
        totals["unread"] = link.frames_unread
        totals["merged"] = link.frames_merged
        totals["split"] = link.frames_split
        accounted = sum(totals[k] for k in (*_ARRIVED, "read_by_killed", "lost_on_link", "unread", "merged"))
        totals["unaccounted"] = totals["sent"] + totals["split"] - accounted
        return totals

    @property
    def frames_witnessed(self) -> bool:
        """Whether a witness counts the frames no module can (sent to nobody, left unread):
        the link emulator on serial links, the bus on ``inproc``, the bus's witness on a CAN
        bus every node shares. Real serial ports and CAN adapters of the modules' own have
        none: a frame sent to a link nobody holds any more is counted nowhere."""
        return self._witnessed_links or self.kind == "inproc"

    @property
    def _witnessed_links(self) -> bool:
        """Whether a witness counts what each link end took and was given: the link emulator,
        or the bus's witness."""
        return self.emulator is not None or self.witness is not None

    def unaccounted_where(self) -> list[str]:
        """Where frames went uncounted (serial links: each module's and cable's own counts
        against what the link emulator carried from and into its ports); [] when they agree."""
        if self.witness is not None:
            return self._bus_disagreements()
        if self.emulator is None:
            return [] if not self.frame_accounting()["unaccounted"] else [f"on the {self.kind} links"]
        out: list[str] = []
        for m, (v, earlier) in enumerate(zip(self.views, self.earlier_lives, strict=True)):
            counts = self._module_counts(m, v, earlier)
            read = sum(counts[k] for k in _ARRIVED) + counts["read_by_killed"]
            out += self._disagreement(v.name, counts["sent"], read, self._ports_of[m])
        cable_read = sum(self.cable_frames.get(f"frames_{k}", 0) for k in _ARRIVED)
        out += self._disagreement("the cables", self.cable_frames.get("frames_sent", 0), cable_read, self._cable_paths)
        return out

    def _disagreement(self, who: str, sent: int, read: int, paths: Iterable[str]) -> list[str]:
        assert self.emulator is not None
        sides = [self.emulator.side_counts(p) for p in paths]
        carried = sum(c.sent for c in sides)
        given = sum(c.written - c.unread for c in sides)
        if (sent, read) == (carried, given):
            return []
        return [f"{who} counted {sent} sent and {read} read; its ports took {carried} from it and gave it {given}"]

    def _module_counts(self, module: int, view: ModuleView, earlier: Mapping[str, int]) -> dict[str, int]:
        """What ``module``'s lives counted: its own counters for the lives that reported them,
        the link emulator's for those killed before they could (``read_by_killed``)."""
        reported = not self._unreported[module]
        c = view.status.get("counters", {}) if reported else {}
        out = {k: earlier.get(f"frames_{k}", 0) + int(c.get(f"frames_{k}", 0)) for k in _FRAME_TERMS}
        killed = dict(self.killed_frames[module])
        if not reported:
            for key, n in self._life_frames(module).items():
                killed[key] += n
        out["sent"] += killed["sent"]
        out["read_by_killed"] = killed["read"]
        return out

    def _life_frames(self, module: int) -> dict[str, int]:
        """The current life's frames as the link emulator counted them at its ports: sent
        from them, and read from them (written into them, less what was left unread)."""
        sent = read = 0
        if self.witness is not None:
            spans = self._life_spans(module)
            sent = sum(self.witness.sent_from(end) for end in {end for end, _since, _until in spans})
            read = self._read_in(spans)
        if self.emulator is not None:
            for path in self._ports_of[module]:
                now = self.emulator.side_counts(path)
                then = self._life_start[module].get(path, SideCounts())
                sent += now.sent - then.sent
                read += (now.written - then.written) - (now.unread - then.unread)
        return {"sent": sent, "read": read}

    # ------------------------------------------------------------ the bus's witness

    def _life_spans(self, module: int) -> list[Span]:
        """The spans ``module``'s current life held its link ends in: as its last status says,
        and for a killed life, until it was killed, with the ends it negotiated after that
        status held from its start."""
        start, killed = self._life_wall[module]
        spans = spans_of(self.views[module].status, killed)
        if killed is not None:
            held = {end for end, _since, _until in spans}
            spans += [(end, start, killed) for end in self._negotiated[module] - held]
        return spans

    def _spans(self, module: int) -> list[tuple[Span, bool]]:
        """Every life's spans, each with whether its life reported its counters."""
        return [*self._bus_spans[module], *((s, not self._unreported[module]) for s in self._life_spans(module))]

    def _held_spans(self) -> list[Span]:
        """Every span any module or cable held a link end in."""
        return [span for m in range(self.topology.size) for span, _ in self._spans(m)] + self._cable_spans

    def _read_in(self, spans: Iterable[Span]) -> int:
        """Frames the bus's witness saw sent to the ends within ``spans``."""
        assert self.witness is not None
        return sum(self.witness.sent_to(end, [(since, until)]) for end, since, until in spans)

    def _bus_tallies(self) -> list[tuple[str, int, int, int, int]]:
        """For each module and the cables: (who, frames it counted sent, frames the bus's
        witness saw sent from its link ends, frames it counted read, frames the witness saw
        sent to its ends while it held them), over the lives that reported their counters
        (a killed life's frames are the witness's only)."""
        assert self.witness is not None
        out = []
        for m, (v, earlier) in enumerate(zip(self.views, self.earlier_lives, strict=True)):
            counts = self._module_counts(m, v, earlier)
            spans = self._spans(m)
            carried = sum(self.witness.sent_from(end) for end in {span[0] for span, _ in spans})
            given = self._read_in(span for span, reported in spans if reported)
            out.append((v.name, counts["sent"], carried, sum(counts[k] for k in _ARRIVED), given))
        if self._cable_spans:
            ends = {end for end, _since, _until in self._cable_spans}
            out.append((
                "the cables", self.cable_frames.get("frames_sent", 0), sum(self.witness.sent_from(e) for e in ends),
                sum(self.cable_frames.get(f"frames_{k}", 0) for k in _ARRIVED), self._read_in(self._cable_spans),
            ))  # fmt: skip
        return out

    def _bus_disagreements(self) -> list[str]:
        """Where a bus's frames went uncounted: each module's (and the cables') own counts
        against what the witness saw sent from its link ends and to them while it held them
        (it may have left some unread when it let an end go, never read more), and frames
        from link ends nobody held."""
        assert self.witness is not None
        out = [
            f"{who} counted {sent} sent and {read} read; the bus carried {carried} from its link ends "
            f"and {given} to them while it held them"
            for who, sent, carried, read, given in self._bus_tallies()
            if sent != carried or read > given
        ]
        held = {end for end, _since, _until in self._held_spans()}
        stray = sum(self.witness.sent_from(end) for end in self.witness.ends() if end not in held)
        if stray:
            out.append(f"{stray} frame(s) came from link ends no module held")
        return out

    def sorted_records(self) -> list[dict[str, Any]]:
        """Trace records merged from the modules, by cycle then module."""
        return sorted(self.records, key=lambda r: (r["cycle"], r["module"]))

    def stop(self, grace: float = 3.0) -> None:
        """Tell every module to stop, end the stragglers by pid, close the link emulator."""
        # _closed is set only once everything is released: a stop interrupted by a second
        # Ctrl-C can be called again and finishes the job (every step below is idempotent)
        if self._closed:
            return
        gc.unfreeze()  # a process that runs worlds one after another (tests) collects them again
        for m, h in enumerate(self.handles):
            if h is not None and h.running():
                self._send(m, Stop())
        deadline = time.monotonic() + grace
        while any(h is not None and h.running() for h in self.handles) and time.monotonic() < deadline:
            self.poll(0.05)
        for h in self.handles:
            if h is not None:
                h.end(grace=1.0)
        self.poll()
        for m, v in enumerate(self.views):  # ended before it reported its counters: counted at its ports
            if self._witnessed_links and self.handles[m] is not None and not v.finished and not v.killed:
                self._unreported[m] = True
                self._life_wall[m] = (self._life_wall[m][0], time.time())
        if self.emulator is not None:  # what is left on the lines and in the ptys is counted
            self.emulator.close()
        if self.witness is not None:  # the last frames on the bus are counted
            self.witness.close()
        if self.physics is not None:
            self.physics.close()
        if self.tracker is not None:
            self.tracker.close()
        if self.bus_tap is not None:
            self.bus_tap.close()
        if self.contacts is not None:
            self.contacts.close()
        shutil.rmtree(self.workdir, ignore_errors=True)
        self._closed = True

    def __enter__(self) -> World:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


#: The modules' (and cables') own terms of the frame accounting, and those that arrived.
_FRAME_TERMS = ("sent", "received", "corrupted", "dropped", "unhandled")
_ARRIVED = ("received", "corrupted", "dropped", "unhandled")
#: The status counters the frame accounting adds up.
FRAME_COUNTERS = frozenset(f"frames_{k}" for k in _FRAME_TERMS)


def module_pids(world: World) -> Sequence[int]:
    """The pids of the world's module processes (tests check they are gone)."""
    return [h.pid for h in world.handles if isinstance(h, ProcessModule)]
