"""The Python front end: build DH2 programs in Python, in the spirit of the paper's
``receptor([PH, PT, PS, PV], [actions])``. It builds the same AST as the text parser::

    from dh2rt.lang.api import H, T, LocalTimer, ClockCycle, DOF1, emit, keep_alive, hormone, program, receptor

    caterpillar = program(
        "caterpillar",
        consts={"ClockCycle": 40},
        hormones=[hormone("X", phase=["A", "B", "C", "D"])],
        receptors=[
            receptor("head_a", (T == "T1") & (LocalTimer == 0),
                     [DOF1(+45), emit("X", "A", via="back"), keep_alive()]),
            receptor("body_a", (T == ["T16", "T2"]) & (H == ("X", "A")),
                     [DOF1(-45), emit("X", "B", via="back"), keep_alive()]),
        ],
    )

Patterns combine with ``&`` (and), ``|`` (or) and ``~`` (not). Hormone patterns: ``H == "LTS"``,
``H == ("X", "A")``, ``"_"`` for any value, ``"?name"`` to bind it, ``(H == "RCT").as_("p")`` to
bind the path. Targets: a connector name, ``"all"``, or ``reply("p")`` for ``p-1``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from dh2rt.lang import ast


def _expr(x: Any) -> ast.Expr:
    if isinstance(x, E):
        return x.node
    if isinstance(x, bool):
        raise TypeError("booleans are not DH2 values")
    if isinstance(x, int):
        return ast.Num(x)
    if isinstance(x, str):
        return ast.Name(x)
    raise TypeError(f"not a DH2 expression: {x!r}")


class E:
    """An integer expression (``ClockCycle / 4``, ``V.count + 1``)."""

    __slots__ = ("node",)

    def __init__(self, node: ast.Expr) -> None:
        self.node = node

    def _bin(self, op: ast.ArithOp, other: Any, swap: bool = False) -> E:
        a, b = (_expr(other), self.node) if swap else (self.node, _expr(other))
        return E(ast.BinOp(op, a, b))

    def __add__(self, o: Any) -> E:
        return self._bin("+", o)

    def __radd__(self, o: Any) -> E:
        return self._bin("+", o, True)

    def __sub__(self, o: Any) -> E:
        return self._bin("-", o)

    def __rsub__(self, o: Any) -> E:
        return self._bin("-", o, True)

    def __mul__(self, o: Any) -> E:
        return self._bin("*", o)

    def __rmul__(self, o: Any) -> E:
        return self._bin("*", o, True)

    def __truediv__(self, o: Any) -> E:
        return self._bin("/", o)

    def __rtruediv__(self, o: Any) -> E:
        return self._bin("/", o, True)

    def __mod__(self, o: Any) -> E:
        return self._bin("%", o)

    def __neg__(self) -> E:
        return E(ast.Neg(self.node))

    __hash__ = None  # type: ignore[assignment]


class P:
    """A pattern; combine with ``&``, ``|``, ``~``."""

    __slots__ = ("node",)

    def __init__(self, node: ast.Pattern) -> None:
        self.node = node

    def __and__(self, other: P) -> P:
        return P(ast.And(self.node, other.node))

    def __or__(self, other: P) -> P:
        return P(ast.Or(self.node, other.node))

    def __invert__(self) -> P:
        return P(ast.Not(self.node))

    def as_(self, path_var: str) -> P:
        """Bind the matched hormone's path (``H == NAME as p``)."""
        if not isinstance(self.node, ast.HormoneIs):
            raise TypeError("as_() applies to a hormone pattern")
        n = self.node
        return P(ast.HormoneIs(n.name, n.args, path_var, n.negate))


class _Comparable(E):
    """A numeric factor usable both in expressions and in comparisons."""

    __slots__ = ()

    def _cmp(self, op: ast.CmpOp, value: Any) -> P:
        raise NotImplementedError

    def __eq__(self, v: Any) -> P:  # type: ignore[override]
        return self._cmp("==", v)

    def __ne__(self, v: Any) -> P:  # type: ignore[override]
        return self._cmp("!=", v)

    def __lt__(self, v: Any) -> P:
        return self._cmp("<", v)

    def __le__(self, v: Any) -> P:
        return self._cmp("<=", v)

    def __gt__(self, v: Any) -> P:
        return self._cmp(">", v)

    def __ge__(self, v: Any) -> P:
        return self._cmp(">=", v)


class _Timer(_Comparable):
    __slots__ = ()

    def _cmp(self, op: ast.CmpOp, value: Any) -> P:
        return P(ast.TimerIs(op, _expr(value)))


class _Var(_Comparable):
    __slots__ = ()

    def _cmp(self, op: ast.CmpOp, value: Any) -> P:
        assert isinstance(self.node, ast.VarRef)
        return P(ast.VarIs(self.node.name, op, _expr(value)))


class _Sensor(_Comparable):
    __slots__ = ()

    def _cmp(self, op: ast.CmpOp, value: Any) -> P:
        assert isinstance(self.node, ast.SensorRef)
        return P(ast.SensorIs(self.node.name, op, _expr(value)))


class _Namespace:
    def __init__(self, kind: str) -> None:
        self._kind = kind

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        if self._kind == "V":
            return _Var(ast.VarRef(name))
        if self._kind == "S":
            return _Sensor(ast.SensorRef(name))
        return _ReceptorFactor(name)


class _ReceptorFactor:
    def __init__(self, name: str) -> None:
        self.name = name

    def __eq__(self, v: Any) -> P:  # type: ignore[override]
        return P(ast.ReceptorIs(self.name, "==", int(v)))

    def __ne__(self, v: Any) -> P:  # type: ignore[override]
        return P(ast.ReceptorIs(self.name, "!=", int(v)))

    __hash__ = None  # type: ignore[assignment]


class _TypeFactor:
    def _types(self, v: str | Iterable[str]) -> tuple[str, ...]:
        return (v,) if isinstance(v, str) else tuple(sorted(set(v)))

    def __eq__(self, v: Any) -> P:  # type: ignore[override]
        return P(ast.TypeIs(self._types(v)))

    def __ne__(self, v: Any) -> P:  # type: ignore[override]
        return P(ast.TypeIs(self._types(v), negate=True))

    __hash__ = None  # type: ignore[assignment]


def _arg_pattern(x: Any) -> ast.ArgPattern:
    if x == "_":
        return ast.Wildcard()
    if isinstance(x, str) and x.startswith("?"):
        return ast.Bind(x[1:])
    return _expr(x)


class _HormoneFactor:
    def _pattern(self, v: str | Sequence[Any], negate: bool) -> P:
        name, args = (v, ()) if isinstance(v, str) else (v[0], tuple(v[1:]))
        return P(ast.HormoneIs(name, tuple(_arg_pattern(a) for a in args), None, negate))

    def __eq__(self, v: Any) -> P:  # type: ignore[override]
        return self._pattern(v, False)

    def __ne__(self, v: Any) -> P:  # type: ignore[override]
        return self._pattern(v, True)

    __hash__ = None  # type: ignore[assignment]


T = _TypeFactor()
H = _HormoneFactor()
V = _Namespace("V")
S = _Namespace("S")
R = _Namespace("R")
LocalTimer = _Timer(ast.Timer())
ClockCycle = E(ast.Name("ClockCycle"))
TRUE = P(ast.TruePattern())


def const(name: str) -> E:
    """A named constant in an expression."""
    return E(ast.Name(name))


# ---------------------------------------------------------------- actions


def DOF1(angle: Any) -> ast.SetDOF:  # noqa: N802 - the paper's name
    return ast.SetDOF(1, _expr(angle))


def DOF2(angle: Any) -> ast.SetDOF:  # noqa: N802 - the paper's name
    return ast.SetDOF(2, _expr(angle))


def set_var(name: str, value: Any) -> ast.SetVar:
    return ast.SetVar(name, _expr(value))


def reply(path_var: str) -> ast.ViaReply:
    """The target ``path_var-1``: back along a bound path."""
    return ast.ViaReply(path_var)


def _target(via: str | ast.Target) -> ast.Target:
    if isinstance(via, str):
        return ast.ViaAll() if via == "all" else ast.ViaConnector(via)
    return via


def emit(name: str, *args: Any, via: str | ast.Target) -> ast.Emit:
    return ast.Emit(ast.HormoneTerm(name, tuple(_expr(a) for a in args)), _target(via))


def periodic(name: str, *args: Any, via: str | ast.Target, every: Any) -> ast.Periodic:
    return ast.Periodic(ast.HormoneTerm(name, tuple(_expr(a) for a in args)), _target(via), _expr(every))


def stop(name: str) -> ast.StopPeriodic:
    return ast.StopPeriodic(name)


def keep_alive() -> ast.KeepAlive:
    return ast.KeepAlive()


def activate(name: str) -> ast.ReceptorOp:
    return ast.ReceptorOp("activate", name)


def inhibit(name: str) -> ast.ReceptorOp:
    return ast.ReceptorOp("inhibit", name)


def create(name: str) -> ast.ReceptorOp:
    return ast.ReceptorOp("create", name)


def terminate(name: str = "self") -> ast.ReceptorOp:
    return ast.ReceptorOp("terminate", name)


def native(name: str, *args: Any) -> ast.NativeCall:
    return ast.NativeCall(name, tuple(_expr(a) for a in args))


# ---------------------------------------------------------------- declarations


def receptor(
    name: str, when: P | None, do: Sequence[ast.Action], status: ast.ReceptorStatus = "active"
) -> ast.Receptor:
    return ast.Receptor(name, (when or TRUE).node, tuple(do), status)


def hormone(name: str, **params: Sequence[str] | str) -> ast.HormoneDecl:
    """``hormone("X", phase=["A", "B"])``; ``n="int"`` declares an integer parameter."""
    out = []
    for pname, domain in params.items():
        out.append(ast.Param(pname, None if domain == "int" else tuple(domain)))
    return ast.HormoneDecl(name, tuple(out))


def program(
    name: str,
    *,
    consts: Mapping[str, Any] | None = None,
    options: Mapping[str, Any] | None = None,
    variables: Mapping[str, Any] | None = None,
    sensors: Sequence[str] = (),
    hormones: Sequence[ast.HormoneDecl] = (),
    natives: Mapping[str, Sequence[str]] | None = None,
    receptors: Sequence[ast.Receptor] = (),
    include: Sequence[ast.Program] = (),
) -> ast.Program:
    """A whole program; ``include`` programs come first, as ``include "file"`` does."""
    parts = [*include]
    own = ast.Program(
        name,
        consts=tuple(ast.Const(k, _expr(v)) for k, v in (consts or {}).items()),
        options=tuple(ast.Const(k, _expr(v)) for k, v in (options or {}).items()),
        variables=tuple(ast.VarDecl(k, _expr(v)) for k, v in (variables or {}).items()),
        sensors=tuple(ast.SensorDecl(s) for s in sensors),
        hormones=tuple(hormones),
        natives=tuple(ast.NativeDecl(k, tuple(v)) for k, v in (natives or {}).items()),
        receptors=tuple(receptors),
        source=f"<api:{name}>",
    )
    parts.append(own)
    return ast.Program(
        name,
        consts=tuple(c for p in parts for c in p.consts),
        options=tuple(c for p in parts for c in p.options),
        variables=tuple(c for p in parts for c in p.variables),
        sensors=tuple(c for p in parts for c in p.sensors),
        hormones=tuple(c for p in parts for c in p.hormones),
        natives=tuple(c for p in parts for c in p.natives),
        receptors=tuple(c for p in parts for c in p.receptors),
        source=own.source,
    )
