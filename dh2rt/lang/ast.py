"""The DH2 abstract syntax tree: frozen dataclasses, equal whichever front end built them.

Every node may carry a ``span`` (where the text parser found it); spans take no part in
equality, hashing or serialization, so a program parsed from text equals the same program
built with :mod:`dh2rt.lang.api`.

Shape (the paper's Fig. 2 grammar, extended as the paper's examples need)::

    Program     := declarations, Receptor*
    Receptor    := name, status (active | passive | absent), Pattern, Action*
    Pattern     := And | Or | Not | TruePattern | TypeIs | TimerIs | SensorIs | VarIs
                 | ReceptorIs | HormoneIs
    Action      := SetDOF | SetVar | Emit | Periodic | StopPeriodic | KeepAlive
                 | ReceptorOp | NativeCall
    Expr        := Num | Name | VarRef | SensorRef | Timer | BinOp | Neg
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from dh2rt.errors import SourceSpan

# ---------------------------------------------------------------- expressions


@dataclass(frozen=True)
class Num:
    """An integer literal."""

    value: int
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Name:
    """A bare name: a constant, ``ClockCycle``, or a value bound by the pattern (``?x``)."""

    name: str
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class VarRef:
    """``V.name``: a local variable."""

    name: str
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class SensorRef:
    """``S.name``: a sensor reading."""

    name: str
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Timer:
    """``LocalTimer``."""

    span: SourceSpan | None = field(default=None, compare=False, repr=False)


ArithOp = Literal["+", "-", "*", "/", "%"]


@dataclass(frozen=True)
class BinOp:
    """Integer arithmetic; ``/`` truncates toward zero as on the modules' processors."""

    op: ArithOp
    left: Expr
    right: Expr
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Neg:
    operand: Expr
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


Expr = Num | Name | VarRef | SensorRef | Timer | BinOp | Neg

# ---------------------------------------------------------------- patterns

CmpOp = Literal["==", "!=", "<", "<=", ">", ">="]


@dataclass(frozen=True)
class TruePattern:
    """Matches every state (a receptor driven by R or V alone)."""

    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class And:
    left: Pattern
    right: Pattern
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Or:
    left: Pattern
    right: Pattern
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Not:
    operand: Pattern
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class TypeIs:
    """``T == t`` or ``T == {t1, t2}`` (``negate`` for ``!=``); names or ``T<n>`` aliases."""

    types: tuple[str, ...]
    negate: bool = False
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class TimerIs:
    """``LocalTimer <op> expr``."""

    op: CmpOp
    value: Expr
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class SensorIs:
    name: str
    op: CmpOp
    value: Expr
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class VarIs:
    name: str
    op: CmpOp
    value: Expr
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class ReceptorIs:
    """``R.name == 1`` (active) or ``R.name == 0`` (passive or absent)."""

    name: str
    op: Literal["==", "!="]
    value: int
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Wildcard:
    """``_`` in a hormone pattern: any value."""

    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Bind:
    """``?name`` in a hormone pattern: any value, bound to ``name`` for the actions."""

    name: str
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


#: In hormone arguments a bare :class:`Name` is an atom when the parameter declares it,
#: else a constant or a bound value: the compiler decides, so both front ends agree.
ArgPattern = Wildcard | Bind | Expr


@dataclass(frozen=True)
class HormoneIs:
    """``H == NAME(args) [as path]`` (present) or ``H != NAME(args)`` (absent)."""

    name: str
    args: tuple[ArgPattern, ...]
    path_var: str | None = None
    negate: bool = False
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


Pattern = TruePattern | And | Or | Not | TypeIs | TimerIs | SensorIs | VarIs | ReceptorIs | HormoneIs

# ---------------------------------------------------------------- actions


@dataclass(frozen=True)
class ViaConnector:
    name: str
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class ViaAll:
    """Through every connected link."""

    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class ViaReply:
    """Along ``path-1``: back the way the hormone bound as ``path_var`` came."""

    path_var: str
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


Target = ViaConnector | ViaAll | ViaReply


@dataclass(frozen=True)
class HormoneTerm:
    """A hormone to create: ``NAME(args)``; an argument is an atom name or an integer expression."""

    name: str
    args: tuple[Expr, ...]
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class SetDOF:
    """``DOF1(angle)`` or ``DOF2(angle)``, degrees."""

    joint: Literal[1, 2]
    value: Expr
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class SetVar:
    """``V.name = expr``."""

    name: str
    value: Expr
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Emit:
    """``emit NAME(args) via target``: place a new hormone in the Buffer."""

    hormone: HormoneTerm
    target: Target
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Periodic:
    """``periodic NAME(args) via target every N``: the paper's periodical_hormone."""

    hormone: HormoneTerm
    target: Target
    period: Expr
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class StopPeriodic:
    """``stop NAME``: the paper's stop_hormone."""

    name: str
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class KeepAlive:
    """``keep_alive()``: the receptor stays active after firing (else it is one-shot)."""

    span: SourceSpan | None = field(default=None, compare=False, repr=False)


ReceptorVerb = Literal["activate", "inhibit", "create", "terminate"]


@dataclass(frozen=True)
class ReceptorOp:
    """``activate|inhibit|create|terminate NAME`` (``self`` names the firing receptor)."""

    verb: ReceptorVerb
    name: str
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class PathArg:
    """A bound path passed to a native action."""

    name: str
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class NativeCall:
    """A computation action registered by name in the runtime."""

    name: str
    args: tuple[Expr | PathArg, ...]
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


Action = SetDOF | SetVar | Emit | Periodic | StopPeriodic | KeepAlive | ReceptorOp | NativeCall

# ---------------------------------------------------------------- declarations

ReceptorStatus = Literal["active", "passive", "absent"]


@dataclass(frozen=True)
class Receptor:
    name: str
    pattern: Pattern
    actions: tuple[Action, ...]
    status: ReceptorStatus = "active"
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Const:
    name: str
    value: Expr
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class VarDecl:
    name: str
    initial: Expr
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class SensorDecl:
    name: str
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Param:
    """A hormone parameter: ``domain`` lists its atoms, or is None for an integer."""

    name: str
    domain: tuple[str, ...] | None
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class HormoneDecl:
    name: str
    params: tuple[Param, ...]
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class NativeDecl:
    name: str
    params: tuple[str, ...]
    span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Program:
    """A whole DH2 program. ``consts`` includes ``ClockCycle``; ``options`` e.g. ``max_hops``."""

    name: str
    consts: tuple[Const, ...] = ()
    options: tuple[Const, ...] = ()
    variables: tuple[VarDecl, ...] = ()
    sensors: tuple[SensorDecl, ...] = ()
    hormones: tuple[HormoneDecl, ...] = ()
    natives: tuple[NativeDecl, ...] = ()
    receptors: tuple[Receptor, ...] = ()
    source: str = field(default="<program>", compare=False)
