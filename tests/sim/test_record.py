"""The recorder streams a real animated GIF whose fixed camera shows the robot moving over a
checkered floor; the plot has its panels, the joint pictures one row per module."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from dh2rt.errors import RecordError
from dh2rt.topology import parse_spec
from sim.gaits import run_caterpillar
from sim.gif import GifStream
from sim.plot import PANELS, plot_figure, plot_run
from sim.record import Recorder, head_modules, sample_world
from sim.world import World


def _frames(path: Path) -> list[Image.Image]:
    out = []
    with Image.open(path) as gif:
        for i in range(getattr(gif, "n_frames", 1)):
            gif.seek(i)
            out.append(gif.convert("RGB"))
    return out


def _robot_pixels(frame: Image.Image) -> tuple[float, float, int]:
    """Centroid (x, y) and count of the robot's saturated pixels (the floor and captions are grey)."""
    a = np.asarray(frame).astype(int)
    chroma = a.max(axis=2) - a.min(axis=2)
    ys, xs = np.nonzero(chroma > 60)
    return float(xs.mean()), float(ys.mean()), len(xs)


def test_fixed_camera_shows_the_robot_move_across_the_frames(tmp_path: Path) -> None:
    out = tmp_path / "run" / "snake.gif"
    with World(parse_spec("snake:5")) as w, Recorder(w, out, fps=10, size=(160, 120), speed=4.0) as rec:
        assert rec.steps_per_frame == 96
        rec.capture("cycle 0")
        # 10 gait periods of 1.6 s: about 70 cm forward
        run_caterpillar(w, 320, on_step=lambda c: rec.capture(f"cycle {c + 1}") if rec.due() else None)
        assert rec.frame_count == 41
    frames = _frames(out)
    assert frames[0].size == (160, 120)
    # identical frames are merged into one longer frame, never dropped: total duration counts them all
    with Image.open(out) as gif:
        total = 0
        for i in range(getattr(gif, "n_frames", 1)):
            gif.seek(i)
            total += gif.info["duration"]
    assert total == 41 * 100
    xs = [_robot_pixels(f)[0] for f in frames]
    # forward is to the right of a fixed camera: the robot's pixels move right by a clear margin
    # (until the camera jumps after it, at most once or twice over 70 cm)
    jumps = sum(1 for a, b in itertools.pairwise(xs) if b < a - 20)
    assert jumps <= 2
    assert max(xs) - xs[0] > 25


def test_follow_camera_keeps_the_robot_in_the_middle(tmp_path: Path) -> None:
    out = tmp_path / "follow.gif"
    with World(parse_spec("snake:5")) as w, Recorder(w, out, size=(160, 120), camera="follow", speed=4.0) as rec:
        rec.capture()
        run_caterpillar(w, 160, on_step=lambda c: rec.capture() if rec.due() else None)
    xs = [_robot_pixels(f)[0] for f in _frames(out)]
    assert max(abs(x - 80) for x in xs) < 30


def test_floor_checker_is_fixed_to_the_world_and_the_physics_unchanged(tmp_path: Path) -> None:
    # recording adds nothing to the world: the same run with and without it ends at the same place
    with World(parse_spec("snake:4")) as w:
        run_caterpillar(w, 64)
        plain = w.centroid()
    with World(parse_spec("snake:4")) as w, Recorder(w, tmp_path / "a.gif", size=(96, 72)) as rec:
        run_caterpillar(w, 64, on_step=lambda c: rec.capture() if rec.due() else None)
        recorded = w.centroid()
    assert plain == recorded
    # the floor is checkered: many grey levels' worth of edges, not one flat colour
    first = np.asarray(_frames(tmp_path / "a.gif")[0]).astype(int)
    grey = first[-20:, :, 1]  # the bottom rows: floor in front of the robot
    assert grey.max() - grey.min() > 15


def test_head_is_the_front_free_module_of_each_piece() -> None:
    with World(parse_spec("snake:4")) as w:
        assert head_modules(w) == [0]
        w.undock(1, 2)  # module 1's back: two pieces, heads 0 and 2
        assert head_modules(w) == [0, 2]
        s = sample_world(w)
        assert len(s) == 5 and len(s[1]) == 4
        assert s[3] == w.module_position(0)
        # the snake is built along +x, module 0 in front: its yaw is 0
        assert abs(s[4]) < 1.0


def test_plot_has_path_heading_and_module_by_time_pictures(tmp_path: Path) -> None:
    with World(parse_spec("snake:6")) as w:
        samples = []
        run_caterpillar(w, 80, on_step=lambda c: samples.append(sample_world(w)))
    names = [f"m{i}" for i in range(6)]
    fig = plot_figure(samples, title="snake:6", names=names)
    titled = {ax.get_title(): ax for ax in fig.axes if ax.get_title()}
    assert set(PANELS) <= set(titled)
    path = titled["path"]
    centroid = next(ln for ln in path.get_lines() if ln.get_label() == "centroid")
    xdata: list[float] = np.asarray(centroid.get_xdata(), dtype=np.float64).tolist()
    assert len(xdata) == 80 and xdata[0] == 0.0
    assert xdata[-1] > 2.0  # cm: the caterpillar moved along +x
    assert any(ln.get_label() == "head" for ln in path.get_lines())
    assert titled["heading and travel"].get_ylabel().startswith("head heading")
    for panel, dof in (("DOF1 (pitch)", 0), ("DOF2 (yaw)", 1)):
        ax = titled[panel]
        (image,) = ax.get_images()
        rows = np.asarray(image.get_array())
        assert rows.shape == (6, 80)  # one row per module, one column per sample
        for m in range(6):
            assert list(rows[m]) == [s[1][m][dof] for s in samples]
        assert [t.get_text() for t in ax.get_yticklabels()] == names
    # the travelling wave: each module's pitch lags the one before it
    pitch = np.asarray(titled["DOF1 (pitch)"].get_images()[0].get_array())
    assert not np.array_equal(pitch[0], pitch[1])
    out = plot_run(samples, tmp_path / "p" / "run.png", title="snake:6", names=names)
    with Image.open(out) as png:
        assert png.format == "PNG" and png.size == (1000, 900)


def test_plot_takes_samples_without_the_head(tmp_path: Path) -> None:
    with World(parse_spec("snake:3")) as w:
        samples = run_caterpillar(w, 40, sample=True)
    fig = plot_figure(samples)
    titles = [ax.get_title() for ax in fig.axes]
    assert "path" in titles and "DOF1 (pitch)" in titles
    assert plot_run(samples, tmp_path / "x.png").exists()


def test_bad_recording_input_is_refused(tmp_path: Path) -> None:
    with pytest.raises(RecordError, match="no samples"):
        plot_run([], tmp_path / "x.png")
    with pytest.raises(RecordError, match="sample 1"):
        plot_run([(0.0, [(0.0, 0.0)], (0.0, 0.0, 0.0)), (0.1, [], (0.0, 0.0, 0.0))], tmp_path / "x.png")
    with pytest.raises(RecordError, match="2 module names for 1"):
        plot_figure([(0.0, [(0.0, 0.0)], (0.0, 0.0, 0.0))], names=["a", "b"])
    with World(parse_spec("snake:1")) as w:
        with pytest.raises(RecordError, match="fps"):
            Recorder(w, tmp_path / "x.gif", fps=0)
        with pytest.raises(RecordError, match="camera"):
            Recorder(w, tmp_path / "x.gif", camera="orbit")  # type: ignore[arg-type]
        with pytest.raises(RecordError, match="speed"):
            Recorder(w, tmp_path / "x.gif", speed=math.inf)
        rec = Recorder(w, tmp_path / "x.gif")
        with pytest.raises(RecordError, match="no frames"):
            rec.save()
        with pytest.raises(RuntimeError), Recorder(w, tmp_path / "y.gif") as rec2:
            rec2.capture()
            raise RuntimeError("the run failed")
        assert not (tmp_path / "y.gif").exists()  # a failed run leaves no half-written GIF


def test_gif_stream_round_trips_frames_exactly(tmp_path: Path) -> None:
    """Frames that fit the palette come back pixel for pixel, changed rectangles and all."""
    rng = np.random.default_rng(3)
    colours = rng.integers(0, 256, size=(8, 3))
    frames = []
    base = colours[rng.integers(0, 8, size=(30, 40))]
    for k in range(6):
        img = base.copy()
        if k % 2:
            img[5 + k : 12 + k, 7:19] = colours[(k + 1) % 8]  # a small change
        frames.append(Image.fromarray(img.astype(np.uint8)))
    frames.insert(3, frames[2].copy())  # a repeat: merged into a longer frame
    gif = GifStream(tmp_path / "s.gif", (40, 30), 100, colors=8)
    for f in frames:
        gif.add(f)
    gif.close()
    back = _frames(tmp_path / "s.gif")
    assert len(back) == len(frames) - 1
    expected = frames[:3] + frames[4:]
    for got, want in zip(back, expected, strict=True):
        assert np.array_equal(np.asarray(got), np.asarray(want))
    with pytest.raises(RecordError, match="frame of"):
        GifStream(tmp_path / "t.gif", (40, 30), 100).add(Image.new("RGB", (10, 10)))
