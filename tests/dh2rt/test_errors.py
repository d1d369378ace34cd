"""One exception tree: every class in dh2rt/errors.py, drawn in its docstring, and no error
class or bare root raise anywhere else in the tree."""

from __future__ import annotations

import ast
import builtins
import inspect
import re
from pathlib import Path

import pytest

from dh2rt import errors

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("dh2rt", "drivers", "sim", "hil", "tools", "benchmarks")
CLASSES = {
    name: cls
    for name, cls in vars(errors).items()
    if inspect.isclass(cls) and issubclass(cls, BaseException) and cls.__module__ == errors.__name__
}


def sources() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


def test_every_class_is_drawn_in_the_docstring_tree() -> None:
    doc = errors.__doc__ or ""
    drawn = set(re.findall(r"[├└]── (\w+)", doc)) | {"DH2Error"}
    assert set(CLASSES) == drawn


@pytest.mark.parametrize("name", sorted(CLASSES))
def test_the_tree_shows_each_class_under_its_base(name: str) -> None:
    """Each drawn class sits under the first dh2rt base it inherits."""
    if name == "DH2Error":
        return
    lines = (errors.__doc__ or "").splitlines()
    row = next(i for i, line in enumerate(lines) if re.search(rf"── {name}\b", line))
    depth = lines[row].index(name)
    parent = next(
        m.group(1)
        for line in reversed(lines[:row])
        if (m := re.search(r"(\w+)", line[depth - 4 :])) and len(line) > depth - 4 and line.index(m.group(1)) < depth
    )
    bases = [b.__name__ for b in CLASSES[name].__mro__[1:] if b.__name__ in CLASSES]
    assert parent == bases[0], (name, parent, bases)


#: Names a class can derive from to be an exception: ours and the builtins'.
EXCEPTION_NAMES = set(CLASSES) | {
    name for name, obj in vars(builtins).items() if inspect.isclass(obj) and issubclass(obj, BaseException)
}


def _name(node: ast.expr) -> str:
    """``X`` for ``X``, ``errors.X`` and ``X(...)``; empty for anything else."""
    if isinstance(node, ast.Call):
        node = node.func
    if isinstance(node, ast.Attribute):
        return node.attr
    return node.id if isinstance(node, ast.Name) else ""


def test_no_error_class_outside_errors_py() -> None:
    found = []
    for path in sources():
        if path == ROOT / "dh2rt" / "errors.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and any(_name(b) in EXCEPTION_NAMES for b in node.bases):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}")
    assert not found


def test_no_bare_root_raise() -> None:
    """The root (and CodecError, which says neither local nor remote) are for catching only."""
    found = []
    for path in sources():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Raise) and node.exc is not None and _name(node.exc) in ("DH2Error", "CodecError"):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not found


def test_the_scans_see_what_they_look_for() -> None:
    """The two scans above would catch the forms they exist to catch."""
    tree = ast.parse("class A(errors.FrameCorrupted): pass\nclass B(KeyError): pass\nraise errors.DH2Error('x')")
    classes = [n for n in ast.walk(tree) if isinstance(n, ast.ClassDef)]
    assert all(_name(b) in EXCEPTION_NAMES for c in classes for b in c.bases)
    raised = next(n for n in ast.walk(tree) if isinstance(n, ast.Raise))
    assert raised.exc is not None and _name(raised.exc) == "DH2Error"


def test_local_and_remote_codec_errors() -> None:
    from dh2rt.hormone import Hormone, HormoneSpec, ParamSpec, Vocabulary
    from dh2rt.wire.can_frames import make_arbitration_id, segment
    from dh2rt.wire.frame import FrameCodec
    from dh2rt.wire.serial_framing import MAX_PAYLOAD, decode_serial, encode_serial

    codec = FrameCodec(Vocabulary([HormoneSpec(0, "X", (ParamSpec("a", ("A",)),))]), 4)
    with pytest.raises(errors.EncodeError):
        codec.encode(9, Hormone("X", ("A",)))  # no connector 9
    with pytest.raises(errors.EncodeError):
        FrameCodec(codec.vocabulary, 16)  # the sender field has 4 bits
    with pytest.raises(errors.EncodeError):
        encode_serial(bytes(MAX_PAYLOAD + 1))
    with pytest.raises(errors.EncodeError):
        make_arbitration_id(0, 0, 0, 1 << 20, 0)
    with pytest.raises(errors.EncodeError):
        segment(b"", 1, 0)
    with pytest.raises(errors.DecodeError):
        codec.decode(b"\x7f\x00")
    with pytest.raises(errors.DecodeError):
        decode_serial(b"\x05\x01\x02\x03\x04")
