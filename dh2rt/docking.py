"""Docking, undocking and routes: the rules every world follows, written once.

Three worlds play the physical robot: the in-process :class:`~dh2rt.robot.Robot`, the
physics runner (``sim.runner``) and the hardware-in-the-loop world (``hil.world``). Each
implements :class:`DockingWorld` (what is docked where, who runs, how to cut and dock, whether
two connectors are aligned) and leaves the rules to this module:

- :func:`check_dock` and :func:`check_cut`: which docks and cuts are possible (male to female
  only, both connectors free, never a module to itself; a cut needs a link);
- :func:`route_end`: where a route (``path``-1, the connector to leave through at each hop)
  leads;
- :func:`reach_and_dock`: the native action's effect, carried out :data:`DOCK_DELAY` cycles
  after it is asked for (bending, aligning and latching take time): the module at the end of
  the route releases its link at the connector the route arrives at, and the asking
  connector docks there, if the world says the two are aligned by then;
- :func:`without_in_flight`: mail in flight across a link that is cut, or to or from a
  module that is killed, is never delivered (it is lost in flight, and counted so). A stale
  arrival would set the receiver's ConnectorStatus back to the dead link (the hop it came
  by), and a piece of a cut robot would keep a type it no longer has.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol, TypeVar

from dh2rt.errors import TopologyError
from dh2rt.profile import Profile

#: Cycles a world takes to carry out a ``reach_and_dock`` (bend, align, latch).
DOCK_DELAY = 10

End = tuple[int, int]  # (module, connector)


class Mail(Protocol):
    """Anything waiting to be delivered to a module at one of its connectors."""

    @property
    def at(self) -> int: ...


M = TypeVar("M", bound=Mail)


def without_in_flight(mail: list[M], connector: int) -> tuple[list[M], int]:
    """``mail`` less what is waiting to arrive at ``connector`` (it crossed a link that is
    gone), and how much that was: the caller counts it as lost in flight."""
    kept = [m for m in mail if m.at != connector]
    return kept, len(mail) - len(kept)


class DockingWorld(Protocol):
    """What a world offers the docking rules."""

    def peer_of(self, end: End) -> End | None:
        """What is docked at module m's connector c, if anything."""
        ...

    def running(self, module: int) -> bool: ...

    def cut(self, module: int, connector: int) -> None: ...

    def dock(self, a: int, a_conn: int, b: int, b_conn: int) -> None: ...

    def aligned(self, a: int, a_conn: int, b: int, b_conn: int) -> bool:
        """Whether the two connectors are close and aligned enough to latch now."""
        ...

    def schedule(self, cycles_from_now: int, action: Callable[[], None]) -> None: ...

    def where(self, module: int, connector: int) -> str:
        """``name.connector``, for messages."""
        ...

    def note(self, message: str) -> None:
        """Log a line (the world adds its cycle)."""
        ...


def check_dock(
    profile: Profile,
    docked: Callable[[End], bool],
    where: Callable[[int, int], str],
    a: int,
    a_conn: int,
    b: int,
    b_conn: int,
) -> None:
    """Raise TopologyError unless ``a.a_conn`` may dock to ``b.b_conn`` now."""
    if a == b:
        raise TopologyError(f"cannot dock {where(a, a_conn)} to {where(b, b_conn)}: a module cannot dock to itself")
    if not profile.can_link(a_conn, b_conn):
        raise TopologyError(f"cannot dock {where(a, a_conn)} to {where(b, b_conn)}: both are {profile.gender(a_conn)}")
    for m, c in ((a, a_conn), (b, b_conn)):
        if docked((m, c)):
            raise TopologyError(f"cannot dock {where(m, c)}: it is already docked")


def check_cut(peer: End | None, where: str) -> End:
    """The end docked at the connector being cut; TopologyError if there is none."""
    if peer is None:
        raise TopologyError(f"cannot cut {where}: nothing is docked there")
    return peer


def route_end(peer_of: Callable[[End], End | None], module: int, route: Sequence[int]) -> End | None:
    """Where ``route`` (the connector to leave through at each hop, as ``path``-1 gives it)
    leads from ``module``: the module reached and the connector it is reached at; None if
    some hop has no link. ``peer_of((m, c))`` is what is docked at module m's connector c."""
    here, at = module, 0
    for c in route:
        nxt = peer_of((here, c))
        if nxt is None:
            return None
        here, at = nxt
    return here, at


def body_up(peer_of: Callable[[End], End | None], profile: Profile, module: int) -> list[int]:
    """``module`` and the modules up its robot from it, each the one the last is docked to by
    its front (a snake's or a tail's spine, from its end towards its head)."""
    front = profile.connector_index("front")
    chain = [module]
    while (peer := peer_of((chain[-1], front))) is not None and peer[0] not in chain:
        chain.append(peer[0])
    return chain


def robot_of(peer_of: Callable[[End], End | None], profile: Profile, module: int) -> set[int]:
    """``module`` and every module docked to it, directly or through others: its robot."""
    seen, todo = {module}, [module]
    while todo:
        m = todo.pop()
        for c in range(1, profile.connector_count + 1):
            peer = peer_of((m, c))
            if peer is not None and peer[0] not in seen:
                seen.add(peer[0])
                todo.append(peer[0])
    return seen


def off_path(peer_of: Callable[[End], End | None], profile: Profile, module: int, count: int, foot: int) -> list[int]:
    """What a ``foot`` on its way to ``module``'s robot steers round, of the ``count`` modules
    in the world: every module but the foot and those on :func:`body_up` (the path it
    follows). That is the legs still on the robot, and any module lying apart from it: a
    foot that died on its way lies beside the robot, where the next foot passes."""
    return sorted(set(range(count)) - set(body_up(peer_of, profile, module)) - {foot})


def squaring_route(peer_of: Callable[[End], End | None], profile: Profile, module: int) -> tuple[int, ...]:
    """The route up ``module``'s robot whose joints square its face to a foot that came: two
    hops (the last two modules' joints), fewer on a shorter robot."""
    front = profile.connector_index("front")
    return (front,) * min(2, len(body_up(peer_of, profile, module)) - 1)


def reach_target(world: DockingWorld, module: int, connector: int, route: Sequence[int]) -> End | None:
    """Where ``reach_and_dock(connector, route)`` from ``module`` would dock now: the module at
    the end of the route and the connector the route arrives at; None (logged) if the route
    is broken, leads back, or either end is not free to act."""
    end = route_end(world.peer_of, module, route)
    if end is None:
        world.note(f"reach_and_dock from {world.where(module, connector)}: route broken")
        return None
    here, at = end
    if here == module or not world.running(here) or not world.running(module):
        return None
    if world.peer_of((module, connector)) is not None:
        world.note(f"reach_and_dock: {world.where(module, connector)} is not free")
        return None
    return here, at


def reach_and_dock(world: DockingWorld, module: int, connector: int, route: Sequence[int]) -> None:
    """Carry out ``reach_and_dock(connector, route)``: :data:`DOCK_DELAY` cycles later the
    module at the end of the route releases its link at the connector the route arrives at,
    and ``module``'s connector docks there. Nothing happens if by then the route leads
    nowhere or the two connectors are not aligned in the world (logged)."""
    route = tuple(route)

    def carry_out() -> None:
        target = reach_target(world, module, connector, route)
        if target is None:
            return
        here, at = target
        if not world.aligned(module, connector, here, at):
            asking, target_end = world.where(module, connector), world.where(here, at)
            world.note(f"{asking} cannot reach {target_end}: not aligned in the world")
            return
        world.cut(here, at)
        world.dock(module, connector, here, at)
        world.note(f"{world.where(module, connector)} docked to {world.where(here, at)}")

    world.schedule(DOCK_DELAY, carry_out)


def reach_dock_target(
    world: DockingWorld, module: int, connector: int, route: Sequence[int], target_conn: int
) -> tuple[int, str] | None:
    """For ``reach_dock(path, mine, theirs)``: the module at the end of ``route`` and the
    request in words (``asking -> target``), if both ends may act now and the target
    connector is free; None (logged) otherwise."""
    target = reach_target(world, module, connector, route)
    if target is None:
        return None
    here = target[0]
    where = f"{world.where(module, connector)} -> {world.where(here, target_conn)}"
    if world.peer_of((here, target_conn)) is not None:
        world.note(f"reach_dock {where}: the target connector is not free")
        return None
    return here, where


def reach_and_dock_to(world: DockingWorld, module: int, connector: int, route: Sequence[int], target_conn: int) -> None:
    """Carry out ``reach_dock(path, mine, theirs)`` in a world that does not model the motion:
    :data:`DOCK_DELAY` cycles later ``module``'s ``connector`` docks to connector
    ``target_conn`` of the module at the end of ``route`` (nothing is released), if the rules
    allow it then and the world says the two are aligned (logged otherwise). The physics
    runner carries the same request out by motion (``firmware.motion.reach``)."""
    route = tuple(route)

    def carry_out() -> None:
        target = reach_dock_target(world, module, connector, route, target_conn)
        if target is None:
            return
        here, where = target
        if not world.aligned(module, connector, here, target_conn):
            world.note(f"reach_dock {where}: not aligned in the world")
            return
        try:
            world.dock(module, connector, here, target_conn)
        except TopologyError as exc:
            world.note(f"reach_dock {where}: {exc}")
            return
        world.note(f"{world.where(module, connector)} docked to {world.where(here, target_conn)}")

    world.schedule(DOCK_DELAY, carry_out)


def release(world: DockingWorld, module: int, connector: int) -> None:
    """Carry out ``release(c)``: the module lets go of its link at connector ``c`` (logged,
    nothing else, if there is none)."""
    if world.peer_of((module, connector)) is None:
        world.note(f"release {world.where(module, connector)}: nothing docked there")
        return
    world.cut(module, connector)
    world.note(f"{world.where(module, connector)} released")
