"""A module's operator channel: the control family's commands, checked, carried out, passed on
(docs/console.md). :class:`OperatorCore` is the state machine, sans-IO (frames in, frames out
as :class:`Out`); :class:`OperatorChannel` drives it from the module's transport
(``Transport.listen(FrameFamily.CONTROL, ...)``, as :mod:`firmware.flash.door` takes the
transfer family) and persists the last counter accepted in the module's flash directory.

The rules, for every signed command (:mod:`dh2rt.wire.operator`):

* trusted key (module.toml's ``trust``, the keys its flash trusts), a signature that holds
  (libsodium's strict check), and a counter above the last one accepted, or the command is
  **refused**: counted by reason, logged, and passed on as an accepted one would be (flooded,
  or along its route), so that every module judges it for itself and counts its own refusal.
  Only the module at the cable (a flooded command) or where a routed one stops (its route's
  end, or where it cannot go on) answers with REFUSED, routed back to the cable: the console
  gets one answer, not one a module. A module that trusts no key takes no command at all
  (``NO_CONTROL``).
* A refused command opens no loop and no amplifier: a module passes on at most
  :data:`REFUSED_PER_CYCLE` refused commands in one of its cycles (the rest are counted
  ``not_passed_on``), never one with 255 hops, and remembers each one it passed on (the whole
  signed command) for :data:`REFUSED_MEMORY_CYCLES` cycles: a copy that comes back around a
  ring is a *duplicate*, dropped and counted, and the same frame again from the cable is
  refused and answered again but not passed on. A frame is passed on by each module at most
  once however many copies of it reach it, so a flood of made-up frames costs each module at
  most one relay per distinct frame, and at most :data:`REFUSED_PER_CYCLE` a cycle.
* The counter a module accepted last is written to its flash directory before the command
  is carried out (at the module's next cycle), so a restart does not reopen replays (of
  commands that act: a STATE, which only reads, is not written, so that reading the robot
  costs no flash writes). It is written *after* the command is passed on (:meth:`OperatorCore.save`,
  called once the frames :meth:`OperatorCore.received` returned are sent): a flood waits for
  no flash write on its way, where an fsync per hop once spread a PAUSE over 8 modules past
  2 cycles on a busy machine. A module that dies between passing a command on and writing
  its counter takes that one command again once after its restart, which only does what
  the operator asked.
* A command's copies come back around (a flood's in a ring; a routed command's never): the
  command accepted last arriving again from a neighbour (hops > 0) at a connector no copy of
  it came in at yet is a *duplicate*, dropped and counted, not a refusal (each neighbour
  passes a command on to a module once: a second copy through the same connector is not a
  copy). The same from the cable (hops 0), or again through a connector, is a replay: each
  module a replayed command reaches counts it ``REPLAYED``.
* INJECT and STATE travel along their route: a module that is not the end of it passes the
  command on through the route's next connector (NO_ROUTE if nothing is linked there, or the
  command came in elsewhere than the route says); the module at its end injects the hormone
  (its program's, by the digest) or answers with its status.
* PAUSE and RESUME are carried out and flooded through every other attached connector.
* Answers (STATE_REPLY, REFUSED) from further out are relayed towards the cable; the
  cable's connector is the one the last command with hops 0 came in at.
* WATCH, from the cable only, makes the module send the cable a WATCHED frame for every
  hormone it receives (or is given) for the cycles the watch asks, each as the link frame
  it came in as.
"""

from __future__ import annotations

import json
import os
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

from dh2rt.errors import DecodeError, HormoneError
from dh2rt.hormone import Arrival, Hormone
from dh2rt.runtime import ModuleRuntime
from dh2rt.transport.base import FrameFamily, Inbound, Listening
from dh2rt.wire import operator as op
from firmware.outbound import Out

#: The file in a module's flash directory that holds the last counter it accepted.
COUNTER_FILE = "operator.json"
#: Refused commands a module passes on in one of its cycles, at most.
REFUSED_PER_CYCLE = 8
#: Cycles a module remembers a refused command it passed on (its copies that come back
#: within them are duplicates; a ring's come back within a cycle or two).
REFUSED_MEMORY_CYCLES = 16
#: The most hops a command carries (a byte): one with as many is passed on no further.
MAX_HOPS = 255


class OperatorCore:
    """The operator channel's state machine for one module (no I/O: the caller sends what
    :meth:`received` returns, reads the module through ``module`` and persists through
    ``persist``)."""

    def __init__(
        self,
        trust: Sequence[bytes],
        module: ModuleRuntime,
        *,
        last_counter: int | None = None,
        persist: Callable[[int], None] = lambda counter: None,
    ) -> None:
        self.trust = {op.key_id(k): bytes(k) for k in trust}
        self.module = module
        #: the counter accepted last (None: none yet) and that command's signature
        self.last_counter = last_counter
        self._last_signature: bytes | None = None
        #: the connectors copies of the command accepted last came in at
        self._last_from: set[int] = set()
        #: the refused commands passed on (hops 0), each with the cycle it was passed on at
        self._passed_refused: dict[op.Signed, int] = {}
        #: (a cycle, the refused commands passed on in it)
        self._refused_spent = (-1, 0)
        self.persist = persist
        #: a counter accepted and not yet written (:meth:`save` writes it)
        self.unsaved: int | None = None
        #: the connector the cable is on (where the last command with hops 0 came in)
        self.cable: int | None = None
        #: the WATCH under way: (its counter, the hormone index or None, the cycle it ends at)
        self.watch: tuple[int, int | None, int] | None = None
        self.refused: Counter[op.RefusalReason] = Counter()
        self.accepted = 0
        self.duplicates = 0
        self.malformed = 0
        self.relayed = 0
        self.not_passed_on = 0

    @property
    def counters(self) -> dict[str, int]:
        """What the module's status shows of its operator channel."""
        out = {"accepted": self.accepted, "duplicates": self.duplicates, "malformed": self.malformed}
        out["relayed"] = self.relayed
        if self.not_passed_on:
            out["not_passed_on"] = self.not_passed_on
        out.update({f"refused_{r.name.lower()}": n for r, n in sorted(self.refused.items())})
        return out

    def received(self, connector: int, payload: bytes) -> list[Out]:
        """A control frame came in at ``connector``: what to send in answer or onwards."""
        try:
            sender, message = op.decode(payload)
        except DecodeError as exc:
            self.malformed += 1
            self._log(f"operator: a frame at connector {connector} does not decode: {exc}")
            return []
        if isinstance(message, op.Signed):
            return self._command(connector, sender, message)
        if isinstance(message, op.Watched):  # for a cable, never relayed
            return []
        return self._relay(message)

    def save(self) -> None:
        """Write the counter accepted last, if it is not written yet: the caller calls this
        after sending what :meth:`received` returned, before the module's next cycle."""
        if self.unsaved is not None:
            counter, self.unsaved = self.unsaved, None
            self.persist(counter)

    # -- commands ----------------------------------------------------------------------------

    def _command(self, connector: int, sender: int, m: op.Signed) -> list[Out]:
        if m.hops == 0:
            self.cable = connector
        seen = replace(m, hops=0)  # the command itself, however far it came
        passed = self._passed_on_refused(seen)
        if passed and m.hops:
            self.duplicates += 1  # a refused command's copy that came around
            return []
        reason = self._judge(connector, m)
        if reason is None and self.last_counter == m.counter:
            self.duplicates += 1  # a flooded copy that came around
            self._last_from.add(connector)
            return []
        kind = op.message_type(m).name
        route = op.route_of(m.command)
        on_route = route is None or self._on_route(connector, sender, m.hops, route)
        if reason is None and not on_route:
            reason = op.RefusalReason.NO_ROUTE
        if reason is None and isinstance(m.command, op.Watch) and m.hops:
            reason = op.RefusalReason.NO_ROUTE  # a watch is the cable's module's only
        if reason is not None:
            self.refused[reason] += 1
            self._log(f"operator: refused {kind} {m.counter} at connector {connector}: {reason.name}")
            ways = self._ways_on(connector, m, route) if on_route and not passed else None
            if ways and self._may_pass_refused(m, seen):
                onward = [Out(c, op.encode(c, m.onward())) for c in ways]
                # a flood is answered by the cable's module; a routed command where it stops
                return onward + self._refusal(m, None, reason) if route is None else onward
            return self._refusal(m, route, reason)
        self.accepted += 1
        self.last_counter, self._last_signature, self._last_from = m.counter, m.signature, {connector}
        if not isinstance(m.command, op.StateRequest | op.Watch):
            # a STATE only reads: replaying one after a restart tells nothing new, so the flash
            # is written (an fsync on the module's loop) only for commands that act, by save()
            self.unsaved = m.counter
        if isinstance(m.command, op.Watch):
            return self._start_watch(m, m.command)
        ways = self._ways_on(connector, m, route)
        if route is None:  # PAUSE / RESUME: here, then every other way
            self.module.pause(isinstance(m.command, op.Pause))
        elif ways is None:
            self.refused[op.RefusalReason.NO_ROUTE] += 1
            self._log(f"operator: {kind} {m.counter}: nothing linked at connector {route[m.hops][0]}")
            return self._refusal(m, route, op.RefusalReason.NO_ROUTE)
        elif not ways:  # the route's end
            if isinstance(m.command, op.Inject):
                return self._inject(m, m.command, route)
            return self._answer(op.StateReply(m.counter, m.hops, route, self.status()))
        return [Out(c, op.encode(c, m.onward())) for c in ways or ()]

    def _ways_on(self, connector: int, m: op.Signed, route: op.Path | None) -> list[int] | None:
        """The connectors ``m`` goes on through from here when it is accepted: every other
        linked one (flooded), the route's next (routed), none (a WATCH, the route's end), or
        None when the route's next has nothing linked."""
        links = self.module.transport.links
        if isinstance(m.command, op.Watch):
            return []
        if route is None:
            return [c for c in sorted(links) if c != connector]
        if m.hops >= len(route):
            return []
        through = route[m.hops][0]
        return [through] if through in links else None

    def _passed_on_refused(self, seen: op.Signed) -> bool:
        """Whether this module passed the refused command ``seen`` on lately (forgetting
        those older than :data:`REFUSED_MEMORY_CYCLES`)."""
        passed, oldest = self._passed_refused, self.module.cycle - REFUSED_MEMORY_CYCLES
        while passed and next(iter(passed.values())) < oldest:
            del passed[next(iter(passed))]
        return seen in passed

    def _may_pass_refused(self, m: op.Signed, seen: op.Signed) -> bool:
        """Whether the refused ``m`` may go on (this cycle's allowance and the hop byte
        permitting), remembering it if so."""
        cycle = self.module.cycle
        spent = self._refused_spent[1] if self._refused_spent[0] == cycle else 0
        if m.hops >= MAX_HOPS:
            return False
        if spent >= REFUSED_PER_CYCLE:
            self.not_passed_on += 1
            return False
        self._refused_spent = (cycle, spent + 1)
        self._passed_refused[seen] = cycle
        return True

    def _judge(self, connector: int, m: op.Signed) -> op.RefusalReason | None:
        """Why ``m``, come in at ``connector``, is refused here, or None; a duplicate passes
        (the caller tells it)."""
        if not self.trust:
            return op.RefusalReason.NO_CONTROL
        key = self.trust.get(m.key_id)
        if key is None:
            return op.RefusalReason.UNTRUSTED_KEY
        if not op.signature_holds(m, key):
            return op.RefusalReason.BAD_SIGNATURE
        last = self.last_counter
        if last is not None and m.counter <= last:
            came_around = m.counter == last and m.hops and m.signature == self._last_signature
            if not came_around or connector in self._last_from:
                return op.RefusalReason.REPLAYED
        return None

    def _on_route(self, connector: int, sender: int, hops: int, route: op.Path) -> bool:
        """Whether a routed command that passed ``hops`` modules came in where its route says."""
        if hops > len(route):
            return False
        return hops == 0 or route[hops - 1] == (sender, connector)

    def _inject(self, m: op.Signed, command: op.Inject, route: op.Path) -> list[Out]:
        rt = self.module
        if command.digest != rt.digest:
            self.refused[op.RefusalReason.WRONG_PROGRAM] += 1
            self._log(f"operator: INJECT {m.counter} for program {command.digest.hex()}, not this one")
            return self._refusal(m, route, op.RefusalReason.WRONG_PROGRAM)
        try:
            name, args, end = rt.program.vocabulary.decode_content(command.content)
            if end != len(command.content):
                raise DecodeError(f"{len(command.content) - end} byte(s) after the hormone")
            hormone = Hormone(name, args)
            rt.inject(hormone)
        except (DecodeError, HormoneError) as exc:
            self.refused[op.RefusalReason.WRONG_PROGRAM] += 1
            self._log(f"operator: INJECT {m.counter}: {exc}")
            return self._refusal(m, route, op.RefusalReason.WRONG_PROGRAM)
        self._log(f"operator: injected {hormone.content()} ({m.counter})")
        return []

    def _start_watch(self, m: op.Signed, watch: op.Watch) -> list[Out]:
        self.watch = (m.counter, watch.hormone, self.module.cycle + watch.cycles)
        self._log(f"operator: watching for {watch.cycles} cycles ({m.counter})")
        return []

    def arrivals(self, arrivals: list[Arrival]) -> list[Out]:
        """The hormones this cycle brought (the runtime's ``on_arrivals``): WATCHED frames
        for the cable while a watch is under way."""
        watch, rt = self.watch, self.module
        if watch is None:
            return []
        counter, index, ends = watch
        if rt.cycle >= ends or self.cable is None or self.cable not in rt.transport.links:
            self.watch = None
            return []
        out = []
        codec = rt.transport.codec
        for a in arrivals:
            if index is not None and codec.vocabulary.by_name[a.hormone.name].index != index:
                continue
            frame = codec.encode(a.remote or self.cable, a.hormone)
            if len(frame) <= op.MAX_WATCHED_FRAME:
                out.append(Out(self.cable, op.encode(self.cable, op.Watched(counter, rt.cycle, a.at, frame))))
        return out

    def _refusal(self, m: op.Signed, route: op.Path | None, reason: op.RefusalReason) -> list[Out]:
        """REFUSED towards the cable, when the way back is known: straight from the cable,
        or along the part of the route the command travelled. A flooded copy's is not (the
        module at the cable answers for the flood)."""
        if m.hops == 0:
            return self._answer(op.Refused(m.counter, 0, (), reason))
        if route is None or m.hops > len(route):
            return []
        return self._answer(op.Refused(m.counter, m.hops, route[: m.hops], reason))

    # -- answers -----------------------------------------------------------------------------

    def _relay(self, answer: op.Answer) -> list[Out]:
        """An answer from further out, one hop nearer the cable now."""
        self.relayed += 1
        return self._answer(answer)

    def _answer(self, answer: op.Answer) -> list[Out]:
        """Send ``answer`` (held here: ``left`` hops from the cable) one hop back."""
        if answer.left == 0:
            if self.cable is None or self.cable not in self.module.transport.links:
                self._log(f"operator: an answer to {answer.counter} has no cable to go to")
                return []
            return [Out(self.cable, op.encode(self.cable, answer))]
        through = answer.path[answer.left - 1][1]
        if isinstance(answer, op.StateReply):
            back: op.Answer = op.StateReply(answer.counter, answer.left - 1, answer.path, answer.status)
        else:
            back = op.Refused(answer.counter, answer.left - 1, answer.path, answer.reason)
        return [Out(through, op.encode(through, back))]

    def status(self) -> op.ModuleStatus:
        """This module's state as a STATE_REPLY carries it."""
        rt = self.module
        e = rt.engine
        return op.ModuleStatus(
            digest=rt.digest,
            type_index=e.type_index,
            paused=rt.paused,
            timer=e.timer,
            cycle=rt.cycle,
            connectors=tuple(e.status),
            sensors=tuple(e.sensors),
            variables=tuple(e.vars),
            receptors=tuple(e.rstatus),
        )

    def _log(self, message: str) -> None:
        self.module.log.append(f"cycle {self.module.cycle}: {message}")


class OperatorChannel:
    """:class:`OperatorCore` on a module's transport, its counter kept in ``directory``."""

    def __init__(self, rt: ModuleRuntime, trust: Sequence[bytes], directory: Path | None) -> None:
        self.rt = rt
        self.path = None if directory is None else Path(directory) / COUNTER_FILE
        self.core = OperatorCore(trust, rt, last_counter=self._read(), persist=self._write)
        self.listening: Listening = rt.transport.listen(FrameFamily.CONTROL, self._on_control)
        rt.on_arrivals = self._on_arrivals

    def _on_arrivals(self, arrivals: list[Arrival]) -> None:
        for out in self.core.arrivals(arrivals):
            self.rt.transport.send_raw(out.connector, out.frame)

    def _on_control(self, frame: Inbound) -> None:
        for out in self.core.received(frame.connector, frame.payload):
            self.rt.transport.send_raw(out.connector, out.frame)
        self.core.save()

    def _read(self) -> int | None:
        if self.path is None or not self.path.exists():
            return None
        try:
            value = json.loads(self.path.read_text())["last_counter"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            # an unreadable record must not reopen replays: refuse every command until the
            # operator's counter passes the largest one can be
            self.rt.log.append(f"operator: {self.path} unreadable ({exc}); commands refused until it is rewritten")
            return (1 << 64) - 1
        return int(value) if isinstance(value, int) and value >= 0 else (1 << 64) - 1

    def _write(self, counter: int) -> None:
        if self.path is None:
            return
        tmp = self.path.with_suffix(".tmp")
        with open(tmp, "w") as f:
            f.write(json.dumps({"last_counter": counter}))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.path)

    def close(self) -> None:
        self.listening.close()
