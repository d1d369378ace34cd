"""Rebuild every module's engine, cycle by cycle, from a capture of a loop run.

Inputs, all from the capture (:mod:`tools.capture_cycles` says what a cycle mark holds and
where it comes from):

* the **link marks** make each link end of the capture a module's connector;
* the **frames**: per connector, the hormones delivered to it (not lost on the link, not
  corrupted) in the order they were sent, and the hormones sent through it;
* each module's **cycle marks**, in its order: LocalTimer as the cycle began, the status it
  reported for the cycle (a send that failed in it is not told apart: its connector reads 0
  from the cycle's start), how many hormones it took in at each connector, what was
  injected, the sensors.

For each mark the module's engine (one per life, started at the mark's timer phase) is given
that status and those sensors, the next hormones delivered at each connector (as many as the
mark says, sorted by connector as the runtime sorts its mailbox) and the injected ones, and
steps; the record it then gives is the trace record the module wrote (:mod:`dh2rt.records`).
What it sent is checked against the frames the module sent, in order, per connector.

What the capture lacks is said, with where, and replay carries on (:class:`Note`):

* a hormone the mark says was taken in with no frame in the capture that could have been it
  (sent no later than :data:`LATE_FRACTION` of a period after the cycle began): the frame is
  missing (removed from the file, or never captured); the engine steps without it, and its
  variables, actuators and receptor statuses are uncertain from there (its timer and status
  are not: the marks give them again each cycle);
* cycles with no mark (a gap in the module's cycle numbers): the state is carried over and
  the timer taken from the next mark, the next certainty;
* a cycle whose timer is the previous cycle's: the module was paused (the console's
  ``pause``): the engine does not step, and what came is held for the cycle it resumes in,
  as the runtime holds it;
* any other timer that does not follow from the previous cycle (a gap): taken from the mark;
* a hormone delivered to the module that it never took in (stamped before its cycle before
  last began, and none of the cycles since counted it): the module ignored it (its link was
  down, or not verified again yet, as the runtime's liveness machine does); let go;
* a sent hormone that is not the next frame the module sent through that connector: a
  divergence between the rebuilt engine and the robot (or a frame missing from the capture).

A send through a connector no link was ever attached at fails, as the runtime's does (and
sets its status to 0): it is not in the record's ``sent``; so does one through a connector
the module reported unlinked that the capture does not have (a bus link released at a cut).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import statistics
from collections import defaultdict, deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from dh2rt.engine import Engine
from dh2rt.errors import DH2Error
from dh2rt.events import parse_hormone
from dh2rt.hormone import Arrival, Emission, Hormone
from dh2rt.natives import STANDARD_NATIVES
from dh2rt.program import CompiledProgram, CompiledReceptor, ModuleState
from dh2rt.records import cycle_json
from dh2rt.wire.frame import program_digest
from tools.capture_cycles import CycleMark, LinkMark, Mark
from tools.decode import Hop

#: A frame taken in at a cycle was delivered before the cycle read its links, a moment after
#: the cycle's start; a frame sent later than this share of a period after the start is taken
#: not to be the one the mark counts (it is a later cycle's: the one counted is missing).
LATE_FRACTION = 0.5
#: How far apart the capture's wall clock and a mark's time (moved from the module's
#: monotonic clock when the mark was written) may be, in seconds.
CLOCKS = 0.002
#: A module and connector: what a link end of the capture is.
End = tuple[int, int]


@dataclass(frozen=True, slots=True)
class Note:
    """Something replay cannot know or found wrong, and where: ``kind`` is ``missing``
    (a frame), ``gap`` (cycles without marks), ``timer``, ``paused``, ``diverged`` (a send the capture
    does not have there), ``ignored`` (a frame the module did not take in: a fact of the run,
    not a gap) or ``unmapped`` (frames on a link no mark names)."""

    kind: str
    module: int | None
    name: str
    life: int
    cycle: int | None
    text: str

    def line(self) -> str:
        where = f"{self.name} (module {self.module})" if self.module is not None else "capture"
        if self.cycle is not None:
            where += f" cycle {self.cycle}" + (f", life {self.life}" if self.life else "")
        return f"{where}: {self.text}"

    def to_json(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in ("kind", "module", "name", "life", "cycle", "text")}


@dataclass(frozen=True, slots=True)
class Step:
    """One rebuilt cycle: its mark, the trace record, the receptors whose actions ran, what
    the engine took in (with the hops they were) and what it sent; ``engine`` is the state
    after it (the same object for every step of one life)."""

    mark: CycleMark
    record: dict[str, Any]
    fired: tuple[str, ...]
    arrivals: tuple[Arrival, ...]
    sent: tuple[Emission, ...]
    engine: Engine
    uncertain: str  # why the engine's state may not be the robot's, or ""
    previous_type: str | None  # the type after the module's previous cycle (None: its first)


@dataclass
class _Module:
    engine: Engine
    life: int
    cycle: int
    uncertain: str = ""
    type_name: str | None = None
    paused_at: int | None = None  # the last cycle it was paused in (see Rebuild._module)


@dataclass
class Frames:
    """The capture's hormone frames by module and connector (see the module docs)."""

    inbound: dict[End, deque[Hop]] = field(default_factory=lambda: defaultdict(deque))
    outbound: dict[End, deque[Hop]] = field(default_factory=lambda: defaultdict(deque))
    digests: set[str] = field(default_factory=set)
    #: module -> (time, digest) of each Hello it sent: a new digest is a program switch
    hellos: dict[int, list[tuple[float, str]]] = field(default_factory=lambda: defaultdict(list))
    unmapped: set[int] = field(default_factory=set)
    first_lost: dict[int, float] = field(default_factory=dict)  # link -> its first frame lost


def digest_of(program: CompiledProgram) -> str:
    """The digest a module's Hello names for ``program`` (hex)."""
    return program_digest(program.image).hex()


def sort_frames(hops: Iterable[Hop], links: Mapping[int, tuple[End, End]]) -> Frames:
    """Each hormone frame to the connector that sent it and (delivered) the one it reached."""
    frames = Frames()
    for hop in hops:
        if hop.kind == "hello":
            frames.digests.add(hop.text.split()[0])
            sent_by = links.get(hop.link) if hop.link is not None and hop.side is not None else None
            if sent_by is not None and hop.side is not None:
                frames.hellos[sent_by[hop.side][0]].append((hop.time, hop.text.split()[0]))
        if hop.link is None or hop.side is None or hop.kind not in ("hormone", "routed", "error"):
            continue
        ends = links.get(hop.link)
        if ends is None:
            frames.unmapped.add(hop.link)
            continue
        frames.outbound[ends[hop.side]].append(hop)
        if hop.lost:
            frames.first_lost.setdefault(hop.link, hop.time)
        if hop.kind != "error" and not hop.lost:  # a corrupted frame fails the receiver's CRC
            frames.inbound[ends[1 - hop.side]].append(hop)
    return frames


def watched(program: CompiledProgram, fired: list[str]) -> CompiledProgram:
    """``program`` whose receptors append their names to ``fired`` when their actions run."""

    def wrap(r: CompiledReceptor) -> CompiledReceptor:
        act = r.act

        def acting(state: ModuleState, bindings: dict[str, Any]) -> None:
            fired.append(r.name)
            act(state, bindings)

        return dataclasses.replace(r, act=acting)

    return dataclasses.replace(program, receptors=tuple(wrap(r) for r in program.receptors))


def periods(marks: Sequence[CycleMark]) -> dict[int, float]:
    """Each module's cycle period, the median between its consecutive cycles' starts."""
    by_module: dict[int, list[CycleMark]] = defaultdict(list)
    for m in marks:
        by_module[m.module].append(m)
    out = {}
    for module, ms in by_module.items():
        gaps = [
            (b.t - a.t) / (b.cycle - a.cycle)
            for a, b in itertools.pairwise(ms)
            if b.life == a.life and b.cycle > a.cycle
        ]
        out[module] = statistics.median(gaps) if gaps else 0.1
    return out


class Rebuild:
    """Steps every module's engine through its marks in the capture's time order."""

    def __init__(
        self,
        program: CompiledProgram,
        marks: Sequence[Mark],
        hops: Iterable[Hop],
        flashed: Sequence[CompiledProgram] = (),
    ) -> None:
        self.fired: list[str] = []
        self.program = watched(program, self.fired)
        self.profile = program.profile
        #: the programs a module may run, by the digest its Hello names (the first, and those
        #: given for a flash run: a module switches when its Hellos name another)
        self.flashed = tuple(flashed)
        self.programs = {digest_of(p): watched(p, self.fired) for p in flashed}
        self.programs[digest_of(program)] = self.program
        #: modules that switched to a program replay does not have: (module, life) -> its note
        self.unknown: dict[tuple[int, int], Note] = {}
        self.marks = marks
        links = {m.link: m.ends for m in marks if isinstance(m, LinkMark)}
        #: connectors a link was ever attached at: a send through any other fails, as the
        #: runtime's does through a connector with no link end (and is not sent)
        self.attached = {end for ends in links.values() for end in ends}
        self.cycles = sorted((m for m in marks if isinstance(m, CycleMark)), key=lambda m: (m.time, m.module))
        self.frames = sort_frames(hops, links)
        in_order = sorted(self.cycles, key=lambda m: (m.module, m.life, m.cycle))
        self.period = periods(in_order)
        #: when each cycle began, on the capture's clock
        self._starts = {(m.module, m.life, m.cycle): m.time for m in in_order}
        #: when each cycle ended: its module's next cycle began (what it sent, it sent before)
        self._ends = {
            (a.module, a.life, a.cycle): b.time
            for a, b in itertools.pairwise(in_order)
            if (a.module, a.life) == (b.module, b.life)
        }
        self.notes: list[Note] = [
            Note("unmapped", None, "", 0, None, f"link {link}: frames on a link no link mark names (not replayed)")
            for link in sorted(self.frames.unmapped)
        ]
        self._modules: dict[int, _Module] = {}

    def _new_engine(self, phase: int, program: CompiledProgram | None = None) -> Engine:
        program = program or self.program
        used = {n: STANDARD_NATIVES[n] for n in program.natives if n in STANDARD_NATIVES}
        return Engine(program, timer_phase=phase, natives=used)

    def program_at(self, mark: CycleMark) -> str | None:
        """The digest of the program ``mark``'s cycle ran: the one the module's last Hello
        before the cycle's end named (a switch or a boot sends one in its first cycle);
        None before any Hello (the first program)."""
        end = self._ends.get((mark.module, mark.life, mark.cycle), math.inf)
        named = [d for t, d in self.frames.hellos.get(mark.module, ()) if t < end]
        return named[-1] if named else None

    def _note(self, kind: str, mark: CycleMark, text: str) -> None:
        self.notes.append(Note(kind, mark.module, mark.name, mark.life, mark.cycle, text))

    def steps(self) -> Iterator[Step]:
        """Every cycle rebuilt, but those of a module after it switched to a program replay
        does not have (:attr:`unknown` says which, from which cycle)."""
        for mark in self.cycles:
            if (mark.module, mark.life) in self.unknown:
                continue
            digest = self.program_at(mark)
            if digest is not None and digest not in self.programs:
                note = Note(
                    "program",
                    mark.module,
                    mark.name,
                    mark.life,
                    mark.cycle,
                    f"runs program {digest} from this cycle (its Hello names it), which replay does not have "
                    "(give it with --flashed FILE): this module's later cycles are not rebuilt",
                )
                self.unknown[(mark.module, mark.life)] = note
                self.notes.append(note)
                continue
            yield self.step(mark)

    def _module(self, mark: CycleMark) -> _Module:
        mod = self._modules.get(mark.module)
        digest = self.program_at(mark)
        program = self.programs.get(digest, self.program) if digest is not None else self.program
        if mod is None or mod.life != mark.life:
            mod = _Module(self._new_engine(mark.timer, program), mark.life, mark.cycle - 1)
            self._modules[mark.module] = mod
            if mark.cycle != 0:
                self._note("gap", mark, f"its first cycle in the capture is {mark.cycle}: state before unknown")
                mod.uncertain = f"cycles before {mark.cycle} not in the capture"
        elif mod.engine.program is not program:  # a rollout's switch (as ModuleRuntime.switch_program)
            old = mod.engine
            mod.engine = self._new_engine(old.timer, program)
            for c, remote in enumerate(old.status, 1):
                if remote:
                    mod.engine.link_up(c, remote)
            mod.engine.dof[0], mod.engine.dof[1] = old.dof[0], old.dof[1]
            self._note("switch", mark, f"switched to program {digest} (its Hello names it)")
        if mark.cycle != mod.cycle + 1:
            self._note("gap", mark, f"no marks for cycles {mod.cycle + 1}..{mark.cycle - 1}: state carried over")
            mod.uncertain = mod.uncertain or f"cycles {mod.cycle + 1}..{mark.cycle - 1} not in the capture"
        held = mark.cycle == mod.cycle + 1 and mark.timer == (mod.engine.timer - 1) % mod.engine.clock
        if held:  # the cycle reports the timer the last one did: the engine did not step (paused)
            if mod.paused_at != mod.cycle:
                self._note("paused", mark, "LocalTimer stood still: paused, the engine holds until it resumes")
            mod.paused_at = mark.cycle
        elif mod.engine.timer != mark.timer:
            if mark.cycle == mod.cycle + 1:
                self._note("timer", mark, f"LocalTimer {mark.timer}, not {mod.engine.timer}: taken from the mark")
            mod.engine.timer = mark.timer
        return mod

    def step(self, mark: CycleMark) -> Step:
        """Rebuild one cycle (see the module docs)."""
        mod = self._module(mark)
        engine = mod.engine
        name = self.profile.connector_index
        for connector, remote in mark.status.items():
            c = name(connector)
            if remote == "0":
                engine.link_down(c)
            else:
                engine.link_up(c, name(remote))
        for sensor, value in mark.sensors.items():
            engine.set_sensor(sensor, value)
        self.fired.clear()
        before = mod.type_name
        out: list[Emission] = []
        faults: list[str] = []
        if mod.paused_at == mark.cycle:  # what comes is held for the cycle it resumes in
            arrivals: list[Arrival] = []
        else:
            if mod.paused_at is None or mark.cycle - mod.paused_at > 2:  # held frames are not ignored ones
                self._drop_ignored(mark)
            arrivals = self._arrivals(mark, mod)
            for em in engine.step(arrivals):
                if self._went_out(mark, em):
                    out.append(em)
                else:
                    engine.send_failed(em.through)
            faults = [f"{a[0]}: {a[1]}" for kind, a in engine.effects if kind == "fault"]
        self._check_sent(mark, out)
        record = cycle_json(engine, mark.cycle, mark.module, mark.name, arrivals, out, faults)
        record["t"] = mark.t
        record["life"] = mark.life
        mod.cycle = mark.cycle
        mod.type_name = record["type"]
        return Step(mark, record, tuple(self.fired), tuple(arrivals), tuple(out), engine, mod.uncertain, before)

    def _went_out(self, mark: CycleMark, em: Emission) -> bool:
        """Whether the runtime could send ``em``: not through a connector no link was ever
        attached at; and through one the module reported unlinked (status 0) only if the
        capture has it there (an emulated serial link takes a frame into an undocked link, and
        it is lost; a bus link released at a cut refuses it, and it is not on the wire)."""
        if (mark.module, em.through) not in self.attached:
            return False
        if mark.status.get(self.profile.connector_name(em.through), "0") != "0":
            return True
        queue = self.frames.outbound.get((mark.module, em.through), deque())
        return any(hop.time >= mark.time - CLOCKS and same(hop.hormone, em.hormone) for hop in list(queue)[:2])

    def _drop_ignored(self, mark: CycleMark) -> None:
        """Let go of the hormones delivered to the module that it never took in: stamped
        before its cycle before last began (a cycle of leeway for the link's delivery), they
        were there for its last two cycles' reads, and neither counted them (the module
        ignored them: their link was down or not verified again yet)."""
        before = self._starts.get((mark.module, mark.life, mark.cycle - 2))
        if before is None:
            return
        for c in range(1, self.profile.connector_count + 1):
            queue = self.frames.inbound.get((mark.module, c), deque())
            while queue and queue[0].time < before:
                hop = queue.popleft()
                self._note(
                    "ignored",
                    mark,
                    f"{self.describe(hop.hormone)} delivered at {self.profile.connector_name(c)} "
                    f"(sent t {hop.time:.6f}) was not taken in by this cycle: the module ignored it "
                    "(its link down, or not verified again yet)",
                )

    def _arrivals(self, mark: CycleMark, mod: _Module) -> list[Arrival]:
        name = self.profile.connector_index
        late = mark.time + LATE_FRACTION * self.period.get(mark.module, 0.1)
        arrivals: list[Arrival] = []
        for connector in sorted(mark.took, key=name):
            queue = self.frames.inbound.get((mark.module, name(connector)), deque())
            wanted = mark.took[connector]
            got = 0
            while got < wanted and queue and queue[0].time <= late:
                hop = queue.popleft()
                assert hop.hormone is not None and hop.sender is not None
                arrivals.append(Arrival(name(connector), name(hop.sender), hop.hormone))
                got += 1
            if got < wanted:
                missing = wanted - got
                self._note(
                    "missing",
                    mark,
                    f"took in {wanted} hormone(s) at {connector}; the capture has {got} that it could have been: "
                    f"{missing} frame(s) missing from the capture (variables, actuators and receptors "
                    "uncertain from here)",
                )
                mod.uncertain = mod.uncertain or f"a hormone taken in at {connector} in cycle {mark.cycle} is missing"
        for text in mark.injected:
            try:
                arrivals.append(Arrival(0, 0, parse_hormone(text, mod.engine.program.vocabulary, "injected hormone")))
            except DH2Error as exc:
                self._note("missing", mark, f"injected {text!r} is no hormone of the program ({exc})")
        return arrivals

    def describe(self, h: Hormone | None) -> str:
        """A hormone as dump shows it: its content and the path it was sent with."""
        if h is None:
            return "(none)"
        name = self.profile.connector_name
        return h.content() + "".join(f" path {' '.join(f'{name(s)}>{name(r)}' for s, r in h.path)}" for _ in h.path[:1])

    def _check_sent(self, mark: CycleMark, out: Sequence[Emission]) -> None:
        """Each hormone the engine sent must be the next the module sent through that
        connector, by content, path and route (a frame corrupted on the link passes).

        Times: a frame is stamped when the link emulator delivered it (docs/capture.md), after
        its cycle began and possibly (a link's latency, the emulator lagging) after the next
        one began, but never before its cycle began. So a frame stamped before this cycle began
        that does not match is an earlier cycle's that no rebuilt cycle sent (said and let go),
        and one that does not match stamped after this cycle ended is a later cycle's (what the
        engine sent is not in the capture); one that matches is this cycle's however late the
        emulator stamped it."""
        cname = self.profile.connector_name
        period = self.period.get(mark.module, 0.1)
        for c in range(1, self.profile.connector_count + 1):  # sent two cycles ago or more, unmatched
            self._let_go(mark, c, lambda hop: hop.time < mark.time - period)
        end = self._ends.get((mark.module, mark.life, mark.cycle), math.inf)
        for em in out:
            self._let_go(mark, em.through, earlier_other(mark.time - CLOCKS, em.hormone))
            queue = self.frames.outbound.get((mark.module, em.through), deque())
            what = f"sent {self.describe(em.hormone)} through {cname(em.through)}"
            if not queue or (queue[0].time > end and not same(queue[0].hormone, em.hormone)):
                self._note("diverged", mark, f"{what}: not in the capture (missing from it, or diverged)")
                continue
            hop = queue.popleft()
            if hop.kind != "error" and not same(hop.hormone, em.hormone):
                self._note(
                    "diverged",
                    mark,
                    f"{what}; the capture's next frame from there is {self.describe(hop.hormone)} (t {hop.time:.6f})",
                )

    def _let_go(self, mark: CycleMark, connector: int, stale: Callable[[Hop], bool]) -> None:
        """Drop the frames at the head of what ``connector`` sent while ``stale``, each a
        divergence: the module sent it, no rebuilt cycle did."""
        queue = self.frames.outbound.get((mark.module, connector), deque())
        while queue and stale(queue[0]):
            hop = queue.popleft()
            self._note(
                "diverged",
                mark,
                f"the capture has {self.describe(hop.hormone)} sent through {self.profile.connector_name(connector)} "
                f"at t {hop.time:.6f}, in an earlier cycle, and no rebuilt cycle sent it",
            )


def earlier_other(before: float, h: Hormone) -> Callable[[Hop], bool]:
    """Whether a frame was stamped before ``before`` and is not ``h``."""
    return lambda hop: hop.time < before and not same(hop.hormone, h)


def same(a: Hormone | None, b: Hormone) -> bool:
    return a is not None and (a.content(), a.path, a.route) == (b.content(), b.path, b.route)
