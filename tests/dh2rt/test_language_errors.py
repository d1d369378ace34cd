"""Every class of bad program gives one clear error at the exact position, never a traceback."""

from __future__ import annotations

import pytest

from dh2rt.compiler import compile_source
from dh2rt.errors import ProgramCompileError, ProgramError, ProgramSyntaxError

HEADER = "const ClockCycle = 40\nhormone X(phase: A | B)\nvar count = 0\n"


def error_of(src: str, file: str = "bad.dh2") -> ProgramError:
    with pytest.raises(ProgramError) as info:
        compile_source(src, file)
    return info.value


@pytest.mark.parametrize(
    ("body", "kind", "line", "col", "words"),
    [
        # syntax
        ("receptor r when T == head and {\n}", ProgramSyntaxError, 4, 31, "expected a pattern"),
        ("receptor r when T == head { DOF1(45) ", ProgramSyntaxError, 4, 38, "expected '}'"),
        ("receptr r { }", ProgramSyntaxError, 4, 1, "expected a declaration"),
        ("receptor r { emit X(A) to back }", ProgramSyntaxError, 4, 24, "expected 'via'"),
        ("receptor r { DOF1(45) $ }", ProgramSyntaxError, 4, 23, "unexpected character '$'"),
        # unknown connector
        ("receptor r { emit X(A) via tail }", ProgramCompileError, 4, 28, "unknown connector 'tail'"),
        # unknown type
        ("receptor r when T == {head, T99} { DOF1(1) }", ProgramCompileError, 4, 17, "unknown topological type 'T99'"),
        # unknown action
        ("receptor r { wiggle(3) }", ProgramCompileError, 4, 14, "unknown action 'wiggle'"),
        ("receptor r { wiggle }", ProgramSyntaxError, 4, 14, "unknown action 'wiggle'"),
        # unknown hormone
        ("receptor r when H == Y(A) { DOF1(1) }", ProgramCompileError, 4, 17, "unknown hormone 'Y'"),
        ("receptor r { emit Y via back }", ProgramCompileError, 4, 19, "unknown hormone 'Y'"),
        # wrong arity
        (
            "receptor r when H == X(A, B) { DOF1(1) }",
            ProgramCompileError,
            4,
            17,
            "takes 1 argument(s), the pattern gives 2",
        ),
        ("receptor r { emit X via back }", ProgramCompileError, 4, 19, "takes 1 argument(s), given 0"),
        # undefined variable
        ("receptor r when V.cnt > 1 { DOF1(1) }", ProgramCompileError, 4, 17, "undefined variable V.cnt"),
        ("receptor r { V.total = V.count + 1 }", ProgramCompileError, 4, 14, "undefined variable V.total"),
        # values
        ("receptor r { emit X(E) via back }", ProgramCompileError, 4, 21, "'E' is not a value of X.phase"),
        ("receptor r { DOF1(angle) }", ProgramCompileError, 4, 19, "undefined name 'angle'"),
        ("receptor r when LocalTimer == 40 { DOF1(1) }", ProgramCompileError, 4, 17, "LocalTimer never equals 40"),
        ("receptor r { emit X(A) via p-1 }", ProgramCompileError, 4, 28, "'p' is not a path bound"),
        ("receptor r { activate nobody }", ProgramCompileError, 4, 14, "unknown receptor 'nobody'"),
        ("receptor r when H == X(?p) or T == head { DOF1(1) }", ProgramCompileError, 4, 17, "top-level 'and'"),
        ("hormone X", ProgramCompileError, 4, 9, "hormone 'X' is declared twice"),
    ],
)
def test_each_class_of_bad_program(body: str, kind: type, line: int, col: int, words: str) -> None:
    err = error_of(HEADER + body)
    assert isinstance(err, kind)
    assert err.span is not None
    assert (err.span.file, err.span.line, err.span.column) == ("bad.dh2", line, col)
    assert words in err.message
    rendered = str(err)
    assert rendered.startswith(f"bad.dh2:{line}:{col}: ")
    # the source line and a caret under the column
    src_line, caret_line = rendered.split("\n")[1:3]
    assert src_line.strip() == (HEADER + body).split("\n")[line - 1].strip()
    assert caret_line.index("^") - 4 == col - 1


def test_over_long_hormone_is_rejected_at_its_declaration() -> None:
    src = "const ClockCycle = 4\nhormone BIG(a: int, b: int, c: int, d: int)\n"
    err = error_of(src)
    assert isinstance(err, ProgramCompileError)
    assert err.span is not None and (err.span.line, err.span.column) == (2, 9)
    assert "too long" in err.message and "21 bytes" in err.message and "limit is 16" in err.message


def test_too_many_parameters() -> None:
    params = ", ".join(f"p{i}: A | B" for i in range(9))
    err = error_of(f"const ClockCycle = 4\nhormone MANY({params})\n")
    assert "9 parameters; the limit is 8" in err.message


def test_missing_clock_cycle_names_the_file_line_and_column() -> None:
    err = error_of("hormone X\n", "nofile.dh2")  # where the declarations begin: the first one
    assert str(err).startswith("nofile.dh2:1:9: ") and "ClockCycle" in str(err)


def test_include_errors_name_the_included_file(tmp_path: object) -> None:
    from pathlib import Path

    base = Path(str(tmp_path))
    (base / "lib.dh2").write_text("const ClockCycle = 4\nreceptor r when T == nope { DOF1(1) }\n")
    (base / "main.dh2").write_text('include "lib.dh2"\n')
    from dh2rt.compiler import compile_file

    with pytest.raises(ProgramCompileError) as info:
        compile_file(str(base / "main.dh2"))
    assert info.value.span is not None
    assert info.value.span.file.endswith("lib.dh2") and info.value.span.line == 2


def test_include_cycle_and_missing_file(tmp_path: object) -> None:
    from pathlib import Path

    from dh2rt.compiler import compile_file

    base = Path(str(tmp_path))
    (base / "a.dh2").write_text('include "a.dh2"\n')
    with pytest.raises(ProgramSyntaxError, match="include cycle"):
        compile_file(str(base / "a.dh2"))
    (base / "b.dh2").write_text('\n  include "missing.dh2"\n')
    with pytest.raises(ProgramSyntaxError) as info:
        compile_file(str(base / "b.dh2"))
    assert info.value.span is not None and (info.value.span.line, info.value.span.column) == (2, 11)
    with pytest.raises(ProgramSyntaxError, match="cannot read program"):
        compile_file(str(base / "nothere.dh2"))
