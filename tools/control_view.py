"""How the control family's frames read in ``dh2rt dump``: the operator's
(:mod:`dh2rt.wire.operator`) and the docking chain's motion frames (:mod:`dh2rt.wire.motion`),
one short line a message, connectors named by the profile, an INJECT's hormone by the program
its digest names when the capture carries it."""

from __future__ import annotations

from collections.abc import Callable, Mapping

from dh2rt.errors import DecodeError
from dh2rt.hormone import Vocabulary
from dh2rt.wire import motion as mw
from dh2rt.wire import operator as op


def path_text(path: op.Path, name: Callable[[int], str]) -> str:
    return " ".join(f"{name(s)}>{name(r)}" for s, r in path) or "(cable's module)"


def control_text(message: op.Message, name: Callable[[int], str], vocabularies: Mapping[bytes, Vocabulary]) -> str:
    """A control message in one line: its type, counter and what it carries."""
    if isinstance(message, op.Signed):
        kind = op.message_type(message).name
        head = f"{kind} #{message.counter} key {message.key_id.hex()} hops {message.hops}"
        command = message.command
        if isinstance(command, op.Inject):
            return f"{head}, {_hormone(command, vocabularies)} at {path_text(command.route, name)}"
        if isinstance(command, op.StateRequest):
            return f"{head}, at {path_text(command.route, name)}"
        if isinstance(command, op.Watch):
            what = "every hormone" if command.hormone is None else f"hormone #{command.hormone}"
            return f"{head}, {what} for {command.cycles} cycles"
        return head
    if isinstance(message, op.Watched):
        at = name(message.at) if message.at else "(injected)"
        return f"WATCHED #{message.counter} cycle {message.cycle} at {at}: {message.frame.hex()}"
    where = f"#{message.counter} from {path_text(message.path, name)}, left {message.left}"
    if isinstance(message, op.Refused):
        return f"REFUSED {where}: {message.reason.name}"
    s = message.status
    status = ",".join(str(c) for c in s.connectors)
    paused = ", paused" if s.paused else ""
    return f"STATE_REPLY {where}: type {s.type_index}, LocalTimer {s.timer}, cycle {s.cycle}, status {status}{paused}"


def _hormone(command: op.Inject, vocabularies: Mapping[bytes, Vocabulary]) -> str:
    vocabulary = vocabularies.get(command.digest)
    if vocabulary is not None:
        try:
            hormone, args, end = vocabulary.decode_content(command.content)
            if end == len(command.content):
                return hormone + (f"({', '.join(map(str, args))})" if args else "")
        except DecodeError:
            pass
    return f"hormone {command.content.hex()} of program {command.digest.hex()}"


def motion_text(message: mw.MotionMessage, name: Callable[[int], str]) -> str:
    """A motion frame in one line: its type, motion and seq, where it is on its route, and
    the angles or targets in degrees."""
    kind = mw.message_type(message).name
    route = path_text(message.route, name)
    if isinstance(message, mw.Angles):
        angles = ", ".join(f"DOF{i + 1} {a:g}" for i, a in enumerate(message.angles))
        links = ",".join(map(str, message.links)) or "none"
        head = f"{kind} motion {message.motion} #{message.seq} from {route}, left {message.left}"
        return f"{head}: module {message.module}, {angles}, links {links}"
    head = f"{kind} motion {message.motion} #{message.seq} to {route}, hops {message.hops}"
    if isinstance(message, mw.Targets):
        return head + ": " + ", ".join(f"DOF{d + 1} {t:g}" for d, t in message.targets)
    if isinstance(message, mw.SetOff):
        others = ",".join(map(str, message.others)) or "none"
        body = ",".join(map(str, message.body))
        return f"{head}: to module {message.target} connector {message.connector}, body {body}, others {others}"
    return head
