"""The stable serialized form of a program: what gets flashed onto a module.

An image is ``MAGIC`` followed by canonical JSON of the AST (sorted keys, no spaces, spans
and source file left out), so the same program gives the same bytes and the same hash
whichever front end built it and wherever its file lives.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from typing import Any

from dh2rt.errors import ImageError
from dh2rt.lang import ast

MAGIC = b"DH2IMG1\n"
_CLASSES: dict[str, type] = {
    name: obj for name, obj in vars(ast).items() if isinstance(obj, type) and dataclasses.is_dataclass(obj)
}


def _encode(node: Any) -> Any:
    if dataclasses.is_dataclass(node) and not isinstance(node, type):
        out: dict[str, Any] = {"": type(node).__name__}
        for f in dataclasses.fields(node):
            if f.compare:
                out[f.name] = _encode(getattr(node, f.name))
        return out
    if isinstance(node, tuple | list):
        return [_encode(x) for x in node]
    if node is None or isinstance(node, bool | int | str):
        return node
    raise TypeError(f"cannot serialize {type(node).__name__}")


def _decode(data: Any) -> Any:
    if isinstance(data, dict):
        cls = _CLASSES.get(data.get("", ""))
        if cls is None:
            raise ImageError(f"program image: unknown node type {data.get('')!r}")
        kwargs = {k: _decode(v) for k, v in data.items() if k != ""}
        try:
            return cls(**kwargs)
        except TypeError as exc:
            raise ImageError(f"program image: malformed {cls.__name__}: {exc}") from None
    if isinstance(data, list):
        return tuple(_decode(x) for x in data)
    return data


def to_image(program: ast.Program) -> bytes:
    """Serialize a program to its canonical image bytes."""
    body = json.dumps(_encode(program), sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return MAGIC + body.encode("ascii")


def from_image(image: bytes) -> ast.Program:
    """Rebuild the AST from image bytes; raises ImageError for anything else."""
    if not image.startswith(MAGIC):
        raise ImageError("not a DH2 program image (bad magic or another format version)")
    try:
        data = json.loads(image[len(MAGIC) :].decode("ascii"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ImageError(f"program image is corrupt: {exc}") from None
    program = _decode(data)
    if not isinstance(program, ast.Program):
        raise ImageError("program image does not hold a program")
    return program


def image_hash(image: bytes) -> str:
    """SHA-256 of the image, hex."""
    return hashlib.sha256(image).hexdigest()
