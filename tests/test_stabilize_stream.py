"""``stabilize`` plans its path while the video is tracked and renders alongside: the pieces
give what planning the whole clip at once gives, the render starts before the tracking ends,
and what goes wrong in the tracking thread reaches the user as it did in one thread.

Truth: ``fill_failed`` and one linear program over a short clip (``solve_window``), the plan of
a whole track made after the fact, and the shortfall of a file cut short."""

from __future__ import annotations

import json
from pathlib import Path

import av
import numpy as np
import pytest
from test_stabilize import FPS, SIZE, pairwise_of, shaky_path

from conftest import assert_one_line_error, ffmpeg, render, run_cli, textured_image, write_clip
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import make_estimator
from mosaic_cli.stabilize.crop import output_warps
from mosaic_cli.stabilize.path import camera_motion, fill_failed, motion_model
from mosaic_cli.stabilize.pipeline import WORK_WIDTH, StabilizeOptions
from mosaic_cli.stabilize.smoothing import L1Smoother, solve_window
from mosaic_cli.stabilize.stream import FailedPairFill, PathFeed
from mosaic_cli.track import track_video


def shaky_clip_with_sound(folder: Path, seed: int) -> Path:
    """60 frames of a shaky pan (320x180, 30 fps) over a procedural texture, with sound."""
    shaken, _ = shaky_path(60, seed=seed)
    texture = textured_image(700, 500, seed=seed)
    silent = write_clip(folder / "silent.mp4", [render(texture, np.linalg.inv(M), SIZE) for M in shaken], fps=FPS)
    clip = folder / "shaky.mp4"
    ffmpeg("-i", str(silent), "-f", "lavfi", "-i", "sine=frequency=440:duration=2", "-c:v", "copy", "-c:a", "aac",
           "-shortest", str(clip))
    return clip


@pytest.fixture(scope="module")
def shaky_clip(tmp_path_factory):
    return shaky_clip_with_sound(tmp_path_factory.mktemp("shaky"), seed=8)


def _fill_streamed(pairwise: np.ndarray, confidence: np.ndarray) -> np.ndarray:
    fill = FailedPairFill()
    out = [H for H, c in zip(pairwise, confidence) for H in fill.push(H, c)] + fill.finish()
    return np.array(out).reshape(-1, 3, 3)


@pytest.mark.parametrize("pattern", ["random", "none_fail", "all_fail", "tie", "fail_at_both_ends"])
def test_failed_pairs_take_the_same_neighbour_one_at_a_time(pattern):
    rng = np.random.default_rng(3)
    n = 40
    pairwise = np.tile(np.eye(3), (n, 1, 1))
    pairwise[:, 0, 2] = np.arange(n)  # each pair told apart by its shift
    confidence = {
        "random": (rng.random(n) > 0.4).astype(float),
        "none_fail": np.ones(n),
        "all_fail": np.zeros(n),
        "tie": np.array([1, 0, 0, 1] * 10, dtype=float),  # the failed pair between two: the earlier
        "fail_at_both_ends": np.r_[np.zeros(5), np.ones(30), np.zeros(5)],
    }[pattern]
    np.testing.assert_array_equal(_fill_streamed(pairwise, confidence), fill_failed(pairwise, confidence))


@pytest.fixture(scope="module")
def shaky_motion():
    shaken, _ = shaky_path(150, seed=5)
    model = motion_model("similarity")
    return np.concatenate([camera_motion(H[None], SIZE, model) for H in pairwise_of(shaken)]), model


@pytest.mark.slow
@pytest.mark.parametrize("crop", [None, 0.9])
def test_the_path_planned_as_pairs_arrive_is_the_whole_clips(shaky_motion, crop):
    motion, model = shaky_motion
    smoother = L1Smoother(window=60, overlap=20)  # half the default's: the same cases in half the frames
    whole = smoother.smooth(motion, SIZE, model, crop)
    rng = np.random.default_rng(1)
    for n_frames in (len(motion) + 1, 120, 61, 60, 19):  # the windows end with the clip, or not
        planner = smoother.planner(SIZE, model, crop)
        cuts = np.sort(rng.choice(np.arange(1, n_frames - 1), size=min(12, n_frames - 2), replace=False))
        parts = [planner.push(chunk) for chunk in np.split(motion[:n_frames - 1], cuts)] + [planner.finish()]
        views = np.concatenate(parts)
        assert len(views) == n_frames
        expected = whole if n_frames == len(whole) else smoother.smooth(motion[:n_frames - 1], SIZE, model, crop)
        np.testing.assert_array_equal(views, expected)
    # Shorter than a window: one linear program over the whole clip.
    short = motion[:18]
    single = model.matrices(solve_window(short, model, None, SIZE, crop, smoother))
    if crop is not None:
        from mosaic_cli.stabilize.crop import zoom_matrix

        single = single @ zoom_matrix(crop)
    np.testing.assert_allclose(smoother.smooth(short, SIZE, model, crop), single, atol=1e-12)


def test_the_first_views_settle_long_before_the_last_pair():
    shaken, _ = shaky_path(150, seed=6)
    smoother = L1Smoother(window=60, overlap=20)  # half the default's: the same in half the frames
    feed = PathFeed(SIZE, motion_model("similarity"), smoother, None)
    window, overlap = smoother.window, smoother.overlap
    for t, H in enumerate(pairwise_of(shaken)):
        feed.add_pair(H, 1.0)
        if t == window - 2:  # the first window's last pair: its first frames are settled
            assert len(feed.warps) == window - overlap
    assert len(feed.warps) < 150
    feed.finish()
    assert len(feed.warps) == 150
    assert np.array_equal(feed.warp(10_000), feed.warps[-1])  # a frame past the end: the last warp


@pytest.mark.slow
def test_stabilize_warps_are_those_of_its_track_planned_afterwards(tmp_path, capsys, shaky_clip):
    clip = shaky_clip
    out, warps_json = tmp_path / "s.mp4", tmp_path / "w.json"
    code, err = run_cli(capsys, "stabilize", clip, out, "--warps", warps_json, "-e", "orb", "--no-overlay-detect", "-q")
    assert code == 0, err
    estimator = make_estimator("orb", default_width=WORK_WIDTH)  # as stabilize makes it
    track = track_video(clip, estimator, show_progress=False)
    model = motion_model(StabilizeOptions().model)  # the default, as stabilize plans it
    motion = np.concatenate([camera_motion(H[None], SIZE, model) for H in fill_failed(track.pairwise, track.confidence)])
    expected = output_warps(L1Smoother().smooth(motion, SIZE, model, None), SIZE)
    np.testing.assert_allclose(np.array(json.loads(warps_json.read_text())["warps"]), expected, atol=1e-9)


def test_an_error_in_the_tracking_thread_is_one_line_and_leaves_no_file(tmp_path, capsys, shaky_clip, monkeypatch):
    import mosaic_cli.stabilize.pipeline as pipeline

    def failing_track(video, estimator, *, on_pair, **_):
        for _ in range(130):  # past the first window: the render is under way
            on_pair(np.eye(3), 1.0)
        raise BadInput(f"{video}: the tracking failed here")

    monkeypatch.setattr(pipeline, "track_video", failing_track)
    out = tmp_path / "s.mp4"
    code, err = run_cli(capsys, "stabilize", shaky_clip, out, "-e", "orb", "--no-overlay-detect", "-q")
    assert_one_line_error(code, err, "the tracking failed here")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_a_truncated_input_is_tagged_and_its_audio_cut_after_the_render(tmp_path, capsys, shaky_clip):
    """The render starts with the frame count the container announces; the tracking pass finds
    fewer, and the output is rewritten with the audio cut where the video ends and the tag."""
    clip = shaky_clip
    mkv = tmp_path / "whole.mkv"
    ffmpeg("-i", str(clip), "-c", "copy", str(mkv))
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(mkv.read_bytes()[: mkv.stat().st_size * 6 // 10])
    out = tmp_path / "out" / "s.mp4"
    out.parent.mkdir()
    code, err = run_cli(capsys, "stabilize", cut, out, "--warps", tmp_path / "w.json", "-e", "orb", "--no-overlay-detect", "-q")
    assert code == 0 and err.count("mosaic: warning: ") == 1, err
    frames = json.loads((tmp_path / "w.json").read_text())["frames"]
    assert frames < 60
    with av.open(str(out)) as container:
        assert "input truncated or damaged" in container.metadata.get("comment", "")
        video = sum(1 for _ in container.decode(video=0))
    with av.open(str(out)) as container:
        audio = container.streams.audio[0]
        end = max(float((p.pts + p.duration) * audio.time_base) for p in container.demux(audio) if p.pts is not None)
    assert video == frames
    assert end == pytest.approx(frames / 30.0, abs=0.05)
    assert sorted(p.name for p in out.parent.iterdir()) == ["s.mp4"]
