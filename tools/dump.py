"""``dh2rt dump CAPTURE``: a robot's traffic, one line per frame, like candump but in DH2
terms (link and side, kind, the hormone as text with its path; segments reassembled; frames
that do not decode, or that a serial link lost, marked ``!!`` with the reason).

Reads pcapng (CAN and serial link frames, as ``dh2rt --capture`` writes it), pcap (link type
227) and every log format python-can reads (``.log``, ``.asc``, ``.blf``, ``.csv``,
``.trc``), streaming. The programs the capture carries give the hormones their names;
``--program`` names one for a capture that carries none. Filters: ``--link``, ``--kind``,
``--hormone``; ``--json`` prints one JSON object per frame.

Exit codes: 0 ok, 2 bad input (a capture or program that cannot be read: the message names
the file and the offset or position; a ``--hormone`` the program does not have), 130
interrupted.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from dh2rt.cmdline import EXIT_OK, EXIT_USAGE, err
from dh2rt.errors import CaptureError, OptionError
from tools.capture_reader import read_records
from tools.decode import KINDS, Decoder
from tools.reading import PROGRAM_HELP, interruptible, options_and_capture


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dh2rt dump",
        description="Show a capture of a robot's traffic in DH2 terms, one line per frame.",
        epilog="Example: dh2rt dump robot.pcapng --kind hormone --link 3",
    )
    p.add_argument("capture", type=Path, help="a pcapng or pcap, or a python-can log (.log .asc .blf ...)")
    p.add_argument("--program", type=Path, help=PROGRAM_HELP)
    p.add_argument("--link", type=int, action="append", help="only this link id (repeatable)")
    p.add_argument("--kind", choices=(*KINDS, "segment", "error"), action="append", help="only this kind (repeatable)")
    p.add_argument("--hormone", action="append", help="only hormones of this name, or this content X(A) (repeatable)")
    p.add_argument("--json", action="store_true", help="one JSON object per frame")
    return p


@interruptible
def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    started = options_and_capture(parser, argv)
    if isinstance(started, int):
        return started
    ns, capture = started
    try:
        wanted = {capture.hormone(text, "--hormone") for text in ns.hormone or ()}
    except OptionError as exc:
        err(str(exc))
        return EXIT_USAGE
    profile = capture.program.profile
    out = sys.stdout
    seen = 0
    try:
        if ns.json or ns.link or ns.kind or ns.hormone:
            for hop in capture.hops():
                seen += 1
                if ns.link and hop.link not in ns.link:
                    continue
                if ns.kind and hop.kind not in ns.kind:
                    continue
                if wanted and (hop.hormone is None or wanted.isdisjoint((hop.hormone.name, hop.hormone.content()))):
                    continue
                out.write((json.dumps(hop.to_json()) if ns.json else hop.describe(profile)) + "\n")
        else:  # every frame, as text: the decoder's lines (Hop.describe's, made faster)
            for line in Decoder(capture.programs).lines(read_records(capture.path)):
                seen += 1
                out.write(line + "\n")
    except CaptureError as exc:
        out.flush()
        err(str(exc))
        return EXIT_USAGE
    except BrokenPipeError:  # `dh2rt dump ... | head`: the reader has what it wanted
        return EXIT_OK
    if not seen:
        err(f"{ns.capture}: no frames in it")
    return EXIT_OK
