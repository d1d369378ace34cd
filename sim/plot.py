"""A run's plot: where the robot went, which way it faced, and the joints as a picture.

:func:`plot_figure` builds a matplotlib figure (Agg, imported lazily) from per-cycle samples;
:func:`plot_run` writes it to a PNG (or SVG, PDF). The panels:

- **path**: the centroid's and the head's XY path on the floor (equal axes), start and end
  marked;
- **heading and travel**: the head's yaw against its start (degrees, unwrapped) and the
  centroid's signed travel along the start heading (cm), over time;
- **DOF1 (pitch)** and **DOF2 (yaw)**: module-by-time images, one row per module in index
  order (module 0 on top), time along x, the angle as colour on a diverging scale centred at
  0. A travelling wave shows as diagonal stripes.

A sample is ``(time s, [(DOF1, DOF2) deg per module], centroid)`` and, from
:func:`sim.record.sample_world`, also ``head position, head yaw deg``; samples without
the last two (as :func:`sim.gaits.run_caterpillar` returns) plot the centroid only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from dh2rt.errors import RecordError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

Vec3 = tuple[float, float, float]
Angles = Sequence[tuple[float, float]]
#: (time s, [(DOF1 deg, DOF2 deg) per module], centroid (x, y, z) m[, head (x, y, z) m, head yaw deg])
Sample = tuple[float, Angles, Vec3] | tuple[float, Angles, Vec3, Vec3, float]

#: Titles of the panels, in the order of ``Figure.axes`` (colour bars follow them).
PANELS = ("path", "heading and travel", "DOF1 (pitch)", "DOF2 (yaw)")


def _check(samples: Sequence[Sample], path: Path | str) -> tuple[int, bool]:
    if not samples:
        raise RecordError(f"{path}: no samples to plot")
    n = len(samples[0][1])
    with_head = len(samples[0]) == 5
    for i, s in enumerate(samples):
        t, angles, centroid = s[0], s[1], s[2]
        if len(angles) != n or len(centroid) != 3 or not math.isfinite(t) or (len(s) == 5) != with_head:
            raise RecordError(
                f"{path}: sample {i} is malformed (expected {n} modules, an (x, y, z) centroid"
                + (", a head position and yaw)" if with_head else ")")
            )
    return n, with_head


def _unwrap(degrees: Sequence[float]) -> list[float]:
    out: list[float] = []
    for d in degrees:
        if out:
            prev = out[-1]
            d = prev + ((d - prev + 180.0) % 360.0 - 180.0)
        out.append(d)
    return out


def plot_figure(samples: Sequence[Sample], *, title: str = "", names: Sequence[str] | None = None) -> Figure:
    """The figure of :data:`PANELS` (see the module's doc); ``names`` label the image rows."""
    n, with_head = _check(samples, "plot")
    if names is not None and len(names) != n:
        raise RecordError(f"plot: {len(names)} module names for {n} modules")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    times = [s[0] for s in samples]
    t0, t1 = times[0], times[-1] if times[-1] > times[0] else times[0] + 1e-3
    cx = [s[2][0] for s in samples]
    cy = [s[2][1] for s in samples]
    fig = Figure(figsize=(10, 9), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(3, 2, height_ratios=(1.25, 1.0, 1.0))
    ax_path = fig.add_subplot(grid[0, 0])
    ax_head = fig.add_subplot(grid[0, 1])
    ax_dof1 = fig.add_subplot(grid[1, :])
    ax_dof2 = fig.add_subplot(grid[2, :], sharex=ax_dof1)

    # path: centimetres relative to the start centroid
    x0, y0 = cx[0], cy[0]
    ax_path.plot([(x - x0) * 100 for x in cx], [(y - y0) * 100 for y in cy], label="centroid", color="tab:blue")
    if with_head:
        hx = [(s[3][0] - x0) * 100 for s in samples]  # type: ignore[misc]
        hy = [(s[3][1] - y0) * 100 for s in samples]  # type: ignore[misc]
        ax_path.plot(hx, hy, label="head", color="tab:red", linewidth=0.8)
        ax_path.plot(hx[-1:], hy[-1:], marker="o", color="tab:red", linestyle="none")
    ax_path.plot([0.0], [0.0], marker="s", color="black", linestyle="none", label="start")
    ax_path.plot([(cx[-1] - x0) * 100], [(cy[-1] - y0) * 100], marker="o", color="tab:blue", linestyle="none")
    ax_path.set_aspect("equal", adjustable="datalim")
    ax_path.set_title(PANELS[0])
    ax_path.set_xlabel("x (cm)")
    ax_path.set_ylabel("y (cm)")
    ax_path.grid(True, linewidth=0.4, alpha=0.6)
    ax_path.legend(fontsize="small")

    # heading and travel
    ax_head.set_title(PANELS[1])
    ax_head.set_xlabel("time (s)")
    if with_head:
        yaws = _unwrap([s[4] for s in samples])  # type: ignore[misc]
        heading = [y - yaws[0] for y in yaws]
        ax_head.plot(times, heading, color="tab:red", label="heading")
        ax_head.set_ylabel("head heading from start (deg)", color="tab:red")
        start = math.radians(yaws[0])
        fx, fy = math.cos(start), math.sin(start)
        travel = [((x - x0) * fx + (y - y0) * fy) * 100 for x, y in zip(cx, cy, strict=True)]
        ax_travel = ax_head.twinx()
        ax_travel.plot(times, travel, color="tab:blue", label="travel")
        ax_travel.set_ylabel("centroid travel along start heading (cm)", color="tab:blue")
    else:
        ax_head.plot(times, [math.hypot(x - x0, y - y0) * 100 for x, y in zip(cx, cy, strict=True)])
        ax_head.set_ylabel("centroid displacement (cm)")
        ax_head.text(0.02, 0.95, "heading not sampled", transform=ax_head.transAxes, va="top", fontsize="small")
    ax_head.grid(True, linewidth=0.4, alpha=0.6)

    labels = list(names) if names is not None else [f"m{m}" for m in range(n)]
    for ax, dof in ((ax_dof1, 0), (ax_dof2, 1)):
        rows = [[s[1][m][dof] for s in samples] for m in range(n)]
        peak = max((abs(v) for row in rows for v in row), default=0.0) or 1.0
        image = ax.imshow(
            rows,
            aspect="auto",
            interpolation="nearest",
            cmap="RdBu_r",
            vmin=-peak,
            vmax=peak,
            extent=(t0, t1, n - 0.5, -0.5),
        )
        ax.set_title(PANELS[2 + dof])
        ax.set_ylabel("module")
        step = max(1, math.ceil(n / 12))
        ax.set_yticks(range(0, n, step), labels[::step], fontsize="small")
        fig.colorbar(image, ax=ax, label="angle (deg)", pad=0.01)
    ax_dof2.set_xlabel("time (s)")
    if title:
        fig.suptitle(title)
    return fig


def plot_run(
    samples: Sequence[Sample], path: Path | str, *, title: str = "", names: Sequence[str] | None = None
) -> Path:
    """Write :func:`plot_figure`'s figure to ``path`` (format from its suffix); return the path."""
    _check(samples, path)
    fig = plot_figure(samples, title=title, names=names)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
