"""--plot on stabilize and track: the plotted series against known values, and the PNG written
from what the command computed."""

from __future__ import annotations

import json
import sys

import cv2
import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli
from mosaic_cli import plots
from mosaic_cli.plots import camera_path_series, crop_series


def translation(dx: float, dy: float) -> np.ndarray:
    return np.array([[1, 0, dx], [0, 1, dy], [0, 0, 1.0]])


def rotation(degrees: float, scale: float = 1.0) -> np.ndarray:
    c, s = scale * np.cos(np.radians(degrees)), scale * np.sin(np.radians(degrees))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_the_path_before_chains_the_motion_and_after_applies_the_views():
    motion = np.array([translation(0.01, -0.02)] * 4)
    before, after = camera_path_series(motion, np.array([np.eye(3)] * 5))
    np.testing.assert_allclose(before.x, [0, 0.01, 0.02, 0.03, 0.04])
    np.testing.assert_allclose(before.y, [0, -0.02, -0.04, -0.06, -0.08])
    np.testing.assert_allclose(after.x, before.x)  # views of the whole frame: the path unchanged
    # Views that undo the motion: a still camera after.
    undo = np.array([np.linalg.inv(translation(0.01 * t, -0.02 * t)) for t in range(5)])
    _, still = camera_path_series(motion, undo)
    np.testing.assert_allclose(still.x, 0, atol=1e-12)
    np.testing.assert_allclose(still.y, 0, atol=1e-12)
    turning, _ = camera_path_series(np.array([rotation(1.5, 1.01)] * 3), np.array([np.eye(3)] * 4))
    np.testing.assert_allclose(turning.rotation, [0, 1.5, 3.0, 4.5])
    np.testing.assert_allclose(turning.scale, [1, 1.01, 1.01**2, 1.01**3])


def test_the_crop_window_of_a_2x_zoom_keeps_half_the_width_about_the_centre():
    w, h = 320, 180
    zoom = translation(w / 2, h / 2) @ np.diag([2.0, 2.0, 1]) @ translation(-w / 2, -h / 2)  # input -> output
    crop = crop_series(np.array([np.eye(3), zoom]), (w, h))
    np.testing.assert_allclose(crop.kept, [1.0, 0.5])
    np.testing.assert_allclose(crop.centre_x, [w / 2, w / 2])
    np.testing.assert_allclose(crop.centre_y, [h / 2, h / 2])


def is_png_of_plausible_size(path) -> bool:
    image = cv2.imread(str(path))
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and image is not None and 300 < image.shape[0] < 2000 and 500 < image.shape[1] < 2000


@pytest.fixture
def shaky(tmp_path_factory, texture):
    """40 frames of a jittering pan, 160x120."""
    from conftest import write_clip

    jitter = np.random.default_rng(3).integers(-4, 5, 40)
    frames = [texture[200 + j:320 + j, 100 + 3 * k:260 + 3 * k] for k, j in enumerate(jitter)]
    return write_clip(tmp_path_factory.mktemp("plot") / "shaky.mp4", frames, fps=20)


@pytest.mark.slow
def test_stabilize_plot_draws_the_path_it_planned_and_the_crop_it_rendered(tmp_path, capsys, shaky, monkeypatch):
    drawn = {}
    original = plots.write_stabilize_plot

    def spy(path, before, after, crop, fps):
        drawn.update(before=before, after=after, crop=crop, fps=fps)
        original(path, before, after, crop, fps)

    monkeypatch.setattr(plots, "write_stabilize_plot", spy)
    out, plot, warps = tmp_path / "steady.mp4", tmp_path / "path.png", tmp_path / "warps.json"
    code, err = run_cli(capsys, "stabilize", shaky, out, "-e", "orb", "--plot", plot, "--warps", warps, "-q")
    assert code == 0, err
    assert is_png_of_plausible_size(plot)
    assert len(drawn["before"].x) == 40 and drawn["fps"] == pytest.approx(20)
    # The crop drawn is that of the warps written.
    written = np.array(json.loads(warps.read_text())["warps"])
    np.testing.assert_allclose(drawn["crop"].kept, crop_series(written, (160, 120)).kept, atol=1e-9)
    # The path after is the steadier: less frame-to-frame jitter than before.
    jitter = {k: np.abs(np.diff(drawn[k].y, 2)).mean() for k in ("before", "after")}
    assert jitter["after"] < 0.5 * jitter["before"]


def test_track_plot_draws_the_confidence_written(tmp_path, capsys, tiny_clip, monkeypatch):
    drawn = {}
    original = plots.write_track_plot

    def spy(path, confidence, fps, paths=None):
        drawn.update(confidence=np.array(confidence), fps=fps, paths=paths)
        original(path, confidence, fps, paths=paths)

    monkeypatch.setattr(plots, "write_track_plot", spy)
    out, plot = tmp_path / "t.json", tmp_path / "confidence.png"
    code, err = run_cli(capsys, "track", tiny_clip, "-o", out, "-e", "orb", "--plot", plot, "-q")
    assert code == 0, err
    assert is_png_of_plausible_size(plot)
    np.testing.assert_allclose(drawn["confidence"], json.loads(out.read_text())["confidence"])
    assert len(drawn["confidence"]) == 7 and drawn["fps"] == pytest.approx(10)


@pytest.mark.parametrize("command", ["track", "stabilize"])
def test_plot_without_matplotlib_is_one_line_before_any_work(tmp_path, capsys, tiny_clip, monkeypatch, command):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib raises ImportError
    out = tmp_path / ("t.json" if command == "track" else "s.mp4")
    args = ["-o", out] if command == "track" else [out]
    code, err = run_cli(capsys, command, tiny_clip, *args, "-e", "orb", "--plot", tmp_path / "p.png", "-q")
    assert_one_line_error(code, err, "--plot needs matplotlib", "pip install 'mosaic-cli[plot]'")
    assert not out.exists() and not (tmp_path / "p.png").exists()


def test_plot_must_be_a_png(tmp_path, capsys, tiny_clip):
    code, err = run_cli(capsys, "track", tiny_clip, "-o", tmp_path / "t.json", "--plot", tmp_path / "p.jpg", "-q")
    assert_one_line_error(code, err, "--plot", "must end in .png")


@pytest.mark.slow
def test_track_plot_draws_which_path_made_each_pair(tmp_path, capsys, monkeypatch):
    """The learned estimator's track names the path of every pair ("path" in the JSON, counted in
    meta.paths); the plot is given those very paths: here a black stretch in a pan, whose pairs
    the carried motion places."""
    from conftest import textured_image, write_clip

    tex = textured_image(800, 480, seed=11)
    frames = [tex[60 + 4 * t: 420 + 4 * t, 100 - 6 * t: 740 - 6 * t] for t in range(12)]
    frames[6] = np.zeros_like(frames[6])
    video = write_clip(tmp_path / "pan.mp4", frames)
    drawn = {}
    original = plots.write_track_plot

    def spy(path, confidence, fps, paths=None):
        drawn.update(paths=paths)
        original(path, confidence, fps, paths=paths)

    monkeypatch.setattr(plots, "write_track_plot", spy)
    out, plot = tmp_path / "t.json", tmp_path / "paths.png"
    code, err = run_cli(capsys, "track", video, "-o", out, "--plot", plot, "-q")
    assert code == 0, err
    data = json.loads(out.read_text())
    assert drawn["paths"] == data["path"] and len(data["path"]) == 11
    assert data["path"][5] == data["path"][6] == "carried"
    assert {k: data["path"].count(k) for k in set(data["path"])} == {k: v for k, v in data["meta"]["paths"].items() if v}
    assert is_png_of_plausible_size(plot)
