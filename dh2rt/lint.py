"""Warnings about a program that compiles but will not do what it says on a real module:
joint angles outside the servos' range (the servo clips them) and native actions this
runtime does not have (it would refuse to boot the program). ``dh2rt check`` prints them
as ``FILE:LINE:COL: warning: ...``; they do not change its exit code."""

from __future__ import annotations

from collections.abc import Collection, Mapping

from dh2rt.errors import SourceSpan
from dh2rt.lang import ast
from dh2rt.profile import Profile

#: The joint range of a CONRO module's servos (degrees), as the physics model and the servo
#: driver clip it.
JOINT_RANGE_DEG = (-90.0, 90.0)


def _where(span: SourceSpan | None, source: str) -> str:
    return str(span) if span is not None else source


def constant(e: ast.Expr, consts: Mapping[str, ast.Expr], depth: int = 0) -> int | None:
    """The value of ``e`` when it depends on constants only, else None."""
    if depth > 64:
        return None
    if isinstance(e, ast.Num):
        return e.value
    if isinstance(e, ast.Name):
        target = consts.get(e.name)
        return None if target is None else constant(target, consts, depth + 1)
    if isinstance(e, ast.Neg):
        v = constant(e.operand, consts, depth + 1)
        return None if v is None else -v
    if isinstance(e, ast.BinOp):
        a, b = constant(e.left, consts, depth + 1), constant(e.right, consts, depth + 1)
        if a is None or b is None:
            return None
        if e.op == "+":
            return a + b
        if e.op == "-":
            return a - b
        if e.op == "*":
            return a * b
        if b == 0:
            return None
        q = abs(a) // abs(b) * (1 if (a >= 0) == (b >= 0) else -1)
        return q if e.op == "/" else a - b * q
    return None


def lint(program: ast.Program, profile: Profile, natives: Collection[str]) -> list[str]:
    """Warnings for ``program`` run on ``profile`` by a runtime that has ``natives``."""
    del profile  # one joint range for every CONRO module today
    consts = {c.name: c.value for c in program.consts}
    lo, hi = JOINT_RANGE_DEG
    out: list[str] = []
    for n in program.natives:
        if n.name not in natives:
            out.append(
                f"{_where(n.span, program.source)}: warning: native {n.name} is declared, but this runtime has "
                f"no such native action (it has: {', '.join(sorted(natives)) or 'none'}); modules will refuse "
                "to boot the program"
            )
    for r in program.receptors:
        for a in r.actions:
            if isinstance(a, ast.SetDOF):
                value = constant(a.value, consts)
                if value is not None and not lo <= value <= hi:
                    out.append(
                        f"{_where(a.span, program.source)}: warning: receptor {r.name} sets DOF{a.joint} to "
                        f"{value} degrees, outside the servos' range {lo:+.0f}..{hi:+.0f} (it will stop at the limit)"
                    )
    return out
