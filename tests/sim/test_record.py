"""The recorder writes a real animated GIF and the plot a real PNG."""

from __future__ import annotations

from pathlib import Path

import pytest
from PIL import Image, ImageChops

from dh2rt.errors import RecordError
from dh2rt.topology import parse_spec
from sim.gaits import run_caterpillar
from sim.record import Recorder, plot_run
from sim.world import World


def test_recorder_writes_an_animated_gif(tmp_path: Path) -> None:
    out = tmp_path / "run" / "snake.gif"
    with World(parse_spec("snake:5")) as w, Recorder(w, out, fps=10, size=(160, 120)) as rec:
        rec.capture()
        run_caterpillar(w, 48, on_step=lambda c: rec.capture() if c % 6 == 5 else None)
        assert rec.frame_count == 9
        assert rec.steps_per_frame == 24
    with Image.open(out) as gif:
        assert gif.format == "GIF"
        assert gif.size == (160, 120)
        assert getattr(gif, "n_frames", 1) == 9
        gif.seek(0)
        first = gif.convert("RGB")
        extrema = first.getextrema()
        assert any(hi - lo > 40 for lo, hi in extrema)  # type: ignore[misc]  # not a blank frame: the robot is there
        gif.seek(8)
        last = gif.convert("RGB")
        assert ImageChops.difference(first, last).getbbox() is not None  # the robot moved


def test_plot_run_writes_a_png(tmp_path: Path) -> None:
    out = tmp_path / "run.png"
    with World(parse_spec("snake:3")) as w:
        samples = run_caterpillar(w, 40, sample=True)
    assert len(samples) == 40 and len(samples[0][1]) == 3
    plot_run(samples, out, title="snake:3")
    with Image.open(out) as png:
        assert png.format == "PNG"
        assert png.size == (800, 600)


def test_bad_recording_input_is_refused(tmp_path: Path) -> None:
    with pytest.raises(RecordError, match="no samples"):
        plot_run([], tmp_path / "x.png")
    with pytest.raises(RecordError, match="sample 1"):
        plot_run([(0.0, [(0.0, 0.0)], (0.0, 0.0, 0.0)), (0.1, [], (0.0, 0.0, 0.0))], tmp_path / "x.png")
    with World(parse_spec("snake:1")) as w:
        with pytest.raises(RecordError, match="fps"):
            Recorder(w, tmp_path / "x.gif", fps=0)
        rec = Recorder(w, tmp_path / "x.gif")
        with pytest.raises(RecordError, match="no frames"):
            rec.save()
