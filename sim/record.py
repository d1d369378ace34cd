"""Seeing a run: headless GIF frames of a World, and a PNG plot of joint angles and travel.

:class:`Recorder` renders with PyBullet's software renderer (``ER_TINY_RENDERER``, no display
needed), the camera following the robot's centroid, and writes an animated GIF with Pillow.
:func:`plot_run` draws plain sample data with matplotlib's Agg backend (imported lazily).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import pybullet as p

from dh2rt.errors import RecordError
from sim.world import World

Vec3 = tuple[float, float, float]
#: One sample: (time s, [(dof1 deg, dof2 deg) per module], centroid (x, y, z) metres).
Sample = tuple[float, Sequence[tuple[float, float]], Vec3]



class Recorder:
    """Captures frames of ``world`` and writes them to ``path`` as an animated GIF.

    Call :meth:`capture` whenever a frame is wanted (e.g. every ``world.physics_hz / fps``
    steps) and :meth:`save` at the end; as a context manager it saves on exit if any frame
    was captured. ``distance`` is the camera distance in metres (default: fits the robot).
    """

    def __init__(
        self,
        world: World,
        path: Path,
        fps: int = 10,
        size: tuple[int, int] = (320, 240),
        *,
        distance: float | None = None,
        yaw_deg: float = 35.0,
        pitch_deg: float = -30.0,
    ) -> None:
        if not 1 <= fps <= 50:
            raise RecordError(f"fps must be between 1 and 50, got {fps}")
        if len(size) != 2 or not all(16 <= s <= 4096 for s in size):
            raise RecordError(f"size must be (width, height) with each in 16..4096, got {size}")
        self.world = world
        self.path = Path(path)
        self.fps = fps
        self.size = (int(size[0]), int(size[1]))
        extent = world.model.length * max(2.0, math.sqrt(world.size) * 1.6)
        self.distance = distance if distance is not None else max(0.4, extent)
        self.yaw_deg = yaw_deg
        self.pitch_deg = pitch_deg
        self._frames: list[Any] = []
        w, h = self.size
        self._projection = p.computeProjectionMatrixFOV(fov=50.0, aspect=w / h, nearVal=0.02, farVal=40.0)

    @property
    def frame_count(self) -> int:
        return len(self._frames)

    @property
    def steps_per_frame(self) -> int:
        """Physics steps between frames for real-time playback at ``fps``."""
        return max(1, round(self.world.physics_hz / self.fps))

    def capture(self) -> None:
        """Render one frame now, the camera aimed at the centroid."""
        from PIL import Image

        w, h = self.size
        view = p.computeViewMatrixFromYawPitchRoll(
            cameraTargetPosition=self.world.centroid(),
            distance=self.distance,
            yaw=self.yaw_deg,
            pitch=self.pitch_deg,
            roll=0.0,
            upAxisIndex=2,
        )
        _, _, rgba, _, _ = p.getCameraImage(
            w,
            h,
            view,
            self._projection,
            renderer=p.ER_TINY_RENDERER,
            physicsClientId=self.world.client,
        )
        # pybullet returns a numpy array when built with numpy, else a flat list.
        raw = rgba.tobytes() if hasattr(rgba, "tobytes") else bytes(bytearray(int(v) for v in rgba))
        self._frames.append(Image.frombytes("RGBA", (w, h), raw).convert("RGB"))

    def save(self) -> Path:
        """Write the GIF (looping) and return its path."""
        if not self._frames:
            raise RecordError(f"{self.path}: no frames captured")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        first, *rest = self._frames
        first.save(
            self.path,
            format="GIF",
            save_all=True,
            append_images=rest,
            duration=round(1000 / self.fps),
            loop=0,
            optimize=False,
        )
        return self.path

    def __enter__(self) -> Recorder:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None and self._frames:
            self.save()


def plot_run(samples: Sequence[Sample], path: Path, *, title: str = "") -> Path:
    """Plot each module's DOF1/DOF2 over time and the centroid's displacement; write a PNG."""
    if not samples:
        raise RecordError(f"{path}: no samples to plot")
    n = len(samples[0][1])
    for i, (t, angles, centroid) in enumerate(samples):
        if len(angles) != n or len(centroid) != 3 or not math.isfinite(t):
            raise RecordError(f"{path}: sample {i} is malformed (expected {n} modules and an (x, y, z) centroid)")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    times = [s[0] for s in samples]
    x0, y0, _ = samples[0][2]
    fig = Figure(figsize=(8, 6), dpi=100)
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    for m in range(n):
        line = ax1.plot(times, [s[1][m][0] for s in samples], label=f"m{m} DOF1", linewidth=1.0)[0]
        ax1.plot(
            times,
            [s[1][m][1] for s in samples],
            linestyle="--",
            color=line.get_color(),
            linewidth=0.7,
        )
    ax1.set_ylabel("angle (deg; DOF2 dashed)")
    if n <= 10:
        ax1.legend(fontsize="x-small", ncol=min(n, 5), loc="upper right")
    ax2.plot(times, [math.hypot(s[2][0] - x0, s[2][1] - y0) for s in samples], label="|displacement|")
    ax2.plot(times, [s[2][0] - x0 for s in samples], label="x", linewidth=0.8)
    ax2.plot(times, [s[2][1] - y0 for s in samples], label="y", linewidth=0.8)
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("centroid displacement (m)")
    ax2.legend(fontsize="small")
    if title:
        fig.suptitle(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path
