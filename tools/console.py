"""``dh2rt console --port DEV --key KEY --program P`` (or ``-i I -c C --contact DEV``): talk to
a running robot through the cable ``dh2rt flash`` uses: inject a hormone, read a module's
state, pause and resume every module, draw the robot as its modules report it.

Commands (at the interactive prompt, with history and completion, or one a line from
``--script FILE``, ``-`` for standard input)::

    inject HORMONE[(ARGS)] [at PATH]   the operator's signal, at the cable's module or at PATH
    state PATH                         a module's type, LocalTimer, ConnectorStatus, sensors,
                                       variables and receptor statuses
    pause / resume                     every module holds its joints and timers / goes on
    topology                           every module the robot reports, as a tree
    watch [HORMONE] [for SECONDS]      the hormones the cable's module receives, live
    help [COMMAND], quit

A PATH names a module by the hops from the cable's module, ``sent>received`` each, by
connector name or number (``back>front back>front``: the third module of a snake whose head
holds the cable); ``.`` is the cable's module itself. The commands are signed with ``--key``
(the robot's private key: ``dh2rt keys new``) and numbered; a module refuses what is not
signed by a key it trusts or numbered above the last it accepted, and says why (docs/console.md).

Exit codes: 0 every command was carried out; 1 a module refused one or did not answer; 2 bad
input (an option, a key, a program, a script line: named); 130 interrupted.
"""

from __future__ import annotations

import argparse
import cmd
import contextlib
import math
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TextIO

from dh2rt.cmdline import EXIT_FAIL, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, err, load_program
from dh2rt.errors import ConsoleInputError, DH2Error, TransportError
from dh2rt.hormone import Hormone
from dh2rt.profile import CONRO, Profile
from dh2rt.program import ABSENT, ACTIVE, CompiledProgram
from dh2rt.runtime import ms_to_s
from dh2rt.signed_image import read_private_key
from dh2rt.transport.base import Transport
from dh2rt.wire import operator as op
from dh2rt.wire.frame import FrameCodec, program_digest
from tools.console_link import ConsoleLink, Outcome
from tools.flash import add_cable_arguments, check_cable_options, open_bus_cable, open_cable

EXIT_CODES = """\
exit codes:
  0    every command was carried out
  1    a module refused a command, or did not answer one
  2    bad input: an option, a key or program file, a script line (named)
  130  interrupted (Ctrl-C)
"""

#: Cycles to wait for a refusal of a command nobody answers when carried out, and for a
#: STATE's reply (it crosses the robot and back: a few cycles a hop on a loaded machine).
QUIET_CYCLES = 10
STATE_CYCLES_PER_HOP = 6
COMMANDS = ("inject", "state", "pause", "resume", "topology", "watch", "help", "quit")
#: How long ``watch`` watches when not told (seconds).
WATCH_S = 10.0


def parse_path(text: str, profile: Profile = CONRO) -> op.Path:
    """``back>front 2>1`` (names or numbers), ``.`` for the cable's module."""
    text = text.strip()
    if text in ("", ".", "(entry)"):
        return ()
    hops = []
    for word in re.split(r"[\s,]+", text):
        sent, sep, received = word.partition(">")
        if not sep:
            raise ConsoleInputError(f"path {text!r}: hop {word!r} is not SENT>RECEIVED (e.g. back>front)")
        hops.append((_connector(sent, profile, text), _connector(received, profile, text)))
    return tuple(hops)


def _connector(word: str, profile: Profile, text: str) -> int:
    if word.isdigit() and 1 <= int(word) <= profile.connector_count:
        return int(word)
    if word in profile.connectors:
        return profile.connector_index(word)
    names = ", ".join(profile.connectors)
    raise ConsoleInputError(f"path {text!r}: no connector {word!r} (one of {names}, or 1..{profile.connector_count})")


def describe_path(path: op.Path, profile: Profile = CONRO) -> str:
    return " ".join(f"{profile.connector_name(s)}>{profile.connector_name(r)}" for s, r in path) or "."


def parse_hormone(text: str, program: CompiledProgram) -> Hormone:
    """``LTS`` or ``X(A, 3)``: a hormone the program declares, its arguments checked."""
    m = re.fullmatch(r"\s*([A-Za-z_][A-Za-z0-9_]*)\s*(?:\((.*)\))?\s*", text)
    if m is None:
        raise ConsoleInputError(f"hormone {text!r}: expected NAME or NAME(ARG, ...)")
    name, raw = m.group(1), m.group(2)
    spec = program.vocabulary.by_name.get(name)
    if spec is None:
        known = ", ".join(sorted(program.vocabulary.by_name)) or "none"
        raise ConsoleInputError(f"hormone {name!r}: program {program.name} declares no such hormone (it has: {known})")
    words = [w.strip() for w in raw.split(",")] if raw and raw.strip() else []
    args: list[str | int] = [int(w) if re.fullmatch(r"-?\d+", w) else w for w in words]
    hormone = Hormone(name, tuple(args))
    try:
        program.vocabulary.check(hormone)
    except DH2Error as exc:
        raise ConsoleInputError(str(exc)) from None
    return hormone


@dataclass
class Session:
    """What the commands act on and where they write."""

    link: ConsoleLink
    program: CompiledProgram
    period: float
    out: TextIO
    #: commands refused or unanswered so far
    failures: int = 0

    @property
    def digest(self) -> bytes:
        return program_digest(self.program.image)

    def say(self, line: str) -> None:
        print(line, file=self.out, flush=True)

    # -- the commands ------------------------------------------------------------------------

    def inject(self, arg: str) -> None:
        text, sep, where = arg.partition(" at ")
        if not text.strip():
            raise ConsoleInputError("inject: which hormone? (inject HORMONE [at PATH])")
        hormone = parse_hormone(text, self.program)
        route = parse_path(where) if sep else ()
        content = self.program.vocabulary.encode_content(hormone)
        outcome = self.link.command(op.Inject(self.digest, content, route), self._quiet(route))
        shown = hormone.content() if hormone.args else hormone.name
        self._report(outcome, f"injected {shown} at {describe_path(route)}")

    def state(self, arg: str) -> op.StateReply | None:
        route = parse_path(arg)
        outcome = self.link.command(op.StateRequest(route), self._wait(route))
        reply = outcome.reply
        if reply is None:
            self._report(outcome, "")
            return None
        self.say(describe_status(reply, self.program))
        return reply

    def pause(self) -> None:
        self._report(self.link.command(op.Pause(), self._quiet(())), "paused (flooded to every module)")

    def resume(self) -> None:
        self._report(self.link.command(op.Resume(), self._quiet(())), "resumed (flooded to every module)")

    def watch(self, arg: str) -> None:
        """Every hormone the cable's module receives (or only ``HORMONE``), one line each as it
        comes, for ``for SECONDS`` (default WATCH_S)."""
        m = re.fullmatch(r"\s*(?:(?!for\b)([A-Za-z_]\w*))?\s*(?:for\s+(\S+))?\s*", arg)
        if m is None:
            raise ConsoleInputError(f"watch {arg.strip()!r}: expected watch [HORMONE] [for SECONDS]")
        name, rest = m.group(1) or "", m.group(2)
        try:
            seconds = float(rest) if rest is not None else WATCH_S
        except ValueError:
            raise ConsoleInputError(f"watch: 'for {rest}': expected a number of seconds") from None
        if not 0 < seconds <= 3600:
            raise ConsoleInputError(f"watch: for {seconds:g} s: expected more than 0 and at most 3600 s")
        index = None
        if name.strip():
            spec = self.program.vocabulary.by_name.get(name.strip())
            if spec is None:
                known = ", ".join(sorted(self.program.vocabulary.by_name))
                raise ConsoleInputError(f"watch: program {self.program.name} declares no hormone {name.strip()!r} "
                                        f"(it has: {known})")  # fmt: skip
            index = spec.index
        cycles = min(0xFFFF, math.ceil(seconds / self.period))
        codec = FrameCodec(self.program.vocabulary, self.program.profile.connector_count)
        seen = [0]

        def show(answer: op.Answer | op.Watched) -> None:
            if isinstance(answer, op.Watched):
                seen[0] += 1
                self.say(describe_watched(answer, codec, self.program.profile))

        outcome = self.link.command(op.Watch(cycles, index), seconds + self.period * QUIET_CYCLES, show)
        self._report(outcome, f"watched {seconds:g} s: {seen[0]} hormone(s)")

    def topology(self) -> None:
        """Ask every module its status, from the cable's outwards along ConnectorStatus."""
        lines: list[str] = []
        todo: list[tuple[op.Path, int]] = [((), 0)]
        seen = 0
        while todo and seen < 64:
            route, came_in = todo.pop()
            outcome = self.link.command(op.StateRequest(route), self._wait(route))
            reply = outcome.reply
            depth = "  " * len(route)
            where = describe_path(route[-1:]) if route else "(cable)"
            if reply is None:
                why = outcome.refused.reason.name if outcome.refused else "no answer"
                lines.append(f"{depth}{where}: {why}")
                self.failures += 1
                continue
            seen += 1
            s = reply.status
            lines.append(f"{depth}{where}: {_type_name(s, self.program)}")
            for c, remote in reversed(list(enumerate(s.connectors, 1))):
                if remote and c != came_in:
                    todo.append(((*route, (c, remote)), remote))
        for line in lines:
            self.say(line)

    # -- reading answers --------------------------------------------------------------------

    def _wait(self, route: op.Path) -> float:
        return self.period * STATE_CYCLES_PER_HOP * (2 * len(route) + 2) + 0.2

    def _quiet(self, route: op.Path) -> float:
        return self.period * QUIET_CYCLES * (len(route) + 1) + 0.1

    def _report(self, outcome: Outcome, done: str) -> None:
        refused = outcome.refused
        if refused is not None:
            self.failures += 1
            self.say(f"refused by the module at {describe_path(refused.path)}: {refused.reason.name}")
        elif outcome.reply is None and not done:
            self.failures += 1
            self.say("no answer (is the cable in, the module running, the path right?)")
        elif done:
            self.say(done)


def describe_watched(w: op.Watched, codec: FrameCodec, profile: Profile) -> str:
    """A watched hormone in one line, as dump writes a hop: cycle, where it came in, kind,
    content, the connector it was sent through, its path."""
    at = profile.connector_name(w.at) if w.at else "(injected)"
    try:
        sender, frame = codec.decode(w.frame)
    except DH2Error as exc:
        return f"cycle {w.cycle:>6}  at {at:<6} error     !! {exc}"
    if not isinstance(frame, Hormone):
        return f"cycle {w.cycle:>6}  at {at:<6} {type(frame).__name__.lower()}"
    kind = "routed" if frame.route is not None else "hormone"
    line = f"cycle {w.cycle:>6}  at {at:<6} {kind:<9} {frame.content()} via {profile.connector_name(sender)}"
    if frame.path:
        line += "  path " + describe_path(frame.path, profile)
    return line


def _type_name(s: op.ModuleStatus, program: CompiledProgram) -> str:
    types = program.profile.types
    if s.type_index >= len(types):
        return f"type {s.type_index}"
    t = types[s.type_index]
    return t.name + (f" (T{t.alias})" if t.alias is not None else "")


def describe_status(reply: op.StateReply, program: CompiledProgram) -> str:
    """A STATE_REPLY in the program's names (indexes when it runs another program)."""
    s = reply.status
    profile = program.profile
    same = s.digest == program_digest(program.image)
    cname = profile.connector_name
    status = " ".join(f"{cname(c)}={cname(r) if r else 0}" for c, r in enumerate(s.connectors, 1))
    lines = [
        f"module {describe_path(reply.path)}: {_type_name(s, program)}, LocalTimer {s.timer}, cycle {s.cycle}"
        + (", PAUSED" if s.paused else ""),
        f"  ConnectorStatus {status}",
    ]
    if not same:
        lines.append(f"  (runs program {s.digest.hex()}, not {program.name}: values by index)")
    for label, names, values in (
        ("sensors", program.sensor_names, s.sensors),
        ("variables", program.var_names, s.variables),
    ):
        if values:
            lines.append(f"  {label} " + " ".join(_named(names, values, same)))
    receptors = tuple(r.name for r in program.receptors)
    words = {ACTIVE: "active", ABSENT: "absent"}
    shown = [words.get(v, "passive") for v in s.receptors]
    if shown:
        lines.append("  receptors " + " ".join(_named(receptors, tuple(range(len(shown))), same, shown)))
    return "\n".join(lines)


def _named(
    names: Sequence[str], values: Sequence[int], same: bool, shown: Sequence[str] | None = None
) -> Iterable[str]:
    for i, v in enumerate(values):
        label = names[i] if same and i < len(names) else f"#{i}"
        yield f"{label}={shown[i] if shown is not None else v}"


# ----------------------------------------------------------------------------- the prompt


class Prompt(cmd.Cmd):
    """The interactive prompt (and the script reader: the same commands)."""

    prompt = "dh2rt> "
    intro = "dh2rt console: inject, state, pause, resume, topology, watch; help; quit (or Ctrl-D)"

    def __init__(self, session: Session, stdin: IO[str] | None = None) -> None:
        super().__init__(stdin=stdin, stdout=session.out)
        self.session = session
        #: bad input met (a script exits 2 on it)
        self.bad_input: str | None = None

    def emptyline(self) -> bool:
        return False

    def default(self, line: str) -> None:
        self._bad(f"unknown command {line.split()[0]!r} (commands: {', '.join(COMMANDS)})")

    def _bad(self, message: str) -> None:
        self.bad_input = message
        self.session.say(f"error: {message}")

    def _run(self, action: Callable[[], object]) -> bool:
        try:
            action()
        except (ValueError, OSError) as exc:  # ConsoleInputError; a route the wire cannot carry; the cable gone
            self._bad(str(exc))
        return False

    def do_inject(self, arg: str) -> bool:
        """inject HORMONE[(ARGS)] [at PATH]: the operator's signal, at the cable's module or at PATH"""
        return self._run(lambda: self.session.inject(arg))

    def do_state(self, arg: str) -> bool:
        """state PATH: a module's status (PATH: hops from the cable's module, '.' for it)"""
        return self._run(lambda: self.session.state(arg))

    def do_pause(self, arg: str) -> bool:
        """pause: every module holds its joints and its timers"""
        return self._run(self.session.pause)

    def do_resume(self, arg: str) -> bool:
        """resume: every module goes on where it paused"""
        return self._run(self.session.resume)

    def do_watch(self, arg: str) -> bool:
        """watch [HORMONE] [for SECONDS]: the hormones the cable's module receives, live (10 s)"""
        return self._run(lambda: self.session.watch(arg))

    def complete_watch(self, text: str, line: str, begidx: int, endidx: int) -> list[str]:
        return sorted(n for n in self.session.program.vocabulary.by_name if n.startswith(text))

    def do_topology(self, arg: str) -> bool:
        """topology: every module the robot reports, as a tree from the cable"""
        return self._run(self.session.topology)

    def do_quit(self, arg: str) -> bool:
        """quit: leave the console (Ctrl-D too)"""
        return True

    def do_EOF(self, arg: str) -> bool:  # noqa: N802 (cmd's name for end of input)
        """Ctrl-D: leave the console"""
        if self.use_rawinput:
            self.session.say("")
        return True

    def complete_inject(self, text: str, line: str, begidx: int, endidx: int) -> list[str]:
        words = line[:begidx].split()
        if len(words) == 1:
            return sorted(n for n in self.session.program.vocabulary.by_name if n.startswith(text))
        if len(words) == 2:
            return ["at"] if "at".startswith(text) else []
        return _complete_hop(text, self.session.program.profile)

    def complete_state(self, text: str, line: str, begidx: int, endidx: int) -> list[str]:
        return _complete_hop(text, self.session.program.profile)


def _complete_hop(text: str, profile: Profile) -> list[str]:
    sent, sep, received = text.partition(">")
    if not sep:
        return [f"{c}>" for c in profile.connectors if c.startswith(sent)]
    return [f"{sent}>{c}" for c in profile.connectors if c.startswith(received)]


# ----------------------------------------------------------------------------- the command


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dh2rt console",
        description="Talk to a running robot through a cable into one module's free connector: inject a\n"
        "hormone, read a module's state, pause and resume every module, draw the robot.",
        epilog=EXIT_CODES
        + "\nexamples:\n  dh2rt console --port /dev/ttyUSB0 --key robot.key --program legs_to_snake.dh2\n"
        "  echo 'inject LTS' | dh2rt console --port /dev/ttyUSB0 --key robot.key --program l2s.dh2 --script -\n",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--key", type=Path, required=True, help="the robot's private key (dh2rt keys new): signs commands")
    p.add_argument("--program", type=Path, required=True, help="the program the robot runs (.dh2): names hormones")
    add_cable_arguments(p)
    p.add_argument("--script", metavar="FILE", help="run the commands in FILE (one a line; '-': standard input)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    if threading.current_thread() is threading.main_thread():  # Ctrl-C is ours from here: exit 130
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        ns = build_parser().parse_args(argv)
    except SystemExit as exc:
        return int(exc.code) if isinstance(exc.code, int) else EXIT_USAGE
    try:
        return _main(ns)
    except KeyboardInterrupt:
        err("interrupted")
        return EXIT_INTERRUPTED


def _main(ns: argparse.Namespace) -> int:
    try:
        ns.timeout, ns.confirm = 1.0, False  # what the flash command's option check reads
        check_cable_options(ns)
        key = read_private_key(ns.key)
        program = load_program(ns.program)
        script = _open_script(ns.script)
    except (ValueError, OSError) as exc:  # KeyFileError, DH2Error (compile) are ValueErrors
        err(_describe_error(exc))
        return EXIT_USAGE
    bus = None
    try:
        if ns.port is not None:
            transport: Transport = open_cable(ns.port, ns.baudrate)
            connector = 1
        else:
            transport, bus = open_bus_cable(ns)
            connector = CONRO.connectors.index(ns.cable_connector) + 1
    except (TransportError, OSError) as exc:
        err(str(exc))
        if script is not None and script is not sys.stdin:
            script.close()
        return EXIT_USAGE
    period = ms_to_s(ns.cycle_ms)
    link = ConsoleLink(transport, key, connector=connector, period=period, on_step=None if bus is None else bus.step)
    try:
        link.start()
        if bus is not None:
            time.sleep(period * 10)  # the cable's link negotiated before the first command
        session = Session(link, program, period, sys.stdout)
        prompt = Prompt(session, stdin=script)
        if script is not None:
            prompt.use_rawinput = False
            prompt.prompt = ""
            return _run_script(prompt, script)
        _interactive(prompt)
        return EXIT_FAIL if session.failures else EXIT_OK
    finally:
        link.close()
        if bus is not None:
            bus.close()
        transport.close()
        if script is not None and script is not sys.stdin:
            script.close()


def _describe_error(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.filename is not None:
        return f"{exc.filename}: {exc.strerror or exc}"
    return str(exc)


def _open_script(name: str | None) -> IO[str] | None:
    if name is None:
        return None
    if name == "-":
        return sys.stdin
    return open(name)


def _run_script(prompt: Prompt, script: IO[str]) -> int:
    for number, line in enumerate(script, 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        prompt.session.say(f"{Prompt.prompt}{line}")
        if prompt.onecmd(line):
            break
        if prompt.bad_input is not None:
            name = getattr(script, "name", "-")
            err(f"{name}:{number}: {prompt.bad_input}")
            return EXIT_USAGE
    return EXIT_FAIL if prompt.session.failures else EXIT_OK


def _interactive(prompt: Prompt) -> None:
    """The prompt with readline's history (kept in ~/.dh2rt_console_history) and completion;
    Ctrl-D (or quit) leaves, Ctrl-C interrupts (exit 130)."""
    history = Path.home() / ".dh2rt_console_history"
    try:
        import readline

        readline.set_completer_delims(" \t\n")
        with contextlib.suppress(OSError):
            readline.read_history_file(history)
    except ImportError:  # no readline on this platform: a plain prompt
        readline = None  # type: ignore[assignment]
    try:
        prompt.cmdloop()
    finally:
        if readline is not None:
            with contextlib.suppress(OSError):
                readline.write_history_file(history)


if __name__ == "__main__":
    sys.exit(main())
