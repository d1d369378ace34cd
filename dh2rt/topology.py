"""Robot topologies: how many modules there are and which connectors are docked.

A topology is what the physical world knows and the modules do not: modules are numbered for
the world's convenience only (labels, traces), never for programs. Built-in specs:

``snake:N``
    N modules, each ``back`` docked to the next one's ``front``; module 0 has a free front.
``tripod``, ``quadruped``, ``hexapod``, ``octopod``
    a spine of 1, 2, 3, 4 modules (``back`` to ``front``) with a leg hanging by its ``front``
    from each spine module's ``left`` and ``right``; the tripod's third leg hangs from the
    spine's ``back``.
``dragon``
    a quadruped with a 5-module tail docked to the rear spine's ``back`` (11 modules, as the
    paper's dragon that becomes an 11-module snake).
``t-shape``
    8 modules: a centre with 2-module arms on ``left`` and ``right`` and a 3-module stem on
    ``back``.
``ring:N``
    a snake whose last ``back`` docks to the first ``front``: a cycle (for testing bounded
    propagation).
a path ending in ``.toml``
    ``modules`` (a count or a list of names) and ``links`` (strings
    ``"A.connector <-> B.connector"``, A and B names or indices).
"""

from __future__ import annotations

import re
import tomllib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from dh2rt.errors import TopologyError
from dh2rt.profile import CONRO, Profile


@dataclass(frozen=True, slots=True)
class Link:
    """A docked pair: connector ``a_conn`` of module ``a`` to ``b_conn`` of module ``b``."""

    a: int
    a_conn: int
    b: int
    b_conn: int

    def ends(self) -> tuple[tuple[int, int], tuple[int, int]]:
        return (self.a, self.a_conn), (self.b, self.b_conn)


@dataclass(frozen=True)
class Topology:
    """Modules (by label) and the links between them, checked against a profile."""

    profile: Profile
    names: tuple[str, ...]
    links: tuple[Link, ...]
    spec: str = ""

    @property
    def size(self) -> int:
        return len(self.names)

    def __post_init__(self) -> None:
        used: dict[tuple[int, int], Link] = {}
        for link in self.links:
            for m, c in link.ends():
                if not 0 <= m < self.size:
                    raise TopologyError(f"{self.spec}: link {self.describe(link)} names module {m}, out of range")
                if not 1 <= c <= self.profile.connector_count:
                    raise TopologyError(f"{self.spec}: link names connector index {c}, out of range")
                if (m, c) in used:
                    raise TopologyError(
                        f"{self.spec}: connector {self.names[m]}.{self.profile.connector_name(c)} is docked twice"
                    )
                used[(m, c)] = link
            if link.a == link.b:
                raise TopologyError(f"{self.spec}: link {self.describe(link)} docks a module to itself")
            if not self.profile.can_link(link.a_conn, link.b_conn):
                raise TopologyError(
                    f"{self.spec}: link {self.describe(link)} joins two {self.profile.gender(link.a_conn)} connectors"
                )

    def describe(self, link: Link) -> str:
        p = self.profile
        return (
            f"{self.names[link.a]}.{p.connector_name(link.a_conn)} <-> "
            f"{self.names[link.b]}.{p.connector_name(link.b_conn)}"
        )

    def module_index(self, ref: str) -> int:
        """A module by label or by index written as digits."""
        if ref in self.names:
            return self.names.index(ref)
        if ref.isdigit() and int(ref) < self.size:
            return int(ref)
        raise TopologyError(f"{self.spec}: no module {ref!r} (modules: 0..{self.size - 1} or their names)")


def _chain(profile: Profile, first: int, count: int) -> list[Link]:
    back, front = profile.connector_index("back"), profile.connector_index("front")
    return [Link(i, back, i + 1, front) for i in range(first, first + count - 1)]


def snake(n: int, profile: Profile = CONRO) -> Topology:
    if n < 1:
        raise TopologyError("snake: needs at least 1 module")
    return Topology(profile, tuple(f"m{i}" for i in range(n)), tuple(_chain(profile, 0, n)), f"snake:{n}")


def ring(n: int, profile: Profile = CONRO) -> Topology:
    if n < 3:
        raise TopologyError("ring: needs at least 3 modules")
    back, front = profile.connector_index("back"), profile.connector_index("front")
    links = [*_chain(profile, 0, n), Link(n - 1, back, 0, front)]
    return Topology(profile, tuple(f"m{i}" for i in range(n)), tuple(links), f"ring:{n}")


def legged(spines: int, tail: int = 0, back_leg: bool = False, spec: str = "", profile: Profile = CONRO) -> Topology:
    """A spine of ``spines`` modules, two legs on each, an optional back leg or tail chain."""
    c = profile.connector_index
    names = [f"spine{i}" for i in range(spines)]
    links = _chain(profile, 0, spines)
    for i in range(spines):
        for side in ("left", "right"):
            names.append(f"{side}_leg{i}")
            links.append(Link(i, c(side), len(names) - 1, c("front")))
    if back_leg:
        names.append("back_leg")
        links.append(Link(spines - 1, c("back"), len(names) - 1, c("front")))
    if tail:
        start = len(names)
        names.extend(f"tail{i}" for i in range(tail))
        links.append(Link(spines - 1, c("back"), start, c("front")))
        links.extend(_chain(profile, start, tail))
    return Topology(profile, tuple(names), tuple(links), spec)


def t_shape(profile: Profile = CONRO) -> Topology:
    c = profile.connector_index
    names = ["centre", "left_arm0", "left_arm1", "right_arm0", "right_arm1", "stem0", "stem1", "stem2"]
    links = [
        Link(0, c("left"), 1, c("front")),
        Link(1, c("back"), 2, c("front")),
        Link(0, c("right"), 3, c("front")),
        Link(3, c("back"), 4, c("front")),
        Link(0, c("back"), 5, c("front")),
        Link(5, c("back"), 6, c("front")),
        Link(6, c("back"), 7, c("front")),
    ]
    return Topology(profile, tuple(names), tuple(links), "t-shape")


#: The keys a topology file may have.
TOML_KEYS = ("modules", "links")
BUILTIN_NAMES = ("snake:N", "ring:N", "tripod", "quadruped", "hexapod", "octopod", "dragon", "t-shape")
_LINK_RE = re.compile(r"^\s*([\w-]+)\.(\w+)\s*<->\s*([\w-]+)\.(\w+)\s*$")


def parse_spec(spec: str, profile: Profile = CONRO) -> Topology:
    """A topology from a built-in spec (see the module docs) or a ``.toml`` file path."""
    if spec.endswith(".toml"):
        return load_toml(Path(spec), profile)
    name, _, arg = spec.partition(":")
    if name in ("snake", "ring"):
        if not arg.isdigit():
            raise TopologyError(f"topology {spec!r}: expected {name}:N with N a whole number")
        return snake(int(arg), profile) if name == "snake" else ring(int(arg), profile)
    fixed = {
        "tripod": lambda: legged(1, back_leg=True, spec="tripod", profile=profile),
        "quadruped": lambda: legged(2, spec="quadruped", profile=profile),
        "hexapod": lambda: legged(3, spec="hexapod", profile=profile),
        "octopod": lambda: legged(4, spec="octopod", profile=profile),
        "dragon": lambda: legged(2, tail=5, spec="dragon", profile=profile),
        "t-shape": lambda: t_shape(profile),
    }
    if name in fixed and not arg:
        return fixed[name]()
    raise TopologyError(f"unknown topology {spec!r}; built-ins: {', '.join(BUILTIN_NAMES)}, or a .toml file")


def load_toml(path: Path, profile: Profile = CONRO) -> Topology:
    """Load a topology file. Errors name the file and the field."""
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise TopologyError(f"{path}: no such topology file") from None
    except UnicodeDecodeError as exc:
        raise TopologyError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    except tomllib.TOMLDecodeError as exc:
        raise TopologyError(f"{path}: {exc}") from None
    unknown = sorted(set(data) - set(TOML_KEYS))
    if unknown:
        raise TopologyError(f"{path}: unknown key(s) {', '.join(map(repr, unknown))} (known: {', '.join(TOML_KEYS)})")
    if "modules" not in data:
        raise TopologyError(f"{path}: missing field 'modules' (a count or a list of names)")
    modules = data["modules"]
    if isinstance(modules, int) and not isinstance(modules, bool):
        if modules < 1:
            raise TopologyError(f"{path}: field 'modules' must be at least 1, got {modules}")
        names: Sequence[str] = [f"m{i}" for i in range(modules)]
    elif isinstance(modules, list) and all(isinstance(m, str) for m in modules):
        names = modules
    else:
        raise TopologyError(f"{path}: field 'modules' must be a count or a list of names")
    if not names:
        raise TopologyError(f"{path}: field 'modules' lists no module")
    if len(set(names)) != len(names):
        raise TopologyError(f"{path}: field 'modules' repeats a name")
    raw_links = data.get("links", [])
    if not isinstance(raw_links, list):
        raise TopologyError(f"{path}: field 'links' must be a list of strings")
    links = list(_parse_links(path, names, raw_links, profile))
    return Topology(profile, tuple(names), tuple(links), str(path))


def _parse_links(path: Path, names: Sequence[str], raw: Iterable[object], profile: Profile) -> Iterable[Link]:
    def module(ref: str, where: str) -> int:
        if ref in names:
            return list(names).index(ref)
        if ref.isdigit() and int(ref) < len(names):
            return int(ref)
        raise TopologyError(f"{path}: {where}: no module {ref!r}")

    def connector(name: str, where: str) -> int:
        try:
            return profile.connector_index(name)
        except TopologyError as exc:
            raise TopologyError(f"{path}: {where}: {exc}") from None

    for i, item in enumerate(raw):
        where = f"links[{i}]"
        m = _LINK_RE.match(item) if isinstance(item, str) else None
        if m is None:
            raise TopologyError(f'{path}: {where}: expected "A.connector <-> B.connector", got {item!r}')
        yield Link(module(m[1], where), connector(m[2], where), module(m[3], where), connector(m[4], where))
