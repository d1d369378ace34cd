"""Hormones: content plus the path they travelled, and the compact encoding of content.

A hormone is ``(content, path)`` as in the paper. Content is a declared hormone name with
arguments; an argument is an *atom* (one of the values its parameter declares, held as ``str``)
or an integer (``int``, 32-bit signed). The path lists the links the hormone crossed, newest
first, as ``(sent_through, received_at)`` connector indices. A *routed* hormone (a reply sent
along ``path-1``) also carries ``route``: the connectors still to send it through, first
first; it is delivered along the route and not flooded.

Connector indices, not module addresses: nothing here names a module.

Content encoding (used by every wire codec and by the size check): one byte for the hormone's
index in the program's vocabulary, then per argument one byte (the atom's index in its
parameter's domain) or a zig-zag varint (an integer, at most 5 bytes, in its shortest form:
the decoder refuses an over-long one, so every accepted encoding re-encodes to itself).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import NamedTuple

from dh2rt.errors import DecodeError, HormoneError

#: An argument value: an atom (``str``) or a 32-bit signed integer.
Value = int | str
#: A path: ``(sent_through, received_at)`` connector indices, newest first.
Path = tuple[tuple[int, int], ...]

MAX_ARGS = 8
MAX_CONTENT_BYTES = 16
INT_MIN = -(2**31)
INT_MAX = 2**31 - 1
#: Default bound on a hormone's path length: a hormone that has crossed this many links is
#: dropped instead of forwarded again. This is what makes flooding terminate on a cycle.
DEFAULT_MAX_HOPS = 64
MAX_HOPS_LIMIT = 255


@dataclass(frozen=True, slots=True)
class Hormone:
    """A hormone: ``name(args)`` plus the path it travelled and, for replies, its route."""

    name: str
    args: tuple[Value, ...] = ()
    path: Path = ()
    route: tuple[int, ...] | None = None

    def content(self) -> str:
        return f"{self.name}({', '.join(str(a) for a in self.args)})"


class Arrival(NamedTuple):
    """A hormone as a link delivers it to a module's engine.

    ``at`` is the connector it arrived at, ``remote`` the connector the neighbour sent it
    through; ``hormone.path`` is as the sender sent it (the engine adds the hop ``(remote, at)``).
    """

    at: int
    remote: int
    hormone: Hormone


class Emission(NamedTuple):
    """A hormone the engine asks to send through one of its connectors (path as sent)."""

    through: int
    hormone: Hormone


@dataclass(frozen=True, slots=True)
class ParamSpec:
    """A hormone parameter: ``domain`` lists its atoms, or is None for an integer."""

    name: str
    domain: tuple[str, ...] | None


@dataclass(frozen=True, slots=True)
class HormoneSpec:
    """A declared hormone: its index in the vocabulary, name and parameters."""

    index: int
    name: str
    params: tuple[ParamSpec, ...]

    @property
    def max_content_bytes(self) -> int:
        return 1 + sum(1 if p.domain is not None else 5 for p in self.params)


class Vocabulary:
    """The hormones a program declares: what both ends of a link must agree on."""

    __slots__ = ("by_index", "by_name")

    def __init__(self, specs: Iterable[HormoneSpec]) -> None:
        self.by_index: tuple[HormoneSpec, ...] = tuple(specs)
        self.by_name: Mapping[str, HormoneSpec] = {s.name: s for s in self.by_index}
        for i, s in enumerate(self.by_index):
            if s.index != i:
                raise ValueError(f"hormone {s.name}: index {s.index} is not its position {i}")

    def check(self, hormone: Hormone) -> None:
        """Raise HormoneError unless ``hormone`` fits its declaration and the size limits."""
        spec = self.by_name.get(hormone.name)
        if spec is None:
            raise HormoneError(f"unknown hormone {hormone.name!r}")
        if len(hormone.args) != len(spec.params):
            raise HormoneError(f"hormone {hormone.name} takes {len(spec.params)} argument(s), got {len(hormone.args)}")
        for value, param in zip(hormone.args, spec.params, strict=True):
            _check_value(hormone.name, param, value)
        if len(hormone.path) > MAX_HOPS_LIMIT:
            raise HormoneError(f"hormone {hormone.name}: path of {len(hormone.path)} hops exceeds {MAX_HOPS_LIMIT}")

    def encode_content(self, hormone: Hormone) -> bytes:
        """Encode name and arguments; raises HormoneError for a hormone that breaks a limit."""
        self.check(hormone)
        spec = self.by_name[hormone.name]
        out = bytearray((spec.index,))
        for value, param in zip(hormone.args, spec.params, strict=True):
            if param.domain is not None:
                out.append(param.domain.index(str(value)))
            else:
                _put_varint(out, _zigzag(int(value)))
        if len(out) > MAX_CONTENT_BYTES:
            raise HormoneError(
                f"hormone {hormone.content()} encodes to {len(out)} bytes; the limit is {MAX_CONTENT_BYTES}"
            )
        return bytes(out)

    def decode_content(self, data: bytes, start: int = 0) -> tuple[str, tuple[Value, ...], int]:
        """Decode content at ``data[start:]``; returns name, args and the offset after it."""
        pos = start
        if pos >= len(data):
            raise DecodeError("hormone content: no bytes")
        idx = data[pos]
        pos += 1
        if idx >= len(self.by_index):
            raise DecodeError(f"hormone content: unknown hormone index {idx}")
        spec = self.by_index[idx]
        args: list[Value] = []
        for param in spec.params:
            if pos >= len(data):
                raise DecodeError(f"hormone {spec.name}: content truncated at parameter {param.name}")
            if param.domain is not None:
                atom = data[pos]
                pos += 1
                if atom >= len(param.domain):
                    raise DecodeError(f"hormone {spec.name}.{param.name}: atom index {atom} out of range")
                args.append(param.domain[atom])
            else:
                raw, pos = _get_varint(data, pos)
                value = _unzigzag(raw)
                if not INT_MIN <= value <= INT_MAX:
                    raise DecodeError(f"hormone {spec.name}.{param.name}: integer out of range")
                args.append(value)
        return spec.name, tuple(args), pos


def _check_value(hormone: str, param: ParamSpec, value: Value) -> None:
    if param.domain is not None:
        if not isinstance(value, str) or value not in param.domain:
            allowed = " | ".join(param.domain)
            raise HormoneError(f"hormone {hormone}.{param.name}: {value!r} is not one of {allowed}")
    elif isinstance(value, bool) or not isinstance(value, int):
        raise HormoneError(f"hormone {hormone}.{param.name}: expected an integer, got {value!r}")
    elif not INT_MIN <= value <= INT_MAX:
        raise HormoneError(f"hormone {hormone}.{param.name}: {value} is outside 32-bit range")


def _zigzag(n: int) -> int:
    return (n << 1) ^ (n >> 63) if n < 0 else n << 1


def _unzigzag(n: int) -> int:
    return (n >> 1) ^ -(n & 1)


def _put_varint(out: bytearray, n: int) -> None:
    while n >= 0x80:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)


def _get_varint(data: bytes, pos: int) -> tuple[int, int]:
    shift = 0
    result = 0
    for _ in range(5):
        if pos >= len(data):
            raise DecodeError("varint truncated")
        b = data[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            if b == 0 and shift:
                raise DecodeError("varint not in its shortest form")
            return result, pos
        shift += 7
    raise DecodeError("varint longer than 5 bytes")
