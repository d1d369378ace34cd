"""``dh2rt replay CAPTURE --step``: walk the rebuilt cycles forward and back at a prompt (with
history and completion), or run the same commands from a file or standard input
(``--script FILE``, ``-`` for standard input).

The whole run is rebuilt first (it is deterministic: the capture decides every cycle), so
going back is looking at an earlier cycle, not undoing one. The position is one rebuilt
cycle, in the order the cycles began; each move shows where it is and that module's state
after the cycle.

Commands::

    next [N]           N cycles forward (1)          back [N]        N cycles back
    continue           to the next breakpoint hit    reverse         to the previous hit
    break SPEC         add a breakpoint (as --break) breaks          list them
    delete N           remove breakpoint N           goto MODULE CYCLE   that module's cycle
    state MODULE       that module's state as of here (its last cycle at or before it)
    notes              what replay said up to here   where           the position again
    quit (or Ctrl-D)
"""

from __future__ import annotations

import cmd
import contextlib
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import IO, Any

from dh2rt.errors import OptionError
from tools.reading import Capture
from tools.replay_rebuild import Note, Rebuild, Step
from tools.replay_view import Breakpoint, parse_break, view, view_text

COMMANDS = ("next", "back", "continue", "reverse", "break", "breaks", "delete", "goto", "state", "notes", "where")
HISTORY = ".dh2rt_replay_history"


class Timeline:
    """Every rebuilt cycle with its view (taken right after it), and the notes."""

    def __init__(self, rebuild: Rebuild, capture: Capture) -> None:
        self.steps: list[Step] = []
        self.views: list[dict[str, Any]] = []
        for step in rebuild.steps():
            self.steps.append(step)
            self.views.append(view(step, ()))
        self.notes: list[Note] = list(rebuild.notes)
        self.modules = {s.mark.name: s.mark.module for s in self.steps}

    def index_of(self, module: int, cycle: int) -> int | None:
        return next((i for i, s in enumerate(self.steps) if (s.mark.module, s.mark.cycle) == (module, cycle)), None)


class ReplayPrompt(cmd.Cmd):
    """The prompt (and the script reader: the same commands)."""

    prompt = "replay> "
    intro = "dh2rt replay: next, back, continue, reverse, break, state, goto, notes; help; quit (or Ctrl-D)"

    def __init__(self, timeline: Timeline, capture: Capture, out: IO[str], breaks: Sequence[Breakpoint]) -> None:
        super().__init__(stdout=out)
        self.timeline = timeline
        self.capture = capture
        self.out = out
        self.breaks = list(breaks)
        self.at = -1  # before the first cycle
        #: bad input met (a script exits 2 on it)
        self.bad_input: str | None = None

    def say(self, text: str) -> None:
        self.out.write(text + "\n")

    def _bad(self, message: str) -> None:
        self.bad_input = message
        self.say(f"error: {message}")

    def emptyline(self) -> bool:
        return False

    def default(self, line: str) -> None:
        self._bad(f"unknown command {line.split()[0]!r} (commands: {', '.join(COMMANDS)})")

    def _count(self, arg: str) -> int | None:
        if not arg.strip():
            return 1
        if arg.strip().isdigit() and int(arg) > 0:
            return int(arg)
        self._bad(f"{arg.strip()!r}: a count is a whole number above 0")
        return None

    def _show(self, index: int) -> None:
        self.at = index
        if index < 0:
            self.say("before the first cycle")
            return
        shown = dict(self.timeline.views[index])
        shown["break"] = [b.text for b in self.breaks if b.hit(self.timeline.steps[index])]
        self.say(view_text(shown))

    def _move(self, to: int) -> None:
        last = len(self.timeline.steps) - 1
        if to > last:
            self.say("the end of the capture")
            to = last
        self._show(max(-1, to))

    def do_next(self, arg: str) -> bool:
        """next [N]: N cycles forward"""
        n = self._count(arg)
        if n is not None:
            self._move(self.at + n)
        return False

    def do_back(self, arg: str) -> bool:
        """back [N]: N cycles back"""
        n = self._count(arg)
        if n is not None:
            self._move(self.at - n)
        return False

    def _seek(self, indices: range) -> None:
        if not self.breaks:
            self._bad("no breakpoints (break SPEC adds one)")
            return
        for i in indices:
            if any(b.hit(self.timeline.steps[i]) for b in self.breaks):
                self._show(i)
                return
        self.say("no breakpoint hit that way")

    def do_continue(self, arg: str) -> bool:
        """continue: forward to the next breakpoint hit"""
        self._seek(range(self.at + 1, len(self.timeline.steps)))
        return False

    def do_reverse(self, arg: str) -> bool:
        """reverse: back to the previous breakpoint hit"""
        self._seek(range(self.at - 1, -1, -1))
        return False

    def do_break(self, arg: str) -> bool:
        """break SPEC: 'hormone H', 'receptor NAME fires' or 'type of MODULE changes'"""
        try:
            self.breaks.append(parse_break(arg.strip(), self.capture, self.timeline.modules))
        except OptionError as exc:
            self._bad(str(exc).replace("--break ", "break ", 1))
            return False
        self.say(f"breakpoint {len(self.breaks)}: {arg.strip()}")
        return False

    def do_breaks(self, arg: str) -> bool:
        """breaks: the breakpoints, numbered"""
        for n, b in enumerate(self.breaks, 1):
            self.say(f"{n}: {b.text}")
        if not self.breaks:
            self.say("no breakpoints")
        return False

    def do_delete(self, arg: str) -> bool:
        """delete N: remove breakpoint N"""
        n = self._count(arg) if arg.strip() else None
        if n is None or n > len(self.breaks):
            self._bad(f"delete {arg.strip()!r}: name a breakpoint by its number (breaks lists them)")
            return False
        self.say(f"deleted {n}: {self.breaks.pop(n - 1).text}")
        return False

    def _module(self, word: str) -> int | None:
        modules = self.timeline.modules
        if word in modules:
            return modules[word]
        if word.isdigit() and int(word) in modules.values():
            return int(word)
        self._bad(f"no module {word!r} in the capture (it has {', '.join(modules)})")
        return None

    def do_goto(self, arg: str) -> bool:
        """goto MODULE CYCLE: that module's cycle"""
        words = arg.split()
        if len(words) != 2 or not words[1].isdigit():
            self._bad("goto MODULE CYCLE, e.g. goto m3 40")
            return False
        module = self._module(words[0])
        if module is None:
            return False
        index = self.timeline.index_of(module, int(words[1]))
        if index is None:
            self._bad(f"{words[0]} has no cycle {words[1]} in the capture")
            return False
        self._show(index)
        return False

    def do_state(self, arg: str) -> bool:
        """state MODULE: that module's state as of here"""
        module = self._module(arg.strip())
        if module is None:
            return False
        index = next((i for i in range(self.at, -1, -1) if self.timeline.steps[i].mark.module == module), None)
        if index is None:
            self.say(f"{arg.strip()}: no cycle of it yet")
            return False
        self.say(view_text(self.timeline.views[index]))
        return False

    def do_where(self, arg: str) -> bool:
        """where: the position again"""
        self._show(self.at)
        return False

    def do_notes(self, arg: str) -> bool:
        """notes: what replay said up to here"""
        if self.at < 0:
            upto: list[Note] = []
        else:
            before = {(s.mark.module, s.mark.life, s.mark.cycle) for s in self.timeline.steps[: self.at + 1]}
            upto = [n for n in self.timeline.notes if n.module is None or (n.module, n.life, n.cycle) in before]
        for note in upto:
            self.say(f"{note.kind}: {note.line()}")
        if not upto:
            self.say("nothing yet")
        return False

    def do_quit(self, arg: str) -> bool:
        """quit: leave"""
        return True

    def do_EOF(self, arg: str) -> bool:  # noqa: N802 (cmd's name for end of input)
        self.say("")
        return True

    def complete_state(self, text: str, line: str, begidx: int, endidx: int) -> list[str]:
        return [m for m in self.timeline.modules if m.startswith(text)]

    complete_goto = complete_state

    def complete_break(self, text: str, line: str, begidx: int, endidx: int) -> list[str]:
        words = line[:begidx].split()
        if len(words) == 1:
            return [w for w in ("hormone", "receptor", "type") if w.startswith(text)]
        if words[1:] == ["hormone"]:
            return [h for h in self.capture.hormone_names() if h.startswith(text)]
        if words[1:] == ["receptor"]:
            return [r.name for r in self.capture.program.receptors if r.name.startswith(text)]
        if words[1:] == ["type"]:
            return ["of"] if "of".startswith(text) else []
        return []


def run_script(prompt: ReplayPrompt, script: IO[str], name: str) -> str | None:
    """The commands of ``script``, each echoed after the prompt; the first bad one ends it
    (returned as ``NAME:LINE: why``)."""
    for number, line in enumerate(script, 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        prompt.say(f"{prompt.prompt}{line}")
        if prompt.onecmd(line):
            break
        if prompt.bad_input is not None:
            return f"{name}:{number}: {prompt.bad_input}"
    return None


def interactive(prompt: ReplayPrompt) -> None:
    """The prompt with readline's history (``~/.dh2rt_replay_history``) and completion;
    Ctrl-D (or quit) leaves, Ctrl-C interrupts (exit 130)."""
    with _history(Path.home() / HISTORY):
        prompt.cmdloop()


@contextlib.contextmanager
def _history(path: Path) -> Iterator[None]:
    """readline's history read from ``path`` and written back, whatever ends the prompt
    (nothing on a platform without readline: a plain prompt)."""
    try:
        import readline
    except ImportError:
        yield
        return
    readline.set_completer_delims(" \t\n")
    if path.exists():
        with contextlib.suppress(OSError):
            readline.read_history_file(path)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            readline.write_history_file(path)
