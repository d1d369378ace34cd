"""Native actions shipped with dh2rt: computation a DH2 program calls by name.

A program declares each native it uses (``native dock_tail_to_foot(path)``); the runtime
supplies the implementation. A native gets the module's :class:`~dh2rt.engine.Engine` and the
evaluated arguments. Natives that need the physical world ask for it with ``engine.effect``;
the in-process robot, the physics world or the real module's drivers carry the effect out.
"""

from __future__ import annotations

from collections.abc import Mapping

from dh2rt.engine import Engine, Native
from dh2rt.hormone import Path

#: Where a module on the assimilation's way holds its yaw (DOF2, degrees): straight.
ASSIST_YAW_DEG = 0.0


def assist_leg_assimilation(engine: Engine) -> None:
    """Fig. 5's ``assist_leg_assimilation()``: help the tail and the foot meet.

    In the paper the modules bend to bring the tail towards the foot. With the CONRO
    profile's genders the foot comes to the tail instead (docs/physics.md, *Legs to snake*):
    it travels along the robot to the tail's back, so the modules on the way hold their yaw
    straight (:data:`ASSIST_YAW_DEG`); a bent spine would put the tail's end off the line the
    foot follows.
    """
    engine.dof[1] = ASSIST_YAW_DEG
    engine.dof_changed = True
    engine.effect("assist")


def dock_tail_to_foot(engine: Engine, path: Path) -> None:
    """Align the tail's ``back`` with the foot at the end of ``path``-1 and dock to it.

    The foot releases its link to the body and becomes the new end of the tail: the leg is
    assimilated. Requested as the effect ``("reach_and_dock", (back, route))``.
    """
    back = engine.profile.connector_index("back")
    route = tuple(received_at for _sent, received_at in path)
    engine.effect("reach_and_dock", back, route)


def reach_dock(engine: Engine, path: Path, mine: int, theirs: int) -> None:
    """Bend this module's connector ``mine`` (profile index) to connector ``theirs`` of the
    module at the end of ``path``-1 and dock there; nothing is released. The chain of
    modules along the route does the bending (in physics: ``firmware.motion.reach``). Requested as the
    effect ``("reach_dock", (mine, route, theirs))``."""
    route = tuple(received_at for _sent, received_at in path)
    engine.effect("reach_dock", int(mine), route, int(theirs))


def release(engine: Engine, connector: int) -> None:
    """Let go of the link at connector ``connector`` (profile index): a cut by the module
    itself. Requested as the effect ``("release", (connector,))``."""
    engine.effect("release", int(connector))


STANDARD_NATIVES: Mapping[str, Native] = {
    "assist_leg_assimilation": assist_leg_assimilation,
    "dock_tail_to_foot": dock_tail_to_foot,
    "reach_dock": reach_dock,
    "release": release,
}
