"""A compiled DH2 program: what the compiler makes and an engine runs.

:class:`CompiledProgram` holds the program's receptors as closures, compiled once, the
receptor index that says which of them can match a state (:mod:`dh2rt.matcher`), the
vocabulary of its hormones and the image it came from. The closures see a module only
through :class:`ModuleState`, the part of an engine's state they may read and change; this
module imports neither the engine nor the compiler.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from dh2rt.hormone import Emission, Path, Vocabulary
from dh2rt.lang import ast
from dh2rt.lang.image import image_hash
from dh2rt.matcher import Guard, ReceptorIndex
from dh2rt.profile import Profile


class ReceptorStatus(enum.IntEnum):
    """The paper's R: 1 active, 0 passive; a terminated receptor is absent."""

    ABSENT = -1
    PASSIVE = 0
    ACTIVE = 1


# Plain ints for the hot path, where an engine keeps each receptor's status in a list.
ABSENT, PASSIVE, ACTIVE = int(ReceptorStatus.ABSENT), int(ReceptorStatus.PASSIVE), int(ReceptorStatus.ACTIVE)

#: A hormone present in H during one step: (name, args, path with the last hop, route or
#: None, connector it arrived at or 0). A plain tuple: a NamedTuple costs 8 times as much to
#: build (408 ns against 52 ns here), and the engine builds one per arrival.
Entry = tuple[str, tuple[Any, ...], Path, tuple[int, ...] | None, int]


class ModuleState(Protocol):
    """What a compiled receptor's closures may read and change of one module (an
    :class:`~dh2rt.engine.Engine` is one)."""

    timer: int
    type_index: int
    status: list[int]
    vars: list[int]
    sensors: list[int]
    rstatus: list[int]
    dof: list[float]
    dof_changed: bool
    #: hormones present this step, by name
    present: dict[str, list[Entry]]
    #: the entries the pattern being matched bound (so they are not forwarded)
    matched: list[Entry]
    #: the Buffer: what this step sends
    out: list[Emission]
    natives: Mapping[str, Callable[..., None]]

    def start_periodic(self, name: str, period: int, send: Callable[[Any], None]) -> None: ...

    def stop_periodic(self, name: str) -> None: ...


Bindings = dict[str, Any]
MatchFn = Callable[[ModuleState, Bindings], bool]
ActionFn = Callable[[ModuleState, Bindings], None]
ValueFn = Callable[[ModuleState, Bindings], Any]


@dataclass(frozen=True, slots=True)
class CompiledReceptor:
    index: int
    name: str
    initial: ReceptorStatus
    match: MatchFn
    act: ActionFn
    keep_alive: bool
    guard: Guard


@dataclass(frozen=True, slots=True)
class NativeSpec:
    name: str
    arity: int


@dataclass
class CompiledProgram:
    """A program ready to run: closures, index, vocabulary, and the image it came from."""

    name: str
    profile: Profile
    clock_cycle: int
    max_hops: int
    var_names: tuple[str, ...]
    var_initial: tuple[int, ...]
    sensor_names: tuple[str, ...]
    vocabulary: Vocabulary
    natives: Mapping[str, NativeSpec]
    receptors: tuple[CompiledReceptor, ...]
    image: bytes
    ast: ast.Program
    #: Which receptors can match which states (see dh2rt.matcher).
    index: ReceptorIndex

    @property
    def hash(self) -> str:
        return image_hash(self.image)

    def receptor_index(self, name: str) -> int:
        for r in self.receptors:
            if r.name == name:
                return r.index
        raise KeyError(f"program {self.name} has no receptor {name!r}")
