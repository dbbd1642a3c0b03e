"""``stabilize`` decodes its input once, for the tracking and the render (stabilize/shared_decode.py).

Truth: ffmpeg's own gray decode (the tracking's frames of old), the two-decode path of old built
here from its parts (``track_video`` on a decode of its own, the path planned, ``Renderer.render``
on another), the decoders counted as they are made, the sequential order of the overlays (the
mask given first), and the frames of a file cut short.  The ring's bound is tried at its minimum
(an L1 window of 16 frames) on a clip six windows long."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import av
import cv2
import numpy as np
import pytest
from test_stabilize import FPS, SIZE, pairwise_of, shaky_path
from test_stabilize_stream import shaky_clip_with_sound

from conftest import ffmpeg, render, run_cli, textured_image, write_clip
from mosaic_cli.device import pair_threads
from mosaic_cli.estimators import estimate_stream, make_estimator
from mosaic_cli.geometry.homography import corner_error
from mosaic_cli.overlay import MaskOptions, frame_mask
from mosaic_cli.overlay import merge as overlay_merge
from mosaic_cli.simulate import OverlaySpec, plan_flight, procedural_map, write_flight
from mosaic_cli.stabilize import StabilizeOptions, pipeline, shared_decode, stabilize
from mosaic_cli.stabilize.path import motion_model
from mosaic_cli.stabilize.render import Renderer, warp_frame
from mosaic_cli.stabilize.shared_decode import SharedDecode, tracking_gray
from mosaic_cli.stabilize.smoothing import L1Smoother
from mosaic_cli.stabilize.stream import PathFeed
from mosaic_cli.track import track_video
from mosaic_cli.video import decode as video_decode
from mosaic_cli.video import open_video, probe

WINDOW, OVERLAP = 16, 4  # a small L1 window: the ring at its minimum is 16 frames
LONG = 96  # frames of the long clip: six windows


@pytest.fixture(scope="module")
def shaky_clip(tmp_path_factory) -> Path:
    return shaky_clip_with_sound(tmp_path_factory.mktemp("one_decode"), seed=11)


@pytest.fixture(scope="module")
def wide_clip(tmp_path_factory) -> Path:
    """40 frames of a shaky pan at 640x360: the default estimator reads it at half the width."""
    size = (640, 360)
    shaken, _ = shaky_path(40, seed=12, size=size)
    texture = textured_image(1400, 1000, seed=12)
    return write_clip(tmp_path_factory.mktemp("wide") / "wide.mp4", [render(texture, np.linalg.inv(M), size) for M in shaken], fps=FPS)


@pytest.fixture(scope="module")
def long_clip(tmp_path_factory) -> Path:
    """96 frames (six of the small windows) of a shaky pan, 320x180."""
    shaken, _ = shaky_path(LONG, seed=13)
    texture = textured_image(1100, 700, seed=13)
    return write_clip(tmp_path_factory.mktemp("long") / "long.mp4", [render(texture, np.linalg.inv(M), SIZE) for M in shaken], fps=FPS)


@pytest.fixture(scope="module")
def burned_clip(tmp_path_factory) -> Path:
    """A fast flight with a logo, a timestamp and letterbox bars burned in (320x180, 40 frames)."""
    ground = procedural_map((1024, 1024), seed=3)
    plan = plan_flight((1024, 1024), "fast", frames=40, size=SIZE, seed=3)
    path = tmp_path_factory.mktemp("burned") / "burned.mp4"
    write_flight(path, ground, plan, crf=16, preset="veryfast", show_progress=False, overlays=OverlaySpec.parse("all"))
    return path


@pytest.fixture
def decoders(monkeypatch) -> list[tuple[str, str, tuple[int, int]]]:
    """Every decoder of a whole stream made from now on (``open_video``'s: no picked frames, no
    seek), as (path, pixels, size)."""
    made: list[tuple[str, str, tuple[int, int]]] = []
    real = video_decode.Decoder

    def counting(info, pixels="rgb", size=None, **request):
        if not any(request.get(k) is not None for k in ("picks", "near_times", "seek", "select", "frames")):
            made.append((info.path, pixels, size or info.source_size))
        return real(info, pixels, size, **request)

    monkeypatch.setattr(video_decode, "Decoder", counting)
    return made


@pytest.fixture
def rings(monkeypatch) -> list[SharedDecode]:
    """Each stabilize run's shared decode, kept to be looked at after the run."""
    made: list[SharedDecode] = []

    class Kept(SharedDecode):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(self)

    monkeypatch.setattr(pipeline, "SharedDecode", Kept)
    return made


@pytest.fixture
def small_window(monkeypatch) -> None:
    """The L1 path in windows of ``WINDOW`` frames, and no room kept for failed pairs: the ring
    at the minimum the path needs (``ring_frames``: the window itself for ORB)."""
    real = pipeline.make_smoother
    monkeypatch.setattr(pipeline, "make_smoother",
                        lambda name, radius=30: L1Smoother(window=WINDOW, overlap=OVERLAP) if name == "l1" else real(name, radius))
    monkeypatch.setattr(shared_decode, "FAILED_RUN", 0)


def frames_of(path: Path) -> list[np.ndarray]:
    with open_video(path) as stream:
        return [np.asarray(f) for f in stream]


def audio_end(path: Path) -> float:
    with av.open(str(path)) as container:
        audio = container.streams.audio[0]
        return max(float((p.pts + p.duration) * audio.time_base) for p in container.demux(audio) if p.pts is not None)


def two_decodes(video: Path, out: Path, estimator: str, smoother: L1Smoother | None = None) -> np.ndarray:
    """The path of old, from its parts: the tracking on a decode of its own (small and gray), the
    path planned from its pairs, the render on a second decode; returns the warps."""
    info = probe(video)
    est = make_estimator(estimator, default_width=pipeline.WORK_WIDTH, device="cpu")  # as stabilize makes it
    options = StabilizeOptions()
    feed = PathFeed(info.source_size, motion_model(options.model), smoother or L1Smoother(), None)
    track_video(video, est, show_progress=False, info=info, on_pair=feed.add_pair)
    feed.finish()
    Renderer(border="replicate").render(video, out, feed.warps, info, show_progress=False, frames=info.frame_count)
    return feed.warps


# -- the tracking's frames ---------------------------------------------------------------------


def test_the_reduced_frame_is_ffmpegs_gray_at_full_size_and_within_a_level_scaled(wide_clip):
    info = probe(wide_clip)
    for width in (640, 320, 160):
        size = (width, round(360 * width / 640))
        with open_video(wide_clip, width=width, gray=True, info=info) as gray, open_video(wide_clip, yuv420p=True, info=info) as yuv:
            pairs = [(g, tracking_gray(f, info.source_size, size, True)) for g, f in zip(gray, yuv)]
        assert len(pairs) == 40
        diff = np.stack([np.abs(a.astype(int) - b.astype(int)) for a, b in pairs])
        if width == 640:
            assert diff.max() == 0  # BT.601 luma stretched to full range: ffmpeg's gray, bit for bit
        else:
            assert diff.max() <= 1 and diff.mean() < 0.5, (width, diff.max(), diff.mean())
    # RGB frames (odd sizes, folders): through their luma plane, the same pixels.
    with open_video(wide_clip, info=info) as rgb, open_video(wide_clip, yuv420p=True, info=info) as yuv:
        for f, y in zip(rgb, yuv):
            assert np.array_equal(tracking_gray(f, info.source_size, (320, 180), False),
                                  tracking_gray(y, info.source_size, (320, 180), True))


# -- the output: that of the two decodes, from one -----------------------------------------------


@pytest.mark.slow
def test_stabilize_decodes_once_and_writes_what_two_decodes_wrote(shaky_clip, tmp_path, decoders, rings):
    """At the estimator's full width the tracking's frames are those of old, bit for bit: so are
    the warps and the encoded frames; the audio is kept and cut as before."""
    result = stabilize(shaky_clip, tmp_path / "one.mp4", StabilizeOptions(estimator="orb"), warps_out=tmp_path / "w.json",
                       show_progress=False)
    ours = [d for d in decoders if Path(d[0]) == shaky_clip]
    assert ours == [(str(shaky_clip), "yuv420p", SIZE)], decoders  # one decode, for the tracking and the render
    assert rings[0].second_decode_from is None and 0 < rings[0].peak <= rings[0].capacity
    decoders.clear()
    warps = two_decodes(shaky_clip, tmp_path / "two.mp4", "orb")
    assert sorted(p for p, _, _ in decoders) == [str(shaky_clip)] * 2  # (the check can fail: the old path decodes twice)
    assert result.frames == 60
    np.testing.assert_allclose(result.warps, warps, atol=1e-9)
    one, two = frames_of(tmp_path / "one.mp4"), frames_of(tmp_path / "two.mp4")
    assert len(one) == len(two) == 60
    assert max(np.abs(a.astype(int) - b.astype(int)).mean() for a, b in zip(one, two)) == 0
    assert audio_end(tmp_path / "one.mp4") == audio_end(tmp_path / "two.mp4") == pytest.approx(60 / FPS, abs=0.05)


@pytest.mark.slow
def test_scaled_for_the_tracking_the_output_is_the_two_decodes_within_the_estimators_noise(wide_clip, tmp_path):
    """The default estimator at 320 px on a 640x360 clip: its frames here differ from ffmpeg's
    scaled gray by a level at most.  Its pairs move by less than its own error against the
    true motion, which stays as it was; the warps stay within a few tenths of a pixel (0.05 px
    at the corners, median, 0.19 px at most, measured), and the frames within the encoder's noise."""
    info = probe(wide_clip)
    est = make_estimator("lstm", device="cpu")
    size = (est.input_width, round(360 * est.input_width / 640))
    with open_video(wide_clip, width=est.input_width, gray=True, info=info) as gray:
        old_pairs = np.array([e.H for e in estimate_stream(est, gray, info.source_size)])
    with open_video(wide_clip, yuv420p=True, info=info) as yuv:
        new_pairs = np.array([e.H for e in estimate_stream(est, (tracking_gray(f, info.source_size, size, True) for f in yuv),
                                                           info.source_size)])
    truth = pairwise_of(shaky_path(40, seed=12, size=(640, 360))[0])
    moved, old_error = corner_error(new_pairs, old_pairs, (640, 360)), corner_error(old_pairs, truth, (640, 360))
    assert 0 < np.median(moved) < np.median(old_error), (np.median(moved), np.median(old_error))
    assert corner_error(new_pairs, truth, (640, 360)).mean() == pytest.approx(old_error.mean(), rel=0.1)

    result = stabilize(wide_clip, tmp_path / "one.mp4", StabilizeOptions(), show_progress=False)
    warps = two_decodes(wide_clip, tmp_path / "two.mp4", "lstm")
    shift = corner_error(result.warps, warps, (640, 360))
    assert np.median(shift) < 0.1 and shift.max() < 0.3, shift
    # The frames: apart by less than the encoder's own error (the decoded output of old against
    # its frames warped here, never encoded).
    one, two, source = frames_of(tmp_path / "one.mp4"), frames_of(tmp_path / "two.mp4"), frames_of(wide_clip)
    assert len(one) == len(two) == 40
    apart = np.mean([np.abs(a.astype(int) - b.astype(int)).mean() for a, b in zip(one, two)])
    encoder = np.mean([np.abs(b.astype(int) - warp_frame(f, W, (640, 360), "replicate")).mean() for b, f, W in zip(two, source, warps)])
    assert 0 < apart < encoder, (apart, encoder)


# -- the ring's bound --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def long_two_decodes(long_clip, tmp_path_factory) -> tuple[np.ndarray, list[np.ndarray]]:
    """The path of old on the long clip (ORB, the small window): its warps and frames, made once
    for the tests of the ring below, which each compare their own run with them."""
    out = tmp_path_factory.mktemp("long_two") / "two.mp4"
    warps = two_decodes(long_clip, out, "orb", L1Smoother(window=WINDOW, overlap=OVERLAP))
    return warps, frames_of(out)


@pytest.mark.slow
def test_the_ring_at_its_minimum_never_falls_short_on_a_long_clip(long_clip, long_two_decodes, tmp_path, small_window, rings,
                                                                  decoders):
    """Six windows at the ring's minimum (the window itself): the render never waits for a frame
    the ring had no room for, the ring never holds more than its bound, one decode."""
    result = stabilize(long_clip, tmp_path / "min.mp4", StabilizeOptions(estimator="orb", rolling_shutter="off"),
                       show_progress=False)
    ring = rings[0]
    assert ring.capacity == WINDOW
    assert ring.second_decode_from is None
    assert ring.peak == WINDOW  # full at times (the render waited for the path), never over
    assert [d for d in decoders if Path(d[0]) == long_clip] == [(str(long_clip), "yuv420p", SIZE)]
    warps, frames = long_two_decodes
    np.testing.assert_allclose(result.warps, warps, atol=1e-9)
    assert result.frames == LONG
    assert all(np.array_equal(a, b) for a, b in zip(frames_of(tmp_path / "min.mp4"), frames))


@pytest.mark.slow
@pytest.mark.parametrize("short_by", [1, 8])
def test_a_ring_below_the_minimum_hands_the_render_a_second_decode(long_clip, long_two_decodes, tmp_path, small_window, rings,
                                                                   decoders, monkeypatch, short_by):
    """Short of the window: the path needs a frame the ring has no room for; the decode goes on
    for the tracking alone, and the render reads the rest from a second decode, with the frames
    and warps of old."""
    monkeypatch.setattr(pipeline, "ring_frames", lambda *a, **k: WINDOW - short_by)
    result = stabilize(long_clip, tmp_path / "short.mp4", StabilizeOptions(estimator="orb", rolling_shutter="off"),
                       show_progress=False)
    ring = rings[0]
    assert ring.second_decode_from == WINDOW - short_by  # at the first window, the ring full when the render waited
    assert ring.peak <= ring.capacity + shared_decode.READ_AHEAD
    assert len([d for d in decoders if Path(d[0]) == long_clip]) == 2
    warps, frames = long_two_decodes
    np.testing.assert_allclose(result.warps, warps, atol=1e-9)
    assert result.frames == LONG
    assert all(np.array_equal(a, b) for a, b in zip(frames_of(tmp_path / "short.mp4"), frames))


def test_a_run_of_failed_pairs_longer_than_the_ring_does_not_stall(long_clip, tmp_path, small_window, rings):
    """Every pair failed (the identity estimator's confidence is 0): each waits for a success that
    never comes, until the end; the ring cannot hold that, and the render goes on regardless."""
    result = stabilize(long_clip, tmp_path / "id.mp4", StabilizeOptions(estimator="identity", rolling_shutter="off"),
                       show_progress=False)
    assert result.frames == LONG
    assert rings[0].second_decode_from == WINDOW
    warps = two_decodes(long_clip, tmp_path / "two.mp4", "identity", L1Smoother(window=WINDOW, overlap=OVERLAP))
    np.testing.assert_allclose(result.warps, warps, atol=1e-9)
    np.testing.assert_allclose(result.warps, np.repeat(np.eye(3)[None], LONG, axis=0), atol=1e-2)  # (no motion told)


@pytest.mark.parametrize("estimator", ["lstm"])
def test_a_learned_estimators_chunk_is_room_in_the_ring(long_clip, tmp_path, small_window, rings, estimator):
    """The network tells its pairs a chunk (16) at a time, and a chunk late (the tracking looks
    ahead on its pool of threads): the ring has room for the window and two chunks less one, and
    the render never falls short."""
    stabilize(long_clip, tmp_path / "net.mp4", StabilizeOptions(estimator=estimator, rolling_shutter="off"), show_progress=False)
    ring = rings[0]
    assert ring.capacity == WINDOW + (31 if pair_threads() > 1 else 15)
    assert ring.second_decode_from is None and ring.peak <= ring.capacity


def test_gaussian_smoothing_tracks_on_the_shared_decode_and_renders_on_its_own(shaky_clip, tmp_path, rings, decoders):
    """Its views all settle at the end: no ring, the render decodes the file itself."""
    result = stabilize(shaky_clip, tmp_path / "g.mp4", StabilizeOptions(estimator="orb", smoothing="gaussian"),
                       show_progress=False)
    assert rings[0].capacity == 0 and rings[0].second_decode_from == 0 and rings[0].peak <= shared_decode.READ_AHEAD
    assert [p for p, _, _ in decoders if Path(p) == shaky_clip] == [str(shaky_clip)] * 2
    assert result.frames == 60


# -- the overlays: a restart reads the ring again ---------------------------------------------


@pytest.fixture
def detection_after_a_full_ring(monkeypatch, rings) -> dict:
    """The pending overlay detection ends only once the tracking has read every frame the ring
    holds and waits for the next (the decode waiting for room): the tracking's wait must look at
    the detection, or nothing would move.  With no ring (gaussian): once it has read 8 frames."""
    state = {"waited": False}
    real = overlay_merge.detect_overlays

    def detect(*args, **kwargs):
        if threading.current_thread().name == "mosaic-overlays":
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                ring = rings[-1] if rings else None
                if ring is not None and ring.capacity and ring._decoded == ring.capacity == ring._tracked:
                    state["waited"] = True  # the ring full, the tracking waiting for a frame
                    break
                if ring is not None and not ring.capacity and ring._tracked >= 8:
                    break  # no ring: the tracking's frames are gone
                time.sleep(0.005)
        return real(*args, **kwargs)

    monkeypatch.setattr(overlay_merge, "detect_overlays", detect)
    return state


@pytest.mark.slow
@pytest.mark.parametrize("smoothing", ["l1", "gaussian"])
def test_an_overlay_found_midway_gives_the_output_of_the_mask_given_first(burned_clip, tmp_path, small_window, rings, decoders,
                                                                          detection_after_a_full_ring, smoothing):
    options = dict(estimator="orb", rolling_shutter="off", smoothing=smoothing)
    result = stabilize(burned_clip, tmp_path / "spec.mp4", StabilizeOptions(**options), show_progress=False)
    assert result.overlay_restart is True
    ring = rings[0]
    full = [d for d in decoders if Path(d[0]) == burned_clip]
    if smoothing == "l1":
        assert detection_after_a_full_ring["waited"]
        assert ring.second_decode_from is None and ring.peak == ring.capacity == WINDOW
        assert len(full) == 1  # the restart read the ring again
    else:  # nothing kept for the render: the tracking decodes again from the first frame
        assert len(full) == 3
    mask = frame_mask(burned_clip)
    assert mask.use is not None
    path = tmp_path / "detected.png"
    cv2.imwrite(str(path), mask.use)
    given = MaskOptions(file=path, detect=False, file_margin=0)
    expected = stabilize(burned_clip, tmp_path / "seq.mp4", StabilizeOptions(**options, mask=given), show_progress=False)
    assert expected.overlay_restart is False
    np.testing.assert_array_equal(result.warps, expected.warps)
    assert all(np.array_equal(a, b) for a, b in zip(frames_of(tmp_path / "spec.mp4"), frames_of(tmp_path / "seq.mp4")))
    if smoothing == "l1":  # the check can fail: the warps of the unmasked pairs are not these (the clip's, whatever the path)
        unmasked = stabilize(burned_clip, tmp_path / "raw.mp4", StabilizeOptions(**options, mask=MaskOptions(detect=False)),
                             show_progress=False)
        assert not np.array_equal(unmasked.warps, expected.warps)


# -- a truncated input -------------------------------------------------------------------------


def test_a_truncated_input_is_rendered_from_the_ring_as_far_as_it_decodes(shaky_clip, tmp_path, capsys, rings, decoders):
    mkv = tmp_path / "whole.mkv"
    ffmpeg("-i", str(shaky_clip), "-c", "copy", str(mkv))
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(mkv.read_bytes()[: mkv.stat().st_size * 6 // 10])
    out = tmp_path / "s.mp4"
    code, err = run_cli(capsys, "stabilize", cut, out, "--warps", tmp_path / "w.json", "-e", "orb", "--no-overlay-detect", "-q")
    assert code == 0 and err.count("mosaic: warning: ") == 1, err
    with open_video(cut) as stream:
        decoded = sum(1 for _ in stream)  # what the file decodes to, read here
    doc = json.loads((tmp_path / "w.json").read_text())
    assert doc["frames"] == decoded < 60 and doc["input"]["frames_decoded"] == decoded
    assert len(frames_of(out)) == decoded
    assert rings[0].second_decode_from is None
    assert [p for p, _, _ in decoders if Path(p) == cut] == [str(cut)] * 2  # the stabilize's one, and the count here
    with av.open(str(out)) as container:
        assert "input truncated or damaged" in container.metadata.get("comment", "")
