"""The trace record of one module's cycle, as the JSON Lines trace and the module runtime
write it.

Fields: ``cycle`` (int), ``module`` (the observer's index; for ``snake:N`` 0 is the end whose
front is free), ``name``, ``type`` (name), ``T`` (alias number or null), ``timer``,
``actuators`` (``{"DOF1": deg, "DOF2": deg}``), ``status`` (connector -> remote connector or
"0"), ``received`` (hormone, connector it arrived at, connector it was sent through, path) and
``sent`` (hormone, connector, and for replies the route still to go). Physics runs add
``pos`` ([x, y, z] metres); the module runtime adds ``t`` (its clock when the cycle began).
A program that declares sensors adds ``sensors`` (``{"roll": deg, ...}``: S as that cycle read it);
one that declares variables adds ``variables`` (``{"waiting": 0, ...}``: V as that cycle left it).
A cycle in which receptor actions failed has ``faults``: ``["receptor NAME: message", ...]``.

It reads an engine only, so that the in-process robot (:mod:`dh2rt.trace`) and the module
runtime (:mod:`dh2rt.runtime`) share it without the runtime depending on the robot.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from dh2rt.engine import Engine
from dh2rt.hormone import Arrival, Emission
from dh2rt.profile import Profile


def arrival_json(a: Arrival, profile: Profile) -> dict[str, Any]:
    name = profile.connector_name
    return {
        "hormone": a.hormone.content(),
        "at": name(a.at) if a.at else None,
        "from": name(a.remote) if a.at else None,
        "path": [[name(x), name(y)] for x, y in a.hormone.path],
    }


def emission_json(e: Emission, profile: Profile) -> dict[str, Any]:
    d: dict[str, Any] = {"hormone": e.hormone.content(), "through": profile.connector_name(e.through)}
    if e.hormone.route is not None:
        d["route"] = [profile.connector_name(c) for c in e.hormone.route]
    return d


def cycle_json(
    engine: Engine,
    cycle: int,
    module: int,
    name: str,
    received: Sequence[Arrival],
    sent: Sequence[Emission],
    faults: Sequence[str] = (),
) -> dict[str, Any]:
    """One module's cycle in the trace format, read from its engine just after the cycle ran
    (the in-process robot and the module runtime both write these)."""
    p = engine.profile
    t = engine.topo_type
    record: dict[str, Any] = {
        "cycle": cycle,
        "module": module,
        "name": name,
        "type": t.name,
        "T": t.alias,
        "timer": (engine.timer - 1) % engine.clock,
        "actuators": {"DOF1": engine.dof[0], "DOF2": engine.dof[1]},
        "status": {c: p.connector_name(s) for c, s in zip(p.connectors, engine.status, strict=True)},
        "received": [arrival_json(a, p) for a in received],
        "sent": [emission_json(x, p) for x in sent],
    }
    if engine.sensors:  # S, as the cycle read it, when the program declares sensors
        record["sensors"] = engine.named_sensors()
    if engine.vars:  # V, as the cycle left it, when the program declares variables
        record["variables"] = engine.variables()
    if faults:
        record["faults"] = list(faults)
    return record
