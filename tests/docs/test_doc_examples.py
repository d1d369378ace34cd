"""Every shell example in README.md and docs/*.md runs as written, with the output it shows.

Fenced blocks labelled ``sh``, ``bash``, ``shell`` or ``console`` are examples. Each doc runs
in a fresh folder of its own, its blocks in order (what one block writes, the next reads, as
for a reader), with ``.venv`` and ``examples`` there as links to the repository's, ``.venv/bin``
first on PATH and HOME inside the folder. A block's commands run in one bash, one after another.

* ``sh`` blocks: every command exits 0, or the code its comment states (``# exit 2``).
* ``console`` blocks: ``$ `` starts a command (``> `` continues it), the lines up to the next
  one are its output, stdout and stderr together, compared line by line as cram and prysk do.
  Varying parts: ``...`` within a line matches any text, a line that is only ``...`` any number
  of lines, and a line ending in `` (re)`` is a regular expression. A command exits 0 unless
  its output ends in ``[N]`` (it exits N) or the next command is ``echo $?``.

HTML comments right above a block (blank lines between are allowed) say more:

* ``<!-- no-test: REASON -->``: the block needs what this machine lacks (hardware, systemd, a
  GUI, root); the test is skipped with the reason, so ``pytest -ra`` lists every such block.
* ``<!-- needs: PROGRAM -->``: skipped, naming PROGRAM, when PROGRAM is not installed.
* ``<!-- long -->``: a long run; marked ``long`` (``make test-long``), not run by ``make test``.
* ``<!-- file: NAME -->`` above any other block: its text is written to NAME, as a reader saves it.
"""

from __future__ import annotations

import functools
import os
import re
import shutil
import signal
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
SHELL_LANGUAGES = {"sh", "bash", "shell", "console"}
#: blocks that need what no test machine has; each says why. Keep the list short.
MAX_NOT_TESTED = 12
BLOCK_TIMEOUT_S = 900
MARK = "@@dh2rt-doc-example@@"
FENCE = re.compile(r"^(\s*)```(\S*)\s*$")
DIRECTIVE = re.compile(r"^\s*<!--\s*(no-test|needs|long|file)\s*(?::\s*(.*?))?\s*-->\s*$")
EXIT_COMMENT = re.compile(r"#.*\bexit (\d+)\s*$")
EXIT_SHOWN = re.compile(r"^\[(\d+)\]$")
LAUNCHER_RUN = re.compile(r"^(\$ )?dh2rt(\s*$|\s+#|\s+--transport)", re.MULTILINE)


@dataclass(frozen=True)
class Command:
    text: str
    output: tuple[str, ...] | None  # None: not compared (sh blocks)
    exit_code: int | None  # None: any (the next command shows it)


@dataclass
class Block:
    doc: Path
    line: int  # of the opening fence, 1-based
    language: str
    body: list[str]
    directives: dict[str, str] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.doc.relative_to(REPO)}:{self.line}"

    @property
    def is_example(self) -> bool:
        return self.language in SHELL_LANGUAGES


def read_blocks(doc: Path) -> list[Block]:
    """Every fenced block of DOC with the directives right above it."""
    lines = doc.read_text(encoding="utf-8").split("\n")
    blocks: list[Block] = []
    i = 0
    while i < len(lines):
        opening = FENCE.match(lines[i])
        if not opening:
            i += 1
            continue
        indent, language = opening.groups()
        end = i + 1
        while end < len(lines) and lines[end].strip() != "```":
            end += 1
        body = [line[len(indent) :] if line.startswith(indent) else line.lstrip() for line in lines[i + 1 : end]]
        blocks.append(Block(doc, i + 1, language, body, directives_above(lines, i)))
        i = end + 1
    return blocks


def directives_above(lines: list[str], fence: int) -> dict[str, str]:
    found: dict[str, str] = {}
    j = fence - 1
    while j >= 0 and (not lines[j].strip() or DIRECTIVE.match(lines[j])):
        directive = DIRECTIVE.match(lines[j])
        if directive:
            found[directive.group(1)] = directive.group(2) or ""
        j -= 1
    return found


def commands(block: Block) -> list[Command]:
    return console_commands(block.body) if block.language == "console" else script_commands(block.body)


def script_commands(body: list[str]) -> list[Command]:
    """Lines joined where they end in a backslash; blank and comment lines dropped."""
    found: list[Command] = []
    pending: list[str] = []
    for line in body:
        if not pending and (not line.strip() or line.lstrip().startswith("#")):
            continue
        pending.append(line)
        if not line.endswith("\\"):
            text = "\n".join(pending)
            stated = EXIT_COMMENT.search(text)
            found.append(Command(text, None, int(stated.group(1)) if stated else 0))
            pending = []
    assert not pending, f"a command ends in a backslash: {pending}"
    return found


def console_commands(body: list[str]) -> list[Command]:
    parsed: list[tuple[str, list[str]]] = []
    for line in body:
        if line.startswith("$ "):
            parsed.append((line[2:], []))
        elif line.startswith("> ") and parsed and parsed[-1][0].endswith("\\") and not parsed[-1][1]:
            parsed[-1] = (parsed[-1][0] + "\n" + line[2:], [])
        else:
            assert parsed, f"output before the first command: {line!r}"
            parsed[-1][1].append(line)
    found: list[Command] = []
    for k, (text, output) in enumerate(parsed):
        shown = EXIT_SHOWN.match(output[-1]) if output else None
        followed_by_status = k + 1 < len(parsed) and parsed[k + 1][0].strip() == "echo $?"
        exit_code = int(shown.group(1)) if shown else (None if followed_by_status else 0)
        found.append(Command(text, tuple(output[:-1] if shown else output), exit_code))
    return found


def line_matches(expected: str, actual: str) -> bool:
    expected, actual = expected.rstrip(), actual.rstrip()
    if expected.endswith(" (re)"):
        return re.fullmatch(expected[: -len(" (re)")], actual) is not None
    if "..." in expected:
        return re.fullmatch(".*".join(map(re.escape, expected.split("..."))), actual, re.DOTALL) is not None
    return expected == actual


def output_matches(expected: tuple[str, ...], actual: list[str]) -> bool:
    """Line by line; a line that is only ``...`` stands for any number of lines."""

    @functools.cache
    def match(i: int, j: int) -> bool:
        if i == len(expected):
            return j == len(actual)
        if expected[i].strip() == "...":
            return match(i + 1, j) or (j < len(actual) and match(i, j + 1))
        return j < len(actual) and line_matches(expected[i], actual[j]) and match(i + 1, j + 1)

    return match(0, 0)


def run_commands(folder: Path, cmds: list[Command], timeout: float) -> list[tuple[int, list[str]]]:
    """Run CMDS in one bash in FOLDER; each one's exit code and output lines."""
    script = ["exec 2>&1"]
    for k, command in enumerate(cmds):
        script += [command.text, f'__rc=$?; echo; echo "{MARK} {k} $__rc"; (exit $__rc)']
    env = {**os.environ, "PATH": f"{folder / '.venv' / 'bin'}:{os.environ['PATH']}", "HOME": str(folder / "home")}
    env.pop("VIRTUAL_ENV", None)
    process = subprocess.Popen(
        ["bash", "-c", "\n".join(script)],
        cwd=folder,
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        out, _ = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        out, _ = process.communicate()
        pytest.fail(f"still running after {timeout:.0f} s; output so far:\n{out[-4000:]}")
    results: list[tuple[int, list[str]]] = []
    rest = out
    for k in range(len(cmds)):
        marker = re.search(rf"\n{re.escape(MARK)} {k} (\d+)\n", rest)
        assert marker, f"bash ended before command {k + 1}:\n{rest[-4000:]}"
        text = rest[: marker.start()]
        results.append((int(marker.group(1)), text.removesuffix("\n").split("\n") if text else []))
        rest = rest[marker.end() :]
    return results


class DocFolder:
    """One doc's folder, and which of its blocks have run there."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.done: set[int] = set()
        (folder / "home").mkdir()
        (folder / ".venv").symlink_to(REPO / ".venv")
        (folder / "examples").symlink_to(REPO / "examples")

    def run(self, block: Block) -> None:
        if block.line in self.done:
            return
        self.done.add(block.line)
        if not block.is_example:
            (self.folder / block.directives["file"]).write_text("\n".join(block.body) + "\n", encoding="utf-8")
            return
        cmds = commands(block)
        for command, (code, output) in zip(cmds, run_commands(self.folder, cmds, BLOCK_TIMEOUT_S), strict=True):
            shown = "\n".join(output[-60:])
            assert command.exit_code is None or code == command.exit_code, (
                f"{block.name}: `{command.text}` exited {code}, the doc says {command.exit_code}:\n{shown}"
            )
            if command.output is not None:
                assert output_matches(command.output, output), (
                    f"{block.name}: `{command.text}` printed\n{shown}\nthe doc shows\n" + "\n".join(command.output)
                )


def steps(doc: Path) -> list[Block]:
    """DOC's examples and the files it has a reader save, in order."""
    return [b for b in read_blocks(doc) if b.is_example or "file" in b.directives]


def runs_by_default(block: Block) -> bool:
    """Whether running a later block first runs this one (never a skipped or long one)."""
    return not skip_reason(block) and "long" not in block.directives


def skip_reason(block: Block) -> str | None:
    if "no-test" in block.directives:
        return block.directives["no-test"]
    needed = block.directives.get("needs")
    if needed and shutil.which(needed) is None:
        return f"needs {needed}, which is not installed"
    return None


def cases() -> list[object]:
    found: list[object] = []
    for doc in DOCS:
        # a block runs the doc's earlier blocks first (in each xdist worker that takes one),
        # so it is real time once it or one of them runs modules in real time: the realtime group
        launcher_before = False
        for block in steps(doc):
            launcher_here = bool(LAUNCHER_RUN.search("\n".join(block.body)))
            if block.is_example:
                marks = [pytest.mark.long] if "long" in block.directives else []
                if launcher_here or launcher_before:
                    marks.append(pytest.mark.realtime)
                found.append(pytest.param(block, id=block.name, marks=marks))
            launcher_before |= launcher_here and runs_by_default(block)
    return found


@pytest.fixture(scope="session")
def doc_folders(tmp_path_factory: pytest.TempPathFactory) -> dict[Path, DocFolder]:
    return {doc: DocFolder(tmp_path_factory.mktemp(doc.stem)) for doc in DOCS}


@pytest.mark.parametrize("block", cases())
def test_doc_example_runs_as_written(block: Block, doc_folders: dict[Path, DocFolder]) -> None:
    reason = skip_reason(block)
    if reason:
        pytest.skip(f"{block.name}: {reason}")
    folder = doc_folders[block.doc]
    for earlier in steps(block.doc):
        if earlier.line >= block.line:
            break
        if runs_by_default(earlier):
            folder.run(earlier)
    folder.run(block)


def test_few_examples_are_not_run_and_each_says_why() -> None:
    not_run = [b for doc in DOCS for b in steps(doc) if "no-test" in b.directives]
    assert all(b.directives["no-test"].strip() for b in not_run), [b.name for b in not_run]
    assert len(not_run) <= MAX_NOT_TESTED, [b.name for b in not_run]


def test_every_shell_example_is_labelled() -> None:
    """A block of commands without a language would escape this test: there is none."""
    unlabelled = [
        b.name
        for doc in DOCS
        for b in read_blocks(doc)
        if not b.language and b.body and re.match(r"(\$ )?(dh2rt|make|sudo|tshark)\b", b.body[0])
    ]
    assert not unlabelled


def test_console_output_matching() -> None:
    assert output_matches(("a ... c", "...", "z"), ["a b c", "x", "y", "z"])
    assert output_matches((r"key id [0-9a-f]{16} (re)",), ["key id 5bcadc3042035389"])
    assert not output_matches(("a", "b"), ["a"])
    assert console_commands(["$ false", "[1]", "$ true"]) == [Command("false", (), 1), Command("true", (), 0)]
