"""Who held a module whose link was lost: the module itself, or the machine.

A link is lost when a neighbour stays silent for the liveness bound (``silence_cycles``
periods). On a robot each module has its own processor, and only its own work can hold it;
in the loop eight module processes share two cores with the world and whatever else runs,
and the scheduler can leave one out for that long. The modules report both sides: how late
each cycle started (``lateness_ms``) and how much CPU their process used from one cycle start
to the next (``work_ms``, :meth:`dh2rt.runtime.ModuleRuntime.work_ms`). A late start after
little work was the machine's; a long stretch of the module's own work is dh2rt's, whatever
the machine.
"""

from __future__ import annotations

from typing import Any


def assert_no_module_held_itself(summary: dict[str, Any], silence_cycles: int = 3) -> None:
    """No module's own work between two cycle starts came near the liveness bound (the
    rollout loading or compiling mid-run once held modules that long, issue 27), and every lost
    link is explained by a module the machine held (its worst start as late as the bound less a
    period) or by the link emulator's relay held as long."""
    assert_rows_not_held_by_themselves(
        summary["modules"],
        period_s=float(summary["cycle_period"]),  # as run (hil.pace may have stretched it)
        silence_cycles=silence_cycles,
        # once the modules cycled: start-up holds the relay longest (up to 1.4 s measured on
        # an idle machine), before any liveness bound runs, and excuses nothing
        relay_held_ms=float(summary.get("relay_held_running_ms") or 0.0),
        log=[line for line in summary["log"] if "silent for" in line][:5],
    )


def assert_rows_not_held_by_themselves(
    rows: list[dict[str, Any]],
    *,
    period_s: float,
    silence_cycles: int,
    relay_held_ms: float = 0.0,
    log: list[str] | None = None,
) -> None:
    """The same judgement on status rows as the modules write them (the launcher's summary
    rows, named by ``name``, or each ``dh2rt module``'s status file, named by ``module``):
    ``counters``, ``lateness_ms`` and ``work_ms``."""
    key = "name" if all("name" in r for r in rows) else "module"
    bound_ms = silence_cycles * period_s * 1000
    worked = {r[key]: (r.get("work_ms") or {}).get("max", 0.0) for r in rows}
    assert all(w < bound_ms / 2 for w in worked.values()), ("a module's own work held it", worked, bound_ms)
    lost = {r[key]: r["counters"]["links_lost"] for r in rows if r["counters"].get("links_lost")}
    if not lost:
        return
    near = bound_ms - period_s * 1000
    late = {r[key]: (r.get("lateness_ms") or {}).get("max", 0.0) for r in rows}
    held = {name: ms for name, ms in late.items() if ms >= near}
    assert held or relay_held_ms >= near, (
        "links lost with no module or relay held by the machine as long as the liveness bound",
        lost, late, worked, relay_held_ms, log or [],
    )  # fmt: skip
