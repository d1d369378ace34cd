"""``dh2rt replay CAPTURE``: rebuild every module's engine cycle by cycle from a capture of a
loop run, and print each module's trace records as ``dh2rt run --trace`` writes them, or
stop at breakpoints.

The capture must have the modules' cycle marks beside it (:mod:`tools.capture_cycles`: the
launcher's ``--capture`` writes them, on serial links and on a bus); how each cycle is
rebuilt, and what replay says where the capture lacks something, is :mod:`tools.replay_rebuild`.

Breakpoints (``--break``, repeatable), checked after each rebuilt cycle, in the capture's
time order:

* ``hormone H``: a module took in (received or was injected) or sent ``H`` (a name, or a
  content ``X(A)``);
* ``receptor NAME fires``: a module ran the actions of receptor ``NAME``;
* ``type of MODULE changes``: ``MODULE`` (its name, ``m4``, or its index) now has another
  type than after its previous cycle.

At each, replay stops: it prints where (module, cycle, its clock) and the module's state
(type, LocalTimer, status, actuators, variables, sensors, receptor statuses, what it took in
and sent), then goes on to the next (``--first``: ends at the first). Without breakpoints it
prints the records (JSON Lines); ``--trace FILE`` writes them to a file in either case.
``--json`` prints one JSON summary instead: the stops, the notes, the counts.

``--model`` compares the rebuilt run with the in-process model of the same topology and
inputs by ``dh2rt diff``'s rule (:mod:`tools.replay_model`); ``--step`` and ``--script``
walk the cycles forward and back at a prompt (:mod:`tools.replay_prompt`).

Exit codes: 0 (whatever the notes say: a missing frame, a divergence from the capture), 1 a
divergence from the model (``--model``), 2 bad input (not a
capture, no cycle marks in it, a ``--program`` whose digest no Hello of the capture names,
a breakpoint that names no hormone, receptor or module; and, once the other modules are
rebuilt, a module that switched to a program neither the capture nor ``--flashed`` holds),
130 interrupted.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import signal
import sys
import tempfile
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import IO, Any

from dh2rt.cmdline import EXIT_FAIL, EXIT_OK, EXIT_USAGE, err
from dh2rt.errors import CaptureError, DH2Error, OptionError, ProgramError
from dh2rt.program import CompiledProgram
from dh2rt.signed_image import Verdict, is_image_file, parse, read_public_key, verify
from dh2rt.wire.frame import program_digest
from tools.capture_cycles import CycleMark, marks_path, read_marks
from tools.reading import PROGRAM_HELP, Capture, interruptible, options_and_capture, program_file
from tools.replay_images import images_on_the_wire
from tools.replay_model import ModelResult, compare_with_model
from tools.replay_prompt import ReplayPrompt, Timeline, interactive, run_script
from tools.replay_rebuild import Note, Rebuild, digest_of
from tools.replay_view import BREAK_FORMS, Breakpoint, parse_break, view, view_text


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dh2rt replay",
        description="Rebuild every module's engine cycle by cycle from a capture of a loop run: its trace "
        "records, or stops at breakpoints.",
        epilog="Example: dh2rt replay robot.pcapng --break 'receptor head_a fires' --first",
    )
    p.add_argument("capture", type=Path, help="a pcapng the launcher's --capture wrote (its cycle marks beside it)")
    p.add_argument("--program", type=Path, help=PROGRAM_HELP + "; its digest must be the one the Hellos name")
    repeatable = (
        ("--flashed", "FILE", "a program a module switched to in the run (a flash): its .dh2 source or image"),
        ("--trust", "PUBKEY", "a public key (dh2rt keys new's .pub): each --flashed image must be signed by one"),
    )
    for flag, metavar, text in repeatable:
        p.add_argument(flag, type=Path, action="append", default=[], metavar=metavar, help=text + "; repeatable")
    p.add_argument("--break", dest="breaks", action="append", default=[], metavar="SPEC", help=BREAK_FORMS)
    p.add_argument("--first", action="store_true", help="end at the first breakpoint hit")
    p.add_argument("--trace", type=Path, metavar="FILE", help="write the rebuilt trace records to FILE (JSON Lines)")
    p.add_argument("--json", action="store_true", help="one JSON summary: stops, notes, counts")
    p.add_argument(
        "--model",
        action="store_true",
        help="compare the rebuilt run with the in-process model of the same topology and inputs (diff's rule)",
    )
    p.add_argument("--step", action="store_true", help="walk the cycles forward and back at a prompt")
    p.add_argument("--script", metavar="FILE", help="the prompt's commands from FILE (- for standard input)")
    return p


def _trust_keys(trust: Sequence[Path]) -> list[bytes]:
    keys = []
    for key in trust:
        try:
            keys.append(read_public_key(key))
        except (DH2Error, OSError) as exc:
            raise OptionError(f"--trust {key}: not a public key ({exc})") from None
    return keys


def _wire_programs(
    capture: Capture, flashed: Sequence[CompiledProgram], keys: Sequence[bytes]
) -> tuple[list[CompiledProgram], list[str]]:
    """The programs of the images the capture's transfer frames carry whole
    (:mod:`tools.replay_images`), but those the capture or ``--flashed`` hold already; with
    ``--trust`` keys, only those signed by one. And what replay says of each image."""
    known = {digest_of(p) for p in (*capture.programs, *flashed)}
    programs, notes = [], []
    for image in images_on_the_wire(capture.path, capture.programs):
        if image.program is None or image.signed is None:
            notes.append(f"{image.note}: not rebuilt (give it with --flashed FILE)")
            continue
        if digest_of(image.program) in known:
            continue
        if keys:
            verdict = verify(image.signed, keys)
            if verdict is not Verdict.OK:
                notes.append(f"{image.note}; {verdict} under the --trust keys: not run")
                continue
        known.add(digest_of(image.program))
        programs.append(image.program)
        notes.append(image.note + ("" if keys else " (its signature not checked: give --trust KEY)"))
    return programs, notes


def _flashed(path: Path, keys: Sequence[bytes]) -> CompiledProgram:
    """``--flashed path``; with ``--trust`` ``keys`` its signature checked as a module checks it."""
    program = program_file(path)
    if keys:
        try:
            verdict = verify(parse(path.read_bytes()), keys) if is_image_file(path) else Verdict.UNSIGNED
        except (DH2Error, OSError) as exc:
            raise OptionError(f"--flashed {path}: {exc}") from None
        if verdict is not Verdict.OK:
            raise OptionError(f"--flashed {path}: {verdict} under the --trust keys: a module would refuse it")
    return program


def _check_flashed(rebuild: Rebuild, paths: Sequence[Path]) -> None:
    given = rebuild.flashed[len(rebuild.flashed) - len(paths) :]  # after the capture's own
    for path, program in zip(paths, given, strict=True):
        mine = digest_of(program)
        if mine not in rebuild.frames.digests:
            named = ", ".join(sorted(rebuild.frames.digests))
            raise OptionError(f"--flashed {path}: digest {mine}; the capture's Hellos name {named}: no module ran it")


def _check_digest(capture: Capture, rebuild: Rebuild, program: Path | None) -> None:
    if program is None or not rebuild.frames.digests:
        return
    mine = program_digest(capture.program.image).hex()
    if mine not in rebuild.frames.digests:
        named = ", ".join(sorted(rebuild.frames.digests))
        raise OptionError(
            f"--program {program}: digest {mine}; the capture's Hellos name {named}: not the program the robot ran"
        )


def _open(ns: argparse.Namespace, capture: Capture) -> tuple[Rebuild, list[Breakpoint]]:
    marks = list(read_marks(ns.capture))
    cycles = [m for m in marks if isinstance(m, CycleMark)]
    if not cycles:
        raise CaptureError(
            f"{ns.capture}: no cycle marks beside it ({marks_path(ns.capture).name}): it holds only the wire, and "
            "replay needs each module's cycles (which frames it took in at which cycle, its timer phase); "
            "a loop run's --capture keeps them"
        )
    rebuild = Rebuild(capture.program, marks, capture.hops(), capture.programs[1:])
    _check_digest(capture, rebuild, ns.program)
    _check_flashed(rebuild, ns.flashed)
    modules = {m.name: m.module for m in cycles}
    breaks = [parse_break(text, capture, modules) for text in ns.breaks]
    return rebuild, breaks


@interruptible
def main(argv: Sequence[str] | None = None) -> int:
    started = options_and_capture(build_parser(), argv)
    if isinstance(started, int):
        return started
    ns, capture = started
    try:
        keys = _trust_keys(ns.trust)
        flashed = tuple(_flashed(path, keys) for path in ns.flashed)
        from_wire, image_notes = _wire_programs(capture, flashed, keys)
        capture = dataclasses.replace(capture, programs=(*capture.programs, *from_wire, *flashed))
        rebuild, breaks = _open(ns, capture)
        trace_out = ns.trace.open("w", encoding="utf-8") if ns.trace is not None else None
    except (CaptureError, OptionError, ProgramError) as exc:
        err(str(exc))
        return EXIT_USAGE
    except OSError as exc:
        err(f"--trace {ns.trace}: cannot be written ({exc.strerror or exc})")
        return EXIT_USAGE
    if not ns.json:
        for line in image_notes:
            print(f"replay: image: {line}", file=sys.stderr)
    if ns.step or ns.script is not None:
        return _prompt(ns, capture, rebuild, breaks)
    records_out = sys.stdout if not breaks and not ns.json and not ns.model else None
    rebuilt: list[dict[str, Any]] = []
    stops: list[dict[str, Any]] = []
    count = 0
    try:
        for step in rebuild.steps():
            count += 1
            if ns.model:
                rebuilt.append(step.record)
            for out in (records_out, trace_out):
                if out is not None:
                    out.write(json.dumps(step.record, separators=(",", ":")) + "\n")
            hits = [b for b in breaks if b.hit(step)]
            if hits:
                stops.append(view(step, [b.text for b in hits]))
                if not ns.json:
                    print(view_text(stops[-1]))
                if ns.first:
                    break
    except CaptureError as exc:
        err(str(exc))
        return EXIT_USAGE
    finally:
        if trace_out is not None:
            trace_out.close()
    model = _model(ns, capture, rebuild, rebuilt) if ns.model else None
    _summary(ns, rebuild.notes, stops, count, len(rebuild.period), model, image_notes)
    if model is not None and model.first is not None:
        return EXIT_FAIL
    return EXIT_USAGE if rebuild.unknown else EXIT_OK  # a program the capture does not hold: incomplete


def _model(ns: argparse.Namespace, capture: Capture, rebuild: Rebuild, rebuilt: list[dict[str, Any]]) -> ModelResult:
    with tempfile.TemporaryDirectory(prefix="dh2rt-replay-") as folder:
        result = compare_with_model(
            rebuilt, capture.program, rebuild.marks, Path(folder), ns.capture, rebuild.frames.first_lost
        )
    if not ns.json:
        print("\n".join(result.lines))
        for line in result.unknown:
            print(f"the model cannot know: {line}")
    return result


def _summary(
    ns: argparse.Namespace,
    notes: Sequence[Note],
    stops: Sequence[dict[str, Any]],
    cycles: int,
    modules: int,
    model: ModelResult | None,
    images: Sequence[str] = (),
) -> None:
    if ns.json:
        doc: dict[str, Any] = {
            "capture": str(ns.capture),
            "modules": modules,
            "cycles": cycles,
            "stops": list(stops),
            "notes": [n.to_json() for n in notes],
            "images": list(images),
        }
        if model is not None:
            doc["model"] = {
                "divergence": model.first,
                "lines": model.lines,
                "unknown": model.unknown,
                "after_unknown": model.after_unknown,
            }
        print(json.dumps(doc, indent=1))
        return
    stream: IO[str] = sys.stderr
    for note in notes:
        print(f"replay: {note.kind}: {note.line()}", file=stream)
    if ns.breaks and not stops:
        print("no breakpoint was hit", file=sys.stdout)


def _prompt(ns: argparse.Namespace, capture: Capture, rebuild: Rebuild, breaks: Sequence[Breakpoint]) -> int:
    """``--step`` (the prompt) or ``--script`` (its commands from a file): see tools.replay_prompt."""
    prompt = ReplayPrompt(Timeline(rebuild, capture), capture, sys.stdout, breaks)
    if ns.script is None:
        if threading.current_thread() is threading.main_thread():  # Ctrl-C at the prompt: exit 130, said
            signal.signal(signal.SIGINT, signal.default_int_handler)
        interactive(prompt)
        return EXIT_OK
    try:
        script = sys.stdin if ns.script == "-" else open(ns.script, encoding="utf-8")  # noqa: SIM115
    except OSError as exc:
        err(f"--script {ns.script}: cannot be read ({exc.strerror or exc})")
        return EXIT_USAGE
    prompt.prompt = "replay> "
    try:
        failed = run_script(prompt, script, "-" if ns.script == "-" else ns.script)
    finally:
        if script is not sys.stdin:
            script.close()
    if failed is not None:
        err(failed)
        return EXIT_USAGE
    return EXIT_OK
