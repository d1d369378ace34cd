"""What the launcher shows of the PyBullet stand-in, as ``dh2rt run --sim pybullet`` does:
``--record GIF`` (frames of the world streamed to the file, 10 per simulated second times
``--record-speed``, the camera ``--camera fixed`` or ``follow``), ``--plot PNG`` (the XY path,
heading, and the joints as module-by-time pictures, sampled every world tick; see
:mod:`sim.plot`) and ``--gui`` (PyBullet's own window, given to the stand-in when it is built).

Frames and samples are taken under the stand-in's lock, between physics steps."""

from __future__ import annotations

from pathlib import Path
from typing import IO, TYPE_CHECKING

if TYPE_CHECKING:
    from hil.physics_stand_in import PhysicsStandIn
    from sim.record import Camera, Recorder, Sample


class RunVisuals:
    """Records and samples a stand-in's world while the loop runs."""

    def __init__(
        self,
        physics: PhysicsStandIn,
        record: Path | None,
        plot: Path | None,
        *,
        camera: Camera = "fixed",
        speed: float = 1.0,
    ) -> None:
        self.physics = physics
        self.plot = plot
        self.recorder: Recorder | None = None
        self.samples: list[Sample] = []
        if record is not None:
            from sim.record import Recorder

            with physics.lock:
                self.recorder = Recorder(physics.world, record, camera=camera, speed=speed)

    def after_tick(self, cycle: int | None = None) -> None:
        """Sample (with ``--plot``) and capture a frame when one is due (with ``--record``)."""
        if self.plot is None and self.recorder is None:
            return
        from sim.record import sample_world

        with self.physics.lock:
            if self.plot is not None:
                self.samples.append(sample_world(self.physics.world))
            if self.recorder is not None and self.recorder.due():
                self.recorder.capture("" if cycle is None else f"cycle {cycle}")

    def finish(self, title: str, out: IO[str]) -> None:
        """Write the animation and the plot; say where they are."""
        if self.recorder is not None:
            if self.recorder.frame_count:
                out.write(f"animation: {self.recorder.save()} ({self.recorder.frame_count} frames)\n")
            else:
                self.recorder.abandon()
        if self.plot is not None and self.samples:
            from sim.record import plot_run

            names = list(self.physics.world.topology.names)
            out.write(f"plot: {plot_run(self.samples, self.plot, title=title, names=names)}\n")
