"""The entry-point groups through which upper layers plug into the ``dh2rt`` command, and
the shape of what they register (python-can finds its interfaces the same way).

``dh2rt.commands``    a command name -> ``module:main`` (``main(argv) -> exit code``)
``dh2rt.simulators``  a ``dh2rt run --sim`` name -> an object that is a :class:`Simulator`

Both the command's front door (:mod:`dh2rt.entry`, which must start fast) and the command
module (:mod:`dh2rt.cli`) read them from here, so neither imports the other for them; nothing
registered is imported until it is chosen.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:  # the command's front door imports this module: it stays light
    import argparse
    from importlib.metadata import EntryPoint

    from dh2rt.events import Event
    from dh2rt.robot import Robot

#: The entry-point group upper layers register their commands in (``pyproject.toml``).
COMMAND_GROUP = "dh2rt.commands"
#: The entry-point group of ``dh2rt run --sim`` simulators.
SIMULATOR_GROUP = "dh2rt.simulators"
#: The core's own subcommands: never looked up among the registered ones.
CORE_COMMANDS = ("check", "run", "image", "keys", "types", "demo")


def registered(group: str) -> dict[str, EntryPoint]:
    """The entry points of ``group`` by name (nothing is imported until one is chosen)."""
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in entry_points(group=group)}


class OptionAdder(Protocol):
    """Where a simulator declares its options: an argparse parser or argument group."""

    def add_argument(self, *args: Any, **kwargs: Any) -> argparse.Action: ...


class Simulator(Protocol):
    """What a ``dh2rt.simulators`` entry point names. Importing it must stay light (no physics
    library): ``dh2rt run --help`` loads it to list its options."""

    def add_arguments(self, parser: OptionAdder) -> None:
        """Declare this simulator's ``dh2rt run`` options (the core declares none of them)."""

    def check(self, options: argparse.Namespace) -> None:
        """Check the options before anything runs; raise a DH2Error naming the culprit."""

    def run(self, robot: Robot, options: argparse.Namespace, events: list[Event]) -> int:
        """Run ``robot`` in the simulation; return the exit code."""
