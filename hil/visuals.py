"""What the launcher shows of the PyBullet stand-in, as ``dh2rt run --sim pybullet`` does:
``--record GIF`` (frames of the world at 10 frames per simulated second), ``--plot PNG``
(each module's DOF1/DOF2 and the centroid over time, sampled every world tick) and ``--gui``
(PyBullet's own window, given to the stand-in when it is built).

Frames and samples are taken under the stand-in's lock, between physics steps."""

from __future__ import annotations

from pathlib import Path
from typing import IO, TYPE_CHECKING

if TYPE_CHECKING:
    from hil.physics_stand_in import PhysicsStandIn
    from sim.record import Recorder, Sample


class RunVisuals:
    """Records and samples a stand-in's world while the loop runs."""

    def __init__(self, physics: PhysicsStandIn, record: Path | None, plot: Path | None) -> None:
        self.physics = physics
        self.plot = plot
        self.recorder: Recorder | None = None
        self.samples: list[Sample] = []
        self._next_frame = 0.0
        if record is not None:
            from sim.record import Recorder

            self.recorder = Recorder(physics.world, record)

    def after_tick(self) -> None:
        if self.plot is not None:
            self.samples.append(self.physics.sample())
        if self.recorder is not None and self.physics.world.time >= self._next_frame:
            with self.physics.lock:
                self.recorder.capture()
            self._next_frame = self.physics.world.time + 1.0 / self.recorder.fps

    def finish(self, title: str, out: IO[str]) -> None:
        """Write the animation and the plot; say where they are."""
        if self.recorder is not None and self.recorder.frame_count:
            out.write(f"animation: {self.recorder.save()} ({self.recorder.frame_count} frames)\n")
        if self.plot is not None and self.samples:
            from sim.record import plot_run

            out.write(f"plot: {plot_run(self.samples, self.plot, title=title)}\n")
