"""The DH2 compiler: AST to a :class:`~dh2rt.program.CompiledProgram` of closures, compiled once.

Checks every name against the declarations and the topology profile and reports the first
error with ``FILE:LINE:COL`` (``ProgramCompileError``). Each receptor becomes a match closure
and an action closure over a module's state (:class:`~dh2rt.program.ModuleState`, which an
engine is), and a guard from which :mod:`dh2rt.matcher` builds the receptor index.
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from dh2rt.errors import HormoneError, ProgramCompileError, SourceSpan
from dh2rt.hormone import (
    DEFAULT_MAX_HOPS,
    INT_MAX,
    INT_MIN,
    MAX_ARGS,
    MAX_CONTENT_BYTES,
    MAX_HOPS_LIMIT,
    Emission,
    Hormone,
    HormoneSpec,
    ParamSpec,
    Path,
    Vocabulary,
)
from dh2rt.lang import ast
from dh2rt.lang.image import to_image
from dh2rt.matcher import Guard, build_index, derive_guard, without_type_tests
from dh2rt.profile import CONRO, Profile
from dh2rt.program import (
    ABSENT,
    ACTIVE,
    PASSIVE,
    ActionFn,
    Bindings,
    CompiledProgram,
    CompiledReceptor,
    MatchFn,
    ModuleState,
    NativeSpec,
    ReceptorStatus,
    ValueFn,
)

_STATUS_CODE = {
    "active": ReceptorStatus.ACTIVE,
    "passive": ReceptorStatus.PASSIVE,
    "absent": ReceptorStatus.ABSENT,
}

_CMP: dict[str, Callable[[Any, Any], bool]] = {
    "==": operator.eq,
    "!=": operator.ne,
    "<": operator.lt,
    "<=": operator.le,
    ">": operator.gt,
    ">=": operator.ge,
}
KNOWN_OPTIONS = ("max_hops",)
#: The longest LocalTimer period a program may declare (``const ClockCycle``), in cycles:
#: 33 minutes at 20 ms. A module keeps its receptor index per LocalTimer value, so memory
#: and compile time grow with ClockCycle (linearly: dh2rt.matcher.build_index).
MAX_CLOCK_CYCLE = 100_000


def _div(a: int, b: int) -> int:
    if b == 0:
        raise ZeroDivisionError("division by zero in a DH2 expression")
    q = abs(a) // abs(b)
    return q if (a >= 0) == (b >= 0) else -q


def _mod(a: int, b: int) -> int:
    return a - b * _div(a, b)


_ARITH: dict[str, Callable[[int, int], int]] = {
    "+": operator.add,
    "-": operator.sub,
    "*": operator.mul,
    "/": _div,
    "%": _mod,
}


# ---------------------------------------------------------------- the compiler


@dataclass
class _Binding:
    kind: str  # "path" | "int" | "atom"
    domain: tuple[str, ...] | None = None


class _Compiler:
    def __init__(self, program: ast.Program, profile: Profile, indexed: bool = True) -> None:
        self.p = program
        self.profile = profile
        self.indexed = indexed
        self.consts: dict[str, int] = {}
        self.vars: dict[str, int] = {}
        self.sensors: dict[str, int] = {}
        self.hormones: dict[str, HormoneSpec] = {}
        self.natives: dict[str, NativeSpec] = {}
        self.receptor_names: dict[str, int] = {}
        self.clock_cycle = 0
        self.max_hops = DEFAULT_MAX_HOPS

    def fail(self, message: str, span: SourceSpan | None) -> ProgramCompileError:
        if span is None:
            return ProgramCompileError(f"{self.p.source}: {message}")
        return ProgramCompileError(message, span)

    def unique(self, kind: str, name: str, seen: Mapping[str, object], span: SourceSpan | None) -> None:
        if name in seen:
            raise self.fail(f"{kind} {name!r} is declared twice", span)

    def first_span(self) -> SourceSpan:
        """Where the program's declarations begin (a whole-program error points there)."""
        p = self.p
        for decls in (p.consts, p.options, p.variables, p.sensors, p.hormones, p.natives, p.receptors):
            for d in decls:
                if d.span is not None:
                    return d.span
        return SourceSpan(p.source, 1, 1)

    # ------------------------------------------------------------ declarations

    def declarations(self) -> None:
        for c in self.p.consts:
            self.unique("constant", c.name, self.consts, c.span)
            self.consts[c.name] = self.const_value(c.value, f"constant {c.name}")
        if "ClockCycle" not in self.consts:
            raise self.fail(
                "the program must declare `const ClockCycle = N` (cycles per LocalTimer period)", self.first_span()
            )
        self.clock_cycle = self.consts["ClockCycle"]
        if not 1 <= self.clock_cycle <= MAX_CLOCK_CYCLE:
            cc = next(c for c in self.p.consts if c.name == "ClockCycle")
            raise self.fail(f"ClockCycle must be 1..{MAX_CLOCK_CYCLE}, got {self.clock_cycle}", cc.span)
        seen_opts: dict[str, int] = {}
        for o in self.p.options:
            self.unique("option", o.name, seen_opts, o.span)
            if o.name not in KNOWN_OPTIONS:
                raise self.fail(f"unknown option {o.name!r} (known: {', '.join(KNOWN_OPTIONS)})", o.span)
            seen_opts[o.name] = value = self.const_value(o.value, f"option {o.name}")
            if not 1 <= value <= MAX_HOPS_LIMIT:
                raise self.fail(f"max_hops must be between 1 and {MAX_HOPS_LIMIT}, got {value}", o.span)
            self.max_hops = value
        for v in self.p.variables:
            self.unique("variable", v.name, self.vars, v.span)
            self.vars[v.name] = len(self.vars)
        for s in self.p.sensors:
            self.unique("sensor", s.name, self.sensors, s.span)
            self.sensors[s.name] = len(self.sensors)
        for h in self.p.hormones:
            self.unique("hormone", h.name, self.hormones, h.span)
            params = tuple(ParamSpec(p.name, p.domain) for p in h.params)
            spec = HormoneSpec(len(self.hormones), h.name, params)
            if len(params) > MAX_ARGS:
                raise self.fail(f"hormone {h.name} has {len(params)} parameters; the limit is {MAX_ARGS}", h.span)
            if spec.max_content_bytes > MAX_CONTENT_BYTES:
                raise self.fail(
                    f"hormone {h.name} is too long: its content may take {spec.max_content_bytes} bytes; "
                    f"the limit is {MAX_CONTENT_BYTES} (1 for the name, 1 per atom, up to 5 per int)",
                    h.span,
                )
            for prm in h.params:
                if prm.domain is not None and len(set(prm.domain)) != len(prm.domain):
                    raise self.fail(f"hormone {h.name}.{prm.name} lists an atom twice", prm.span)
                if prm.domain is not None and len(prm.domain) > 255:
                    raise self.fail(f"hormone {h.name}.{prm.name} has more than 255 atoms", prm.span)
            self.hormones[h.name] = spec
        for n in self.p.natives:
            self.unique("native action", n.name, self.natives, n.span)
            self.natives[n.name] = NativeSpec(n.name, len(n.params))
        for r in self.p.receptors:
            self.unique("receptor", r.name, self.receptor_names, r.span)
            self.receptor_names[r.name] = len(self.receptor_names)

    def const_value(self, e: ast.Expr, what: str) -> int:
        folded = self.fold(e, {})
        if folded is None:
            raise self.fail(f"{what} must be a constant integer expression", _span_of(e))
        return folded

    # ------------------------------------------------------------ expressions

    def fold(self, e: ast.Expr, binds: Mapping[str, Any]) -> int | None:
        """The constant value of ``e``, or None if it depends on the state."""
        if isinstance(e, ast.Num):
            return e.value
        if isinstance(e, ast.Name):
            if e.name in binds:
                return None
            if e.name in self.consts:
                return self.consts[e.name]
            raise self.fail(f"undefined name {e.name!r} (not a constant or a bound value)", e.span)
        if isinstance(e, ast.Neg):
            v = self.fold(e.operand, binds)
            return None if v is None else -v
        if isinstance(e, ast.BinOp):
            a, b = self.fold(e.left, binds), self.fold(e.right, binds)
            if a is None or b is None:
                return None
            if e.op in "/%" and b == 0:
                raise self.fail("division by zero", e.span)
            return _ARITH[e.op](a, b)
        return None

    def int_expr(self, e: ast.Expr, binds: Mapping[str, _Binding]) -> ValueFn:
        """Compile an integer expression to a closure (constants folded)."""
        const = self.fold(e, binds)
        if const is not None:
            return _constant(const)
        if isinstance(e, ast.Name):
            b = binds[e.name]
            if b.kind != "int":
                raise self.fail(f"{e.name!r} is bound to a {b.kind}, not a number", e.span)
            return _bound(e.name)
        if isinstance(e, ast.VarRef):
            if e.name not in self.vars:
                raise self.fail(f"undefined variable V.{e.name} (declare it with `var {e.name} = 0`)", e.span)
            i = self.vars[e.name]
            return lambda en, _b: en.vars[i]
        if isinstance(e, ast.SensorRef):
            if e.name not in self.sensors:
                raise self.fail(f"unknown sensor S.{e.name} (declare it with `sensor {e.name}`)", e.span)
            i = self.sensors[e.name]
            return lambda en, _b: en.sensors[i]
        if isinstance(e, ast.Timer):
            return lambda en, _b: en.timer
        if isinstance(e, ast.Neg):
            f = self.int_expr(e.operand, binds)
            return lambda en, bb: -f(en, bb)
        if isinstance(e, ast.BinOp):
            lf, rf, op = self.int_expr(e.left, binds), self.int_expr(e.right, binds), _ARITH[e.op]
            return lambda en, bb: op(lf(en, bb), rf(en, bb))
        raise self.fail(f"unexpected expression {type(e).__name__}", _span_of(e))

    def arg_value(self, e: ast.Expr, param: ParamSpec, hormone: str, binds: Mapping[str, _Binding]) -> ValueFn:
        """An argument of a hormone being created: an atom of its domain or an integer."""
        where = f"{hormone}.{param.name}"
        if param.domain is None:
            if isinstance(e, ast.Name) and e.name not in binds and e.name not in self.consts:
                raise self.fail(f"{where} is an int; {e.name!r} is not a constant or a bound value", e.span)
            return self.int_expr(e, binds)
        if isinstance(e, ast.Name) and e.name in param.domain:
            return _constant(e.name)
        if isinstance(e, ast.Name) and e.name in binds:
            b = binds[e.name]
            if b.kind != "atom" or b.domain is None or not set(b.domain) <= set(param.domain):
                raise self.fail(f"{e.name!r} may hold values that {where} does not accept", e.span)
            return _bound(e.name)
        shown = e.name if isinstance(e, ast.Name) else "an expression"
        raise self.fail(f"{shown!r} is not a value of {where} (one of {' | '.join(param.domain)})", _span_of(e))

    # ------------------------------------------------------------ patterns

    def pattern(self, p: ast.Pattern, binds: dict[str, _Binding], may_bind: bool) -> MatchFn:
        if isinstance(p, ast.TruePattern):
            return lambda _e, _b: True
        if isinstance(p, ast.And):
            lf, rf = self.pattern(p.left, binds, may_bind), self.pattern(p.right, binds, may_bind)
            return lambda e, b: lf(e, b) and rf(e, b)
        if isinstance(p, ast.Or):
            lf, rf = self.pattern(p.left, binds, False), self.pattern(p.right, binds, False)

            def either(e: ModuleState, b: Bindings) -> bool:
                mark = len(e.matched)
                if lf(e, b):
                    return True
                del e.matched[mark:]
                return rf(e, b)

            return either
        if isinstance(p, ast.Not):
            inner = self.pattern(p.operand, binds, False)

            def negated(e: ModuleState, b: Bindings) -> bool:
                mark = len(e.matched)
                result = inner(e, b)
                del e.matched[mark:]
                return not result

            return negated
        if isinstance(p, ast.TypeIs):
            wanted = frozenset(self.type_index(t, p.span) for t in p.types)
            if p.negate:
                return lambda e, _b: e.type_index not in wanted
            return lambda e, _b: e.type_index in wanted
        if isinstance(p, ast.TimerIs):
            k = self.fold(p.value, binds)
            if k is not None and p.op == "==" and not 0 <= k < self.clock_cycle:
                raise self.fail(f"LocalTimer never equals {k}: it counts 0..{self.clock_cycle - 1}", p.span)
            cmp, vf = _CMP[p.op], self.int_expr(p.value, binds)
            if k is not None and p.op == "==":
                return lambda e, _b: e.timer == k
            return lambda e, b: cmp(e.timer, vf(e, b))
        if isinstance(p, ast.VarIs | ast.SensorIs):
            ref: ast.Expr = ast.VarRef(p.name, p.span) if isinstance(p, ast.VarIs) else ast.SensorRef(p.name, p.span)
            lf2, rf2, cmp = self.int_expr(ref, binds), self.int_expr(p.value, binds), _CMP[p.op]
            return lambda e, b: cmp(lf2(e, b), rf2(e, b))
        if isinstance(p, ast.ReceptorIs):
            if p.name not in self.receptor_names:
                raise self.fail(f"unknown receptor {p.name!r} in R.{p.name}", p.span)
            i, want = self.receptor_names[p.name], (p.value == 1) == (p.op == "==")
            return lambda e, _b: (e.rstatus[i] == ACTIVE) == want
        if isinstance(p, ast.HormoneIs):
            return self.hormone_pattern(p, binds, may_bind)
        raise self.fail(f"unexpected pattern {type(p).__name__}", None)

    def hormone_pattern(self, p: ast.HormoneIs, binds: dict[str, _Binding], may_bind: bool) -> MatchFn:
        spec = self.hormone_spec(p.name, p.span)
        if len(p.args) != len(spec.params):
            raise self.fail(
                f"hormone {p.name} takes {len(spec.params)} argument(s), the pattern gives {len(p.args)}", p.span
            )
        if p.negate and (p.path_var or any(isinstance(a, ast.Bind) for a in p.args)):
            raise self.fail("a hormone pattern with != cannot bind values or a path", p.span)
        new_names = [a.name for a in p.args if isinstance(a, ast.Bind)] + ([p.path_var] if p.path_var else [])
        if new_names and not may_bind:
            raise self.fail("values and paths can be bound only in the top-level 'and' of a pattern", p.span)
        checks: list[tuple[int, Any]] = []  # (arg index, required value)
        setters: list[tuple[int, str]] = []
        for i, (a, param) in enumerate(zip(p.args, spec.params, strict=True)):
            if isinstance(a, ast.Wildcard):
                continue
            if isinstance(a, ast.Bind):
                if a.name in binds:
                    raise self.fail(f"{a.name!r} is bound twice in one pattern", a.span)
                binds[a.name] = _Binding("atom", param.domain) if param.domain else _Binding("int")
                setters.append((i, a.name))
                continue
            if param.domain is not None:
                if not (isinstance(a, ast.Name) and a.name in param.domain):
                    shown = a.name if isinstance(a, ast.Name) else "an expression"
                    raise self.fail(
                        f"{shown!r} is not a value of {p.name}.{param.name} (one of {' | '.join(param.domain)})",
                        _span_of(a),
                    )
                checks.append((i, a.name))
            else:
                v = self.fold(a, binds)
                if v is None:
                    raise self.fail(f"{p.name}.{param.name}: a pattern value must be a constant", _span_of(a))
                checks.append((i, v))
        if p.path_var:
            if p.path_var in binds:
                raise self.fail(f"{p.path_var!r} is bound twice in one pattern", p.span)
            binds[p.path_var] = _Binding("path")
        name, negate, path_var = p.name, p.negate, p.path_var
        checks_t, setters_t = tuple(checks), tuple(setters)

        def match(e: ModuleState, b: Bindings) -> bool:
            entries = e.present.get(name)
            if entries:
                for entry in entries:
                    args = entry[1]
                    for i, want in checks_t:
                        if args[i] != want:
                            break
                    else:
                        if negate:
                            return False
                        for i, bname in setters_t:
                            b[bname] = args[i]
                        if path_var is not None:
                            b[path_var] = entry[2]
                        e.matched.append(entry)
                        return True
            return negate

        return match

    @property
    def type_count(self) -> int:
        return len(self.profile.types)

    def type_index(self, name: str, span: SourceSpan | None) -> int:
        t = self.profile.type_by_name(name)
        if t is None:
            known = ", ".join(x.name + (f" (T{x.alias})" if x.alias else "") for x in self.profile.types[:9])
            raise self.fail(f"unknown topological type {name!r} in profile {self.profile.name} (e.g. {known})", span)
        return t.index

    def hormone_spec(self, name: str, span: SourceSpan | None) -> HormoneSpec:
        spec = self.hormones.get(name)
        if spec is None:
            raise self.fail(f"unknown hormone {name!r} (declare it with `hormone {name}(...)`)", span)
        return spec

    # ------------------------------------------------------------ actions

    def actions(self, r: ast.Receptor, binds: Mapping[str, _Binding]) -> tuple[ActionFn, bool]:
        fns: list[ActionFn] = []
        keep = False
        for a in r.actions:
            if isinstance(a, ast.KeepAlive):
                keep = True
                continue
            fns.append(self.action(a, r, binds))
        seq = tuple(fns)
        if len(seq) == 1:
            return seq[0], keep

        def run(e: ModuleState, b: Bindings) -> None:
            for f in seq:
                f(e, b)

        return run, keep

    def action(self, a: ast.Action, r: ast.Receptor, binds: Mapping[str, _Binding]) -> ActionFn:
        if isinstance(a, ast.SetDOF):
            vf, j = self.int_expr(a.value, binds), a.joint - 1

            def set_dof(e: ModuleState, b: Bindings) -> None:
                e.dof[j] = float(vf(e, b))
                e.dof_changed = True

            return set_dof
        if isinstance(a, ast.SetVar):
            if a.name not in self.vars:
                raise self.fail(f"undefined variable V.{a.name} (declare it with `var {a.name} = 0`)", a.span)
            vf, i = self.int_expr(a.value, binds), self.vars[a.name]

            def set_var(e: ModuleState, b: Bindings) -> None:
                e.vars[i] = vf(e, b)

            return set_var
        if isinstance(a, ast.Emit):
            make, send = self.hormone_term(a.hormone, binds), self.target(a.target, binds)
            return lambda e, b: send(e, b, make(e, b))
        if isinstance(a, ast.Periodic):
            make, send = self.hormone_term(a.hormone, binds), self.target(a.target, binds)
            period = self.fold(a.period, binds)
            if period is None or period < 1:
                raise self.fail("the period of a periodic hormone must be a constant of at least 1", _span_of(a.period))
            name = a.hormone.name

            def start(e: ModuleState, b: Bindings) -> None:
                h = make(e, b)
                bound = dict(b)
                e.start_periodic(name, period, lambda en: send(en, bound, h))
                send(e, b, h)

            return start
        if isinstance(a, ast.StopPeriodic):
            self.hormone_spec(a.name, a.span)
            name = a.name

            def stop(e: ModuleState, _b: Bindings) -> None:
                e.stop_periodic(name)

            return stop
        if isinstance(a, ast.ReceptorOp):
            if a.name == "self":
                idx = self.receptor_names[r.name]
            elif a.name in self.receptor_names:
                idx = self.receptor_names[a.name]
            else:
                raise self.fail(f"unknown receptor {a.name!r} in {a.verb}", a.span)
            return _RECEPTOR_OPS[a.verb](idx)
        if isinstance(a, ast.NativeCall):
            spec = self.natives.get(a.name)
            if spec is None:
                raise self.fail(
                    f"unknown action {a.name!r} (not built in, and not declared with `native {a.name}(...)`)", a.span
                )
            if len(a.args) != spec.arity:
                raise self.fail(f"native {a.name} takes {spec.arity} argument(s), given {len(a.args)}", a.span)
            argfs = tuple(self.native_arg(x, binds) for x in a.args)
            name = a.name

            def call(e: ModuleState, b: Bindings) -> None:
                e.natives[name](e, *(f(e, b) for f in argfs))

            return call
        raise self.fail(f"unexpected action {type(a).__name__}", None)

    def native_arg(self, x: ast.Expr | ast.PathArg, binds: Mapping[str, _Binding]) -> ValueFn:
        name = x.name if isinstance(x, ast.Name | ast.PathArg) else None
        if name is not None and name in binds and binds[name].kind in ("path", "atom"):
            return _bound(name)
        if isinstance(x, ast.PathArg):
            raise self.fail(f"{x.name!r} is not a bound path", x.span)
        return self.int_expr(x, binds)

    def hormone_term(
        self, t: ast.HormoneTerm, binds: Mapping[str, _Binding]
    ) -> Callable[[ModuleState, Bindings], Hormone]:
        spec = self.hormone_spec(t.name, t.span)
        if len(t.args) != len(spec.params):
            raise self.fail(f"hormone {t.name} takes {len(spec.params)} argument(s), given {len(t.args)}", t.span)
        argfs = [self.arg_value(x, prm, t.name, binds) for x, prm in zip(t.args, spec.params, strict=True)]
        name = t.name
        constant = all(
            (x.name not in binds) if isinstance(x, ast.Name) else self.fold(x, binds) is not None for x in t.args
        )
        if constant:
            h = Hormone(name, tuple(f(None, {}) for f in argfs))  # type: ignore[arg-type]
            try:
                Vocabulary([HormoneSpec(0, name, spec.params)]).encode_content(h)
            except HormoneError as exc:
                raise self.fail(str(exc), t.span) from None
            return lambda _e, _b: h
        fs = tuple(argfs)
        params = spec.params

        def make(e: ModuleState, b: Bindings) -> Hormone:
            args = tuple(f(e, b) for f in fs)
            for v, prm in zip(args, params, strict=True):
                if prm.domain is None and not INT_MIN <= v <= INT_MAX:
                    raise HormoneError(f"hormone {name}.{prm.name}: {v} is outside 32-bit range")
            return Hormone(name, args)

        return make

    def target(self, t: ast.Target, binds: Mapping[str, _Binding]) -> Callable[[ModuleState, Bindings, Hormone], None]:
        if isinstance(t, ast.ViaConnector):
            try:
                c = self.profile.connector_index(t.name)
            except ValueError:
                raise self.fail(
                    f"unknown connector {t.name!r} (profile {self.profile.name}: {', '.join(self.profile.connectors)})",
                    t.span,
                ) from None

            def via(e: ModuleState, _b: Bindings, h: Hormone) -> None:
                e.out.append(Emission(c, h))

            return via
        if isinstance(t, ast.ViaAll):

            def via_all(e: ModuleState, _b: Bindings, h: Hormone) -> None:
                for i, s in enumerate(e.status):
                    if s:
                        e.out.append(Emission(i + 1, h))

            return via_all
        if t.path_var not in binds or binds[t.path_var].kind != "path":
            raise self.fail(
                f"{t.path_var!r} is not a path bound by this receptor's pattern (H == ... as {t.path_var})", t.span
            )
        pv = t.path_var

        def via_reply(e: ModuleState, b: Bindings, h: Hormone) -> None:
            route = reply_route(b[pv])
            if route:
                e.out.append(Emission(route[0], Hormone(h.name, h.args, (), route[1:])))

        return via_reply

    # ------------------------------------------------------------ whole program

    def compile(self) -> CompiledProgram:
        self.declarations()
        receptors: list[CompiledReceptor] = []
        for i, r in enumerate(self.p.receptors):
            binds: dict[str, _Binding] = {}
            # The index files a receptor only under the types its pattern allows, so the
            # compiled match leaves out top-level type tests: the bucket already made them.
            # guard() checks those type names, with their positions, as the match would have.
            match = self.pattern(without_type_tests(r.pattern) if self.indexed else r.pattern, binds, True)
            guard = derive_guard(r.pattern, self) if self.indexed else Guard()
            act, keep = self.actions(r, binds)
            receptors.append(CompiledReceptor(i, r.name, _STATUS_CODE[r.status], match, act, keep, guard))
        image = to_image(self.p)
        return CompiledProgram(
            name=self.p.name,
            profile=self.profile,
            clock_cycle=self.clock_cycle,
            max_hops=self.max_hops,
            var_names=tuple(self.vars),
            var_initial=tuple(self.const_value(v.initial, f"initial value of {v.name}") for v in self.p.variables),
            sensor_names=tuple(self.sensors),
            vocabulary=Vocabulary(self.hormones.values()),
            natives=dict(self.natives),
            receptors=tuple(receptors),
            image=image,
            ast=self.p,
            index=build_index([r.guard for r in receptors], self.type_count, self.clock_cycle),
        )


def _constant(value: Any) -> ValueFn:
    return lambda _e, _b: value


def _bound(name: str) -> ValueFn:
    return lambda _e, b: b[name]


def reply_route(path: Path) -> tuple[int, ...]:
    """The connectors a reply leaves through, hop by hop, to retrace ``path`` (path-1)."""
    return tuple(received_at for _sent, received_at in path)


def _activate(i: int) -> ActionFn:
    def op(e: ModuleState, _b: Bindings) -> None:
        if e.rstatus[i] != ABSENT:
            e.rstatus[i] = ACTIVE

    return op


def _inhibit(i: int) -> ActionFn:
    def op(e: ModuleState, _b: Bindings) -> None:
        if e.rstatus[i] != ABSENT:
            e.rstatus[i] = PASSIVE

    return op


def _create(i: int) -> ActionFn:
    def op(e: ModuleState, _b: Bindings) -> None:
        e.rstatus[i] = ACTIVE

    return op


def _terminate(i: int) -> ActionFn:
    def op(e: ModuleState, _b: Bindings) -> None:
        e.rstatus[i] = ABSENT

    return op


_RECEPTOR_OPS: dict[str, Callable[[int], ActionFn]] = {
    "activate": _activate,
    "inhibit": _inhibit,
    "create": _create,
    "terminate": _terminate,
}


def _span_of(node: object) -> SourceSpan | None:
    return getattr(node, "span", None)


def compile_program(program: ast.Program, profile: Profile = CONRO, *, indexed: bool = True) -> CompiledProgram:
    """Check and compile a program; raises ProgramCompileError with the position.

    ``indexed=False`` files every receptor as a candidate in every state (the paper's
    "match every active receptor" loop): the same semantics, for measuring the index.
    """
    try:
        return _Compiler(program, profile, indexed).compile()
    except RecursionError:  # a tree built in Python deeper than the text parser allows
        raise ProgramCompileError(
            f"{program.source}: a pattern or an expression is nested too deeply to compile"
        ) from None


def compile_source(text: str, file: str = "<string>", profile: Profile = CONRO) -> CompiledProgram:
    from dh2rt.lang.parser import parse

    return compile_program(parse(text, file), profile)


def compile_file(path: str, profile: Profile = CONRO) -> CompiledProgram:
    from dh2rt.lang.parser import parse_file

    return compile_program(parse_file(path), profile)


def load_image(image: bytes, profile: Profile = CONRO) -> CompiledProgram:
    """Compile a program from its image (what a flashed module does at boot)."""
    from dh2rt.lang.image import from_image

    return compile_program(from_image(image), profile)
