"""Writing ``dh2rt.lua``: the dissector's Lua with its generated block filled in.

The dissector (``tools/wireshark/dh2rt.lua``) is its own template: the lines between
``-- BEGIN GENERATED`` and ``-- END GENERATED`` are written here, from the codec's layout
(:mod:`tools.wireshark.layout`), the profile's connector names and the programs that name
the hormones (index, name, parameters and the digest their Hellos carry). The committed file
is what :func:`dissector` writes with no program, and a test keeps it so.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from importlib.resources import files
from typing import Any

from dh2rt.errors import DissectorTemplateError
from dh2rt.profile import CONRO, Profile
from dh2rt.program import CompiledProgram
from dh2rt.wire.frame import program_digest
from tools.wireshark.layout import wire_layout

BEGIN = "-- BEGIN GENERATED\n"
END = "-- END GENERATED\n"
_INDENT = "    "
#: Tables that fit in this many characters are written on one line.
_INLINE = 96


#: The dissector's Lua has lost its generated block's markers.
TemplateError = DissectorTemplateError


def template() -> str:
    """The dissector's Lua as shipped (the committed ``dh2rt.lua``)."""
    return files("tools.wireshark").joinpath("dh2rt.lua").read_text(encoding="utf-8")


def dissector(programs: Sequence[CompiledProgram] = (), profile: Profile | None = None, base: str | None = None) -> str:
    """The dissector's Lua knowing ``programs`` (none: hormones show as ``#INDEX``), for
    robots of ``profile`` (default: the first program's, else CONRO)."""
    text = template() if base is None else base
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        raise TemplateError(f"the dissector's Lua has no {BEGIN.strip()!r} ... {END.strip()!r} block")
    chosen = profile or (programs[0].profile if programs else CONRO)
    return text[: start + len(BEGIN)] + generated_block(programs, chosen) + text[end:]


def generated_block(programs: Sequence[CompiledProgram], profile: Profile) -> str:
    """The Lua between the markers: LAYOUT, CONNECTORS and PROGRAMS."""
    names = ", ".join(f"{p.name} ({program_digest(p.image).hex()})" for p in programs) or "none"
    lines = [
        "-- Written by `dh2rt wireshark`; do not edit.",
        f"-- Profile {profile.name}; programs: {names}.",
        f"local LAYOUT = {lua(wire_layout(profile))}",
        f"local CONNECTORS = {lua(list(profile.connectors))}",
        f"local PROGRAMS = {lua([program_table(p) for p in programs])}",
    ]
    return "\n".join(lines) + "\n"


def program_table(program: CompiledProgram) -> dict[str, Any]:
    """What the dissector knows of one program: its hormones by index, and its digest."""
    hormones: dict[int, Any] = {}
    for spec in program.vocabulary.by_index:
        params: list[dict[str, Any]] = []
        for param in spec.params:
            entry: dict[str, Any] = {"name": param.name}
            if param.domain is not None:  # an integer parameter has no domain (nil in Lua)
                entry["domain"] = list(param.domain)
            params.append(entry)
        hormones[spec.index] = {"name": spec.name, "params": params}
    return {"name": program.name, "digest": program_digest(program.image).hex(), "hormones": hormones}


# -- Lua literals ------------------------------------------------------------------------


def lua(value: Any, depth: int = 0) -> str:
    """``value`` (str, int, bool, list, dict with str or int keys) as a Lua expression."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return lua_string(value)
    if isinstance(value, Mapping):
        items = [f"{_lua_key(k)} = {lua(v, depth + 1)}" for k, v in value.items()]
    elif isinstance(value, list | tuple):
        items = [lua(v, depth + 1) for v in value]
    else:
        raise TypeError(f"no Lua literal for {value!r}")
    return _table(items, depth)


def _table(items: list[str], depth: int) -> str:
    if not items:
        return "{}"
    inline = "{ " + ", ".join(items) + " }"
    if len(inline) + len(_INDENT) * depth <= _INLINE and "\n" not in inline:
        return inline
    inner = _INDENT * (depth + 1)
    return "{\n" + "".join(f"{inner}{item},\n" for item in items) + _INDENT * depth + "}"


def _lua_key(key: object) -> str:
    if isinstance(key, int) and not isinstance(key, bool):
        return f"[{key}]"
    if isinstance(key, str) and key.isidentifier() and key.isascii():
        return key
    if isinstance(key, str):
        return f"[{lua_string(key)}]"
    raise TypeError(f"no Lua table key for {key!r}")


def lua_string(text: str) -> str:
    """A double-quoted Lua string; anything but printable ASCII as decimal escapes of its
    UTF-8 bytes (which every Lua reads)."""
    out = []
    for byte in text.encode("utf-8"):
        char = chr(byte)
        if char in '"\\' or not 0x20 <= byte < 0x7F:
            out.append(f"\\{byte:03d}")
        else:
            out.append(char)
    return '"' + "".join(out) + '"'
