"""The text front end: ``.dh2`` source to :class:`dh2rt.lang.ast.Program`.

A hand-written lexer and recursive-descent parser, so that every error names
``FILE:LINE:COL`` and shows the line with a caret. The grammar, with examples, is in
``docs/language.md``. Newlines are whitespace; ``#`` starts a comment; actions may be
separated by ``;``.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

from dh2rt.errors import ProgramSyntaxError, SourceSpan
from dh2rt.lang import ast

#: How deeply parentheses, `not`s and signs may nest in one pattern or expression.
MAX_NESTING = 100
#: How many binary operators (``and``, ``or``, ``+``, ``-``, ``*``, ``/``, ``%``) one
#: declaration, receptor pattern or action may hold: with MAX_NESTING this
#: bounds how deep a program's trees are, so that every later stage (compiling, the image,
#: a module's boot) handles them within Python's recursion limit.
MAX_OPERATORS = 256

_TOKEN_RE = re.compile(
    r"""
    (?P<ws>[ \t\r\n]+|\#[^\n]*)
  | (?P<int>\d+)
  | (?P<ident>[A-Za-z_][A-Za-z0-9_]*)
  | (?P<string>"[^"\n]*")
  | (?P<op>==|!=|<=|>=|[<>=+\-*/%(){},;.?|:])
    """,
    re.VERBOSE,
)

_T = TypeVar("_T")


@dataclass(frozen=True, slots=True)
class Token:
    kind: str  # "int", "ident", "string", "op", "eof"
    text: str
    line: int
    column: int


def tokenize(text: str, file: str) -> list[Token]:
    """Split ``text`` into tokens; raises ProgramSyntaxError at the first bad character."""
    lines = text.split("\n")
    tokens: list[Token] = []
    pos, line, line_start = 0, 1, 0
    while pos < len(text):
        m = _TOKEN_RE.match(text, pos)
        if m is None:
            col = pos - line_start + 1
            raise ProgramSyntaxError(
                f"unexpected character {text[pos]!r}",
                SourceSpan(file, line, col, lines[line - 1]),
            )
        kind = m.lastgroup or ""
        if kind != "ws":
            tokens.append(Token(kind, m.group(), line, pos - line_start + 1))
        newlines = m.group().count("\n")
        if newlines:
            line += newlines
            line_start = m.start() + m.group().rfind("\n") + 1
        pos = m.end()
    tokens.append(Token("eof", "", line, pos - line_start + 1))
    return tokens


@dataclass
class _Decls:
    name: str | None = None
    consts: list[ast.Const] = field(default_factory=list)
    options: list[ast.Const] = field(default_factory=list)
    variables: list[ast.VarDecl] = field(default_factory=list)
    sensors: list[ast.SensorDecl] = field(default_factory=list)
    hormones: list[ast.HormoneDecl] = field(default_factory=list)
    natives: list[ast.NativeDecl] = field(default_factory=list)
    receptors: list[ast.Receptor] = field(default_factory=list)


_CMP_OPS = ("==", "!=", "<", "<=", ">", ">=")
_RECEPTOR_VERBS = ("activate", "inhibit", "create", "terminate")
_DECL_WORDS = "program, include, const, option, var, sensor, hormone, native or receptor"


class Parser:
    """Parses one file; ``include "other.dh2"`` parses the other file into the same program."""

    def __init__(self, text: str, file: str, *, _including: tuple[str, ...] = ()) -> None:
        self.file = file
        self.lines = text.split("\n")
        self.tokens = tokenize(text, file)
        self.i = 0
        self.including = (*_including, file)
        self.depth = 0  # parentheses, `not`s and signs open around the current token
        self.operators = 0  # binary operators so far in the current declaration or action

    # ------------------------------------------------------------ token helpers

    @property
    def tok(self) -> Token:
        return self.tokens[self.i]

    def span(self, tok: Token | None = None) -> SourceSpan:
        t = tok or self.tok
        src = self.lines[t.line - 1] if 0 < t.line <= len(self.lines) else ""
        return SourceSpan(self.file, t.line, t.column, src)

    def nest(self, tok: Token) -> None:
        """One level deeper in a pattern or an expression; refused past MAX_NESTING (a
        program is text a person wrote: this bounds the parser's recursion, not them)."""
        self.depth += 1
        if self.depth > MAX_NESTING:
            raise self.error(f"nested more than {MAX_NESTING} levels deep", tok)

    def operator(self, tok: Token) -> SourceSpan:
        """One more binary operator in the current declaration or action (its span);
        refused past MAX_OPERATORS, naming where the one too many is."""
        self.operators += 1
        if self.operators > MAX_OPERATORS:
            raise self.error(
                f"more than {MAX_OPERATORS} operators in one pattern or expression: "
                "split it (a variable, a constant, another receptor)",
                tok,
            )
        return self.span(tok)

    def error(self, message: str, tok: Token | None = None) -> ProgramSyntaxError:
        return ProgramSyntaxError(message, self.span(tok))

    def describe(self, tok: Token) -> str:
        return "end of file" if tok.kind == "eof" else repr(tok.text)

    def at(self, *texts: str) -> bool:
        return self.tok.kind in ("op", "ident") and self.tok.text in texts

    def accept(self, text: str) -> Token | None:
        if self.at(text):
            tok = self.tok
            self.i += 1
            return tok
        return None

    def expect(self, text: str, what: str | None = None) -> Token:
        tok = self.accept(text)
        if tok is None:
            raise self.error(f"expected {what or repr(text)}, found {self.describe(self.tok)}")
        return tok

    def ident(self, what: str) -> Token:
        if self.tok.kind != "ident":
            raise self.error(f"expected {what}, found {self.describe(self.tok)}")
        tok = self.tok
        self.i += 1
        return tok

    def comma_list(self, close: str, item: Callable[[], _T]) -> list[_T]:
        items: list[_T] = []
        if self.accept(close):
            return items
        while True:
            items.append(item())
            if self.accept(close):
                return items
            self.expect(",", f"',' or {close!r}")

    # ------------------------------------------------------------ top level

    def parse_program(self) -> ast.Program:
        decls = _Decls()
        self.parse_into(decls)
        return ast.Program(
            name=decls.name or Path(self.file).stem,
            consts=tuple(decls.consts),
            options=tuple(decls.options),
            variables=tuple(decls.variables),
            sensors=tuple(decls.sensors),
            hormones=tuple(decls.hormones),
            natives=tuple(decls.natives),
            receptors=tuple(decls.receptors),
            source=self.file,
        )

    def parse_into(self, d: _Decls) -> None:
        while self.tok.kind != "eof":
            self.operators = 0
            if self.accept("program"):
                d.name = self.ident("a program name").text
            elif self.accept("include"):
                self.include(d)
            elif self.accept("const"):
                name = self.ident("a constant name")
                self.expect("=")
                d.consts.append(ast.Const(name.text, self.expr(), self.span(name)))
            elif self.accept("option"):
                name = self.ident("an option name")
                self.expect("=")
                d.options.append(ast.Const(name.text, self.expr(), self.span(name)))
            elif self.accept("var"):
                name = self.ident("a variable name")
                initial: ast.Expr = ast.Num(0)
                if self.accept("="):
                    initial = self.expr()
                d.variables.append(ast.VarDecl(name.text, initial, self.span(name)))
            elif self.accept("sensor"):
                while True:
                    name = self.ident("a sensor name")
                    d.sensors.append(ast.SensorDecl(name.text, self.span(name)))
                    if not self.accept(","):
                        break
            elif self.accept("hormone"):
                d.hormones.append(self.hormone_decl())
            elif self.accept("native"):
                name = self.ident("a native action name")
                self.expect("(")
                params = self.comma_list(")", lambda: self.ident("a parameter name").text)
                d.natives.append(ast.NativeDecl(name.text, tuple(params), self.span(name)))
            elif self.accept("receptor"):
                d.receptors.append(self.receptor())
            else:
                raise self.error(f"expected a declaration ({_DECL_WORDS}), found {self.describe(self.tok)}")
            self.accept(";")

    def include(self, d: _Decls) -> None:
        tok = self.tok
        if tok.kind != "string":
            raise self.error(f"expected a quoted file name after include, found {self.describe(tok)}")
        self.i += 1
        target = Path(self.file).parent / tok.text[1:-1]
        if str(target) in self.including:
            raise self.error(f"include cycle: {target} includes itself", tok)
        try:
            text = read_source(target)
        except ProgramSyntaxError as exc:
            raise self.error(f"cannot include {target}: {exc.message}", tok) from None
        sub = Parser(text, str(target), _including=self.including)
        name = d.name
        sub.parse_into(d)
        d.name = name  # the including file names the program

    def hormone_decl(self) -> ast.HormoneDecl:
        name = self.ident("a hormone name")
        params: list[ast.Param] = []
        if self.accept("("):
            params = self.comma_list(")", self.param)
        return ast.HormoneDecl(name.text, tuple(params), self.span(name))

    def param(self) -> ast.Param:
        name = self.ident("a parameter name")
        self.expect(":", "':' and a parameter type (int, or atoms like A | B)")
        if self.accept("int"):
            return ast.Param(name.text, None, self.span(name))
        atoms = [self.ident("an atom name or int").text]
        while self.accept("|"):
            atoms.append(self.ident("an atom name").text)
        return ast.Param(name.text, tuple(atoms), self.span(name))

    def receptor(self) -> ast.Receptor:
        name = self.ident("a receptor name")
        status: ast.ReceptorStatus = "active"
        word: ast.ReceptorStatus
        for word in ("active", "passive", "absent"):
            if self.accept(word):
                status = word
                break
        pattern: ast.Pattern = ast.TruePattern(self.span(name))
        if self.accept("when"):
            pattern = self.pattern()
        self.expect("{", "'{' to open the receptor's actions")
        actions: list[ast.Action] = []
        while not self.accept("}"):
            if self.tok.kind == "eof":
                raise self.error(f"receptor {name.text}: expected '}}' to close its actions, found end of file")
            self.operators = 0
            actions.append(self.action())
            self.accept(";")
        return ast.Receptor(name.text, pattern, tuple(actions), status, self.span(name))

    # ------------------------------------------------------------ patterns

    def pattern(self) -> ast.Pattern:
        left = self.and_pattern()
        while tok := self.accept("or"):
            sp = self.operator(tok)
            left = ast.Or(left, self.and_pattern(), sp)
        return left

    def and_pattern(self) -> ast.Pattern:
        left = self.not_pattern()
        while tok := self.accept("and"):
            sp = self.operator(tok)
            left = ast.And(left, self.not_pattern(), sp)
        return left

    def not_pattern(self) -> ast.Pattern:
        if tok := self.accept("not"):
            self.nest(tok)
            inner = self.not_pattern()
            self.depth -= 1
            return ast.Not(inner, self.span(tok))
        return self.primary_pattern()

    def cmp_op(self, allowed: tuple[str, ...] = _CMP_OPS) -> str:
        tok = self.tok
        if tok.kind == "op" and tok.text in allowed:
            self.i += 1
            return tok.text
        raise self.error(f"expected one of {' '.join(allowed)}, found {self.describe(tok)}")

    def primary_pattern(self) -> ast.Pattern:
        tok = self.tok
        sp = self.span(tok)
        if self.accept("("):
            self.nest(tok)
            inner = self.pattern()
            self.expect(")", "')' to close the parenthesis")
            self.depth -= 1
            return inner
        if self.accept("true"):
            return ast.TruePattern(sp)
        if self.accept("T"):
            op = self.cmp_op(("==", "!="))
            return ast.TypeIs(tuple(sorted(set(self.type_set()))), op == "!=", sp)
        if self.accept("LocalTimer"):
            op = self.cmp_op()
            return ast.TimerIs(op, self.expr(), sp)  # type: ignore[arg-type]
        if self.accept("H"):
            op = self.cmp_op(("==", "!="))
            return self.hormone_pattern(op == "!=", sp)
        if tok.kind == "ident" and tok.text in ("S", "V", "R") and self.tokens[self.i + 1].text == ".":
            self.i += 2
            name = self.ident("a name after '.'").text
            if tok.text == "R":
                op = self.cmp_op(("==", "!="))
                val = self.tok
                if val.kind != "int" or val.text not in ("0", "1"):
                    raise self.error(f"R.{name} compares with 1 (active) or 0 (not active), found {self.describe(val)}")
                self.i += 1
                return ast.ReceptorIs(name, op, int(val.text), sp)  # type: ignore[arg-type]
            op = self.cmp_op()
            value = self.expr()
            if tok.text == "S":
                return ast.SensorIs(name, op, value, sp)  # type: ignore[arg-type]
            return ast.VarIs(name, op, value, sp)  # type: ignore[arg-type]
        raise self.error(
            "expected a pattern (T, LocalTimer, H, S.name, V.name, R.name, true, not, or '('), "
            f"found {self.describe(tok)}"
        )

    def type_set(self) -> list[str]:
        if self.accept("{"):
            return self.comma_list("}", lambda: self.ident("a type name (e.g. head or T1)").text)
        return [self.ident("a type name (e.g. head or T1) or {type, ...}").text]

    def hormone_pattern(self, negate: bool, sp: SourceSpan) -> ast.HormoneIs:
        name = self.ident("a hormone name").text
        args: list[ast.ArgPattern] = []
        if self.accept("("):
            args = self.comma_list(")", self.arg_pattern)
        path_var = None
        if self.accept("as"):
            path_var = self.ident("a name for the hormone's path").text
        return ast.HormoneIs(name, tuple(args), path_var, negate, sp)

    def arg_pattern(self) -> ast.ArgPattern:
        tok = self.tok
        if tok.kind == "ident" and tok.text == "_":
            self.i += 1
            return ast.Wildcard(self.span(tok))
        if self.accept("?"):
            name = self.ident("a name to bind after '?'")
            return ast.Bind(name.text, self.span(tok))
        return self.expr()

    # ------------------------------------------------------------ actions

    def action(self) -> ast.Action:
        tok = self.tok
        sp = self.span(tok)
        if tok.kind != "ident":
            raise self.error(f"expected an action, found {self.describe(tok)}")
        word = tok.text
        if word in ("DOF1", "DOF2"):
            self.i += 1
            self.expect("(")
            value = self.expr()
            self.expect(")")
            return ast.SetDOF(1 if word == "DOF1" else 2, value, sp)
        if word == "V" and self.tokens[self.i + 1].text == ".":
            self.i += 2
            name = self.ident("a variable name").text
            self.expect("=", "'=' (assignment)")
            return ast.SetVar(name, self.expr(), sp)
        if word == "emit":
            self.i += 1
            term = self.hormone_term()
            self.expect("via", "'via' and a connector, all, or path-1")
            return ast.Emit(term, self.target(), sp)
        if word == "periodic":
            self.i += 1
            term = self.hormone_term()
            self.expect("via", "'via' and a connector, all, or path-1")
            target = self.target()
            self.expect("every", "'every' and a period in cycles")
            return ast.Periodic(term, target, self.expr(), sp)
        if word == "stop":
            self.i += 1
            return ast.StopPeriodic(self.ident("the name of a periodic hormone").text, sp)
        if word == "keep_alive":
            self.i += 1
            self.expect("(")
            self.expect(")")
            return ast.KeepAlive(sp)
        if word in _RECEPTOR_VERBS:
            self.i += 1
            receptor = self.ident("a receptor name or self").text
            return ast.ReceptorOp(word, receptor, sp)  # type: ignore[arg-type]
        self.i += 1
        if not self.at("("):
            raise self.error(
                f"unknown action {word!r}: expected DOF1, DOF2, V.name = ..., emit, periodic, stop, "
                "keep_alive(), activate, inhibit, create, terminate, or a native call name(...)",
                tok,
            )
        self.i += 1
        args = self.comma_list(")", self.expr)
        return ast.NativeCall(word, tuple(args), sp)

    def hormone_term(self) -> ast.HormoneTerm:
        name = self.ident("a hormone name")
        args: list[ast.Expr] = []
        if self.accept("("):
            args = self.comma_list(")", self.expr)
        return ast.HormoneTerm(name.text, tuple(args), self.span(name))

    def target(self) -> ast.Target:
        tok = self.tok
        sp = self.span(tok)
        if self.accept("all"):
            return ast.ViaAll(sp)
        name = self.ident("a connector name, all, or a bound path followed by -1").text
        if self.accept("-"):
            one = self.tok
            if one.kind != "int" or one.text != "1":
                raise self.error(f"expected 1 in {name}-1 (the reversed path), found {self.describe(one)}")
            self.i += 1
            return ast.ViaReply(name, sp)
        return ast.ViaConnector(name, sp)

    # ------------------------------------------------------------ expressions

    def expr(self) -> ast.Expr:
        left = self.term()
        while self.at("+", "-"):
            tok = self.tok
            self.i += 1
            sp = self.operator(tok)
            left = ast.BinOp(tok.text, left, self.term(), sp)  # type: ignore[arg-type]
        return left

    def term(self) -> ast.Expr:
        left = self.unary()
        while self.at("*", "/", "%"):
            tok = self.tok
            self.i += 1
            sp = self.operator(tok)
            left = ast.BinOp(tok.text, left, self.unary(), sp)  # type: ignore[arg-type]
        return left

    def unary(self) -> ast.Expr:
        tok = self.tok
        if self.accept("-"):
            if self.tok.kind == "int":  # a negative literal is one number, as in the Python API
                lit = self.tok
                self.i += 1
                return ast.Num(-int(lit.text), self.span(tok))
            self.nest(tok)
            inner = self.unary()
            self.depth -= 1
            return ast.Neg(inner, self.span(tok))
        if self.accept("+"):
            self.nest(tok)
            inner = self.unary()
            self.depth -= 1
            return inner
        return self.atom()

    def atom(self) -> ast.Expr:
        tok = self.tok
        sp = self.span(tok)
        if tok.kind == "int":
            self.i += 1
            return ast.Num(int(tok.text), sp)
        if self.accept("("):
            self.nest(tok)
            inner = self.expr()
            self.expect(")", "')' to close the parenthesis")
            self.depth -= 1
            return inner
        if tok.kind == "ident":
            if tok.text in ("V", "S") and self.tokens[self.i + 1].text == ".":
                self.i += 2
                name = self.ident("a name after '.'").text
                return ast.VarRef(name, sp) if tok.text == "V" else ast.SensorRef(name, sp)
            self.i += 1
            if tok.text == "LocalTimer":
                return ast.Timer(sp)
            return ast.Name(tok.text, sp)
        raise self.error(f"expected a value (number, name, V.name, S.name, LocalTimer), found {self.describe(tok)}")


def parse(text: str, file: str = "<string>") -> ast.Program:
    """Parse DH2 source text."""
    return Parser(text, file).parse_program()


def parse_file(path: str | Path) -> ast.Program:
    """Parse a ``.dh2`` file; a missing file raises ProgramSyntaxError naming it."""
    p = Path(path)
    return parse(read_source(p), str(p))


def read_source(p: Path) -> str:
    """A program file's text; ProgramSyntaxError naming the file (and, for bytes that are
    not UTF-8, the line and column of the first one) when it cannot be read."""
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ProgramSyntaxError(f"{p}: cannot read program: {exc.strerror or exc}") from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        column = exc.start - (raw.rfind(b"\n", 0, exc.start) + 1) + 1
        shown = raw.split(b"\n")[line - 1].decode("utf-8", errors="replace")
        span = SourceSpan(str(p), line, column, shown)
        raise ProgramSyntaxError(f"byte 0x{raw[exc.start]:02x} is not UTF-8 text (programs are UTF-8)", span) from None
