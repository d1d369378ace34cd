"""Receptor matching: dh2rt's indexed closures against the paper's regular expressions and CLIPS.

The paper (Sec. 6) turned a module's state into a string ("<factor><value>, ...") and matched
every receptor's pattern, a regular expression such as ``(.*,((T2|T19)|t0),.*){2}``, against
it. The baseline here does exactly that, with each conjunct a lookahead so a pattern means
what the DH2 pattern means: the state string is built once per state, then every active
receptor's compiled regex is tried. CLIPS (clipspy) is a rules-engine peer: facts for the
state, one rule per receptor, the agenda read after asserting.

The states are every (module, cycle) state of a real run, and the benchmark first checks that
all three methods pick the same receptors in every state.

    python -m benchmarks.bench_matching [--quick]
"""

from __future__ import annotations

import argparse
import json
import re
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from dh2rt.compiler import compile_file
from dh2rt.engine import Engine
from dh2rt.lang import ast
from dh2rt.profile import Profile
from dh2rt.program import ACTIVE, CompiledProgram, Entry
from dh2rt.robot import Robot
from dh2rt.topology import parse_spec

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
State = tuple[int, int, dict[str, list[Entry]]]


# ---------------------------------------------------------------- the paper's method


def _type_tokens(profile: Profile, names: Sequence[str]) -> list[str]:
    out = []
    for n in names:
        t = profile.type_by_name(n)
        assert t is not None
        out.append(f"T{t.alias}" if t.alias is not None else f"T{t.name}")
    return out


def to_regex(p: ast.Pattern, profile: Profile, consts: dict[str, int]) -> str:
    """A DH2 pattern as a regex over the paper's state string (lookahead per conjunct)."""
    if isinstance(p, ast.And):
        return to_regex(p.left, profile, consts) + to_regex(p.right, profile, consts)
    if isinstance(p, ast.Or):
        return f"(?:{to_regex(p.left, profile, consts)}|{to_regex(p.right, profile, consts)})"
    if isinstance(p, ast.Not):
        return f"(?!{to_regex(p.operand, profile, consts)})"
    if isinstance(p, ast.TypeIs):
        alt = "|".join(_type_tokens(profile, p.types))
        return f"(?{'!' if p.negate else '='}.*,({alt}),)"
    if isinstance(p, ast.TimerIs) and p.op == "==":
        return f"(?=.*,t{_fold(p.value, consts)},)"
    if isinstance(p, ast.HormoneIs):
        tokens = (_arg_token(a, consts) for a in p.args)
        args = "".join(r"\." + ("[^,.]+" if t is None else re.escape(str(t))) for t in tokens)
        return f"(?{'!' if p.negate else '='}.*,H{p.name}{args},)"
    if isinstance(p, ast.TruePattern):
        return ""
    raise NotImplementedError(f"no regex for {type(p).__name__}")


def _arg_token(a: ast.ArgPattern, consts: dict[str, int]) -> str | int | None:
    """A hormone pattern's argument as the state holds it: an atom's name, a constant
    expression's value, or None for any value (``_``, ``?name``)."""
    if isinstance(a, ast.Wildcard | ast.Bind):
        return None
    if isinstance(a, ast.Name) and a.name not in consts:
        return a.name
    return _fold(a, consts)


def _program_consts(program: CompiledProgram) -> dict[str, int]:
    consts = {"ClockCycle": program.clock_cycle}
    consts.update({c.name: _fold(c.value, consts) for c in program.ast.consts})
    return consts


def _fold(e: ast.Expr, consts: dict[str, int]) -> int:
    if isinstance(e, ast.Num):
        return e.value
    if isinstance(e, ast.Name):
        return consts[e.name]
    if isinstance(e, ast.Neg):
        return -_fold(e.operand, consts)
    if isinstance(e, ast.BinOp):
        a, b = _fold(e.left, consts), _fold(e.right, consts)
        return {"+": a + b, "-": a - b, "*": a * b, "/": a // b, "%": a % b}[e.op]
    raise NotImplementedError(type(e).__name__)


class PaperMatcher:
    """The paper's method: one state string, one regex per active receptor."""

    def __init__(self, program: CompiledProgram) -> None:
        consts = _program_consts(program)
        self.patterns = [re.compile("^" + to_regex(r.pattern, program.profile, consts)) for r in program.ast.receptors]
        self.type_token = [f"T{t.alias}" if t.alias is not None else f"T{t.name}" for t in program.profile.types]

    def state_string(self, type_index: int, timer: int, present: dict[str, list[Entry]]) -> str:
        parts = ["", self.type_token[type_index], f"t{timer}"]
        for entries in present.values():
            for e in entries:
                parts.append("H" + ".".join((e[0], *map(str, e[1]))))
        parts.append("")
        return ",".join(parts)

    def matching(self, type_index: int, timer: int, present: dict[str, list[Entry]], rstatus: list[int]) -> list[int]:
        s = self.state_string(type_index, timer, present)
        return [i for i, rx in enumerate(self.patterns) if rstatus[i] == ACTIVE and rx.match(s)]


# ---------------------------------------------------------------- CLIPS


class ClipsMatcher:
    """One CLIPS rule per receptor; a state is asserted as facts and the agenda read."""

    def __init__(self, program: CompiledProgram) -> None:
        import clips

        self.clips = clips
        self.env = clips.Environment()
        self.env.build("(deftemplate state (slot type) (slot timer))")
        self.env.build("(deftemplate hormone (slot name) (multislot args))")
        consts = _program_consts(program)
        self.names = [r.name for r in program.ast.receptors]
        for r in program.ast.receptors:
            self.env.build(f"(defrule {r.name} {self._lhs(r.pattern, program.profile, consts)} => )")
        self.state = self.env.find_template("state")
        self.hormone = self.env.find_template("hormone")
        self.type_token = [
            clips.Symbol(f"T{t.alias}" if t.alias is not None else f"T{t.name}") for t in program.profile.types
        ]
        self.index = {n: i for i, n in enumerate(self.names)}

    def _lhs(self, p: ast.Pattern, profile: Profile, consts: dict[str, int]) -> str:
        if isinstance(p, ast.And):
            return self._lhs(p.left, profile, consts) + " " + self._lhs(p.right, profile, consts)
        if isinstance(p, ast.TypeIs):
            alt = "|".join(_type_tokens(profile, p.types))
            return f"(state (type {'~' if p.negate else ''}{alt}))"
        if isinstance(p, ast.TimerIs):
            return f"(state (timer {_fold(p.value, consts)}))"
        if isinstance(p, ast.HormoneIs) and not p.negate:
            args = " ".join("?" if t is None else str(t) for t in (_arg_token(a, consts) for a in p.args))
            return f"(hormone (name {p.name}) (args {args}))"
        raise NotImplementedError(f"no CLIPS rule for {type(p).__name__}")

    def matching(self, type_index: int, timer: int, present: dict[str, list[Entry]], rstatus: list[int]) -> list[int]:
        env, sym = self.env, self.clips.Symbol
        env.reset()
        self.state.assert_fact(type=self.type_token[type_index], timer=timer)
        for entries in present.values():
            for e in entries:
                self.hormone.assert_fact(name=sym(e[0]), args=[sym(a) if isinstance(a, str) else a for a in e[1]])
        return sorted(self.index[a.name] for a in env.activations() if rstatus[self.index[a.name]] == ACTIVE)


# ---------------------------------------------------------------- dh2rt


def dh2rt_matching(engine: Engine) -> Callable[[int, int, dict[str, list[Entry]]], list[int]]:
    matching = engine.matching_receptors

    def match(type_index: int, timer: int, present: dict[str, list[Entry]]) -> list[int]:
        engine.type_index = type_index
        engine.timer = timer
        engine.present = present
        return matching()

    return match


def collect_states(program: CompiledProgram, topology: str, cycles: int) -> list[State]:
    """Every module's state at the start of every cycle of a real run."""
    robot = Robot(program, parse_spec(topology), seed=1)
    states: list[State] = []
    for _ in range(cycles):
        for m, e in enumerate(robot.engines):
            assert e is not None
            present: dict[str, list[Entry]] = {}
            for at, remote, h in robot.inbox.get(m, []):
                present.setdefault(h.name, []).append((h.name, h.args, ((remote, at), *h.path), h.route, at))
            status = list(e.status)
            for at, remote, _h in robot.inbox.get(m, []):
                status[at - 1] = remote
            states.append((program.profile.type_of_status[tuple(status)], e.timer, present))
        robot.step()
    return states


def time_it(fn: Callable[[], Any], repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench_program(name: str, topology: str, cycles: int, repeat: int, with_clips: bool) -> dict[str, Any]:
    program = compile_file(str(EXAMPLES / f"{name}.dh2"))
    states = collect_states(program, topology, cycles)
    engine = Engine(program)
    ours = dh2rt_matching(engine)
    paper = PaperMatcher(program)
    rstatus = engine.rstatus
    clips_m = ClipsMatcher(program) if with_clips else None
    # the three methods agree on every state before anything is timed
    for t, timer, present in states:
        expected = paper.matching(t, timer, present, rstatus)
        assert ours(t, timer, present) == expected, (t, timer, present)
        if clips_m is not None:
            assert clips_m.matching(t, timer, present, rstatus) == expected
    with_hormones = sum(1 for s in states if s[2])

    def run_ours() -> None:
        for t, timer, present in states:
            ours(t, timer, present)

    def run_paper() -> None:
        for t, timer, present in states:
            paper.matching(t, timer, present, rstatus)

    # interleaved, best of `repeat`: both methods see the same machine conditions
    t_ours = t_paper = float("inf")
    for _ in range(repeat):
        t_ours = min(t_ours, time_it(run_ours, 1))
        t_paper = min(t_paper, time_it(run_paper, 1))
    row: dict[str, Any] = {
        "program": name,
        "topology": topology,
        "receptors": len(program.receptors),
        "states": len(states),
        "states_with_hormones": with_hormones,
        "dh2rt_us_per_state": t_ours / len(states) * 1e6,
        "regex_us_per_state": t_paper / len(states) * 1e6,
        "speedup_vs_regex": t_paper / t_ours,
    }
    if clips_m is not None:
        sample = states[: max(1, len(states) // 10)]
        cm = clips_m

        def run_clips() -> None:
            for t, timer, present in sample:
                cm.matching(t, timer, present, rstatus)

        t_clips = time_it(run_clips, 1) / len(sample)
        row["clips_us_per_state"] = t_clips * 1e6
        row["speedup_vs_clips"] = t_clips / (t_ours / len(states))
    return row


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--quick", action="store_true", help="a few seconds, for smoke tests")
    parser.add_argument("--no-clips", action="store_true", help="skip the CLIPS comparison")
    args = parser.parse_args(argv)
    cycles, repeat = (80, 1) if args.quick else (400, 9)
    try:
        import clips  # noqa: F401

        with_clips = not args.no_clips
    except ImportError:
        with_clips = False
    rows = [
        bench_program("caterpillar", "snake:20", cycles, repeat, with_clips),
        bench_program("locomotion", "octopod", cycles, repeat, with_clips),
    ]
    print("Receptor matching per module state (lower is better); the same states for every method")
    for r in rows:
        line = (
            f"  {r['program']:<12} on {r['topology']:<9} {r['receptors']:>2} receptors, {r['states']:>5} states "
            f"({r['states_with_hormones']} with hormones): dh2rt {r['dh2rt_us_per_state']:.2f} us, "
            f"regex {r['regex_us_per_state']:.2f} us -> {r['speedup_vs_regex']:.1f}x"
        )
        if "clips_us_per_state" in r:
            line += f"; CLIPS {r['clips_us_per_state']:.1f} us -> {r['speedup_vs_clips']:.0f}x"
        print(line)
    result = {
        "benchmark": "matching",
        "quick": args.quick,
        "rows": rows,
        "min_speedup_vs_regex": min(r["speedup_vs_regex"] for r in rows),
        "target_speedup_vs_regex": 10.0,
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
