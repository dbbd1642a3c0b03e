"""Tracking that starts before overlay detection ends (mosaic_cli/overlay/speculate.py): with
no overlay, exactly the estimates of tracking after the mask; with one, a restart, and exactly
the results of the sequential order (the mask first) in track, stabilize and stitch; the
detection's and the build's errors as before; a failed render does not wait for the detection.

The detection is held until the tracking has estimated ``HELD`` pairs (:func:`held_detection`),
so that every run here takes the speculative path, with pairs held back when it settles."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import assert_one_line_error, overlay_flight_pair, run_cli
from mosaic_cli.errors import ProcessingError
from mosaic_cli.estimators import make_estimator
from mosaic_cli.overlay import MaskOptions, frame_mask, frame_mask_pending
from mosaic_cli.overlay import merge as overlay_merge
from mosaic_cli.overlay.speculate import Gate
from mosaic_cli.stabilize import StabilizeOptions, stabilize
from mosaic_cli.stitch import StitchOptions, stitch
from mosaic_cli.track import track_video

SIZE = (320, 180)
FRAMES = 30
HELD = 8  # pairs the tracking has estimated (and held back) when the detection begins


@pytest.fixture(scope="module")
def clips(tmp_path_factory) -> dict[str, Path]:
    """A fast flight, plain and with a logo, a timestamp and letterbox bars burned in."""
    plain, burned, _ = overlay_flight_pair(tmp_path_factory.mktemp("speculative"), FRAMES, SIZE, crf=16)
    return {"plain": plain, "burned": burned}


@pytest.fixture
def held_detection(monkeypatch) -> dict:
    """The pending detection (its thread's) starts only once the tracking has passed ``HELD``
    frames, and the tracking goes on only once it has ended: every run here settles its mask at
    frame ``HELD`` + 1, with ``HELD`` - 1 pairs held back (before the rolling-shutter probe has
    its 20 frames).  ``state["detected"]``: the detections run, pending or not."""
    state = {"detected": 0, "started": threading.Event()}
    real_frames, real_detect = Gate.frames, overlay_merge.detect_overlays

    def frames(self, items):
        for k, item in enumerate(real_frames(self, items)):
            if k + 1 == HELD and self.pending is not None:
                state["started"].set()
                deadline = time.monotonic() + 60
                while not self.pending.done() and time.monotonic() < deadline:
                    time.sleep(0.005)
            yield item

    def detect(*args, **kwargs):
        if threading.current_thread().name == "mosaic-overlays":  # a pending mask's, not frame_mask's
            assert state["started"].wait(60), "the tracking never started"
        state["detected"] += 1
        return real_detect(*args, **kwargs)

    monkeypatch.setattr(Gate, "frames", frames)
    monkeypatch.setattr(overlay_merge, "detect_overlays", detect)
    return state


def sequential(video: Path, estimator: str = "orb"):
    """Today's order: the mask first, then the tracking with it."""
    mask = frame_mask(video)
    est = make_estimator(estimator, device="cpu")
    est.set_mask(mask.use)
    return mask, track_video(video, est, show_progress=False)


def speculative(video: Path, estimator: str = "orb"):
    pending, est = frame_mask_pending(lambda: make_estimator(estimator, device="cpu"), video)
    with pending:
        result = track_video(video, est, show_progress=False, mask=pending)
    return pending.result(), result


def assert_same_track(a, b) -> None:
    assert np.array_equal(a.pairwise, b.pairwise)
    assert np.array_equal(a.confidence, b.confidence)
    assert a.paths == b.paths


def mask_file(folder: Path, use: np.ndarray | None) -> MaskOptions:
    """``use`` as a --mask file, detection off: the sequential order's mask, given at once."""
    if use is None:
        return MaskOptions(detect=False)
    path = folder / "detected.png"
    cv2.imwrite(str(path), use)
    return MaskOptions(file=path, detect=False, file_margin=0)


# -- track -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("estimator", ["orb", pytest.param("lstm", marks=pytest.mark.slow)])
def test_without_an_overlay_the_speculative_track_is_the_sequential_one(clips, held_detection, estimator):
    mask, expected = sequential(clips["plain"], estimator)
    assert mask.use is None
    settled, result = speculative(clips["plain"], estimator)
    assert settled.use is None and held_detection["detected"] == 2 and held_detection["started"].is_set()
    assert result.meta["overlay_restart"] is False
    assert_same_track(result, expected)


@pytest.mark.parametrize("estimator", ["orb", pytest.param("lstm", marks=pytest.mark.slow)])
def test_an_overlay_found_restarts_the_track_with_the_mask(clips, held_detection, estimator):
    from mosaic_cli.estimators.rolling import RollingProbe
    from mosaic_cli.video import probe as probe_video

    info = probe_video(clips["burned"])
    mask, expected = sequential(clips["burned"], estimator)
    assert mask.use is not None and mask.excluded > 0.1
    pending, est = frame_mask_pending(lambda: make_estimator(estimator, device="cpu"), clips["burned"])
    fed = RollingProbe(info)  # fed by the discarded pass too: it starts again with the kept one
    with pending:
        result = track_video(clips["burned"], est, show_progress=False, mask=pending, probe=fed)
    assert np.array_equal(pending.result().use, mask.use)
    assert result.meta["overlay_restart"] is True and result.meta["overlay_lost_seconds"] > 0
    assert_same_track(result, expected)
    fresh = RollingProbe(info)
    track_video(clips["burned"], make_estimator("orb"), show_progress=False, probe=fresh)
    for a, b in zip(fed.measured(0).arrays(), fresh.measured(0).arrays()):
        assert np.array_equal(a, b)
    # The check can fail: the pairs estimated before the overlays were known are not these.
    unmasked = track_video(clips["burned"], make_estimator(estimator, device="cpu"), show_progress=False, max_frames=HELD)
    assert not np.array_equal(unmasked.pairwise, expected.pairwise[:HELD - 1])


@pytest.mark.slow
def test_the_track_command_restarts_and_writes_the_sequential_track(clips, held_detection, tmp_path, capsys):
    _, expected = sequential(clips["burned"])
    out = tmp_path / "track.json"
    code, err = run_cli(capsys, "track", clips["burned"], "-o", out, "-e", "orb", "--rolling-shutter", "auto")
    assert code == 0, err
    doc = json.loads(out.read_text())
    assert np.array_equal(np.array(doc["pairwise"]), expected.pairwise)
    assert doc["confidence"] == expected.confidence.tolist()
    meta = doc["meta"]
    assert meta["overlay_restart"] is True and meta["mask"]["excluded"] > 0.1 and "rolling_shutter" in doc
    # The progress counts the kept pass's frames only: the discarded one's were held back.
    assert f"track (orb): {FRAMES}/{FRAMES} in" in err, err
    assert "(overlays " in err


# -- stabilize -------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("name,restart", [("plain", False), ("burned", True)])
def test_stabilize_warps_are_those_of_the_mask_given_first(clips, held_detection, tmp_path, name, restart):
    video = clips[name]
    result = stabilize(video, tmp_path / "spec.mp4", StabilizeOptions(estimator="orb", rolling_shutter="auto"),
                       show_progress=False)
    assert result.overlay_restart is restart
    given = mask_file(tmp_path, frame_mask(video).use)
    expected = stabilize(video, tmp_path / "seq.mp4", StabilizeOptions(estimator="orb", rolling_shutter="auto", mask=given),
                         show_progress=False)
    assert expected.overlay_restart is False
    assert np.array_equal(result.warps, expected.warps)
    assert result.rolling is not None and expected.rolling is not None
    assert result.rolling.readout == expected.rolling.readout
    if restart:  # the check can fail: the warps of the unmasked pairs are not these
        unmasked = stabilize(video, tmp_path / "raw.mp4", StabilizeOptions(estimator="orb", mask=MaskOptions(detect=False)),
                             show_progress=False)
        assert not np.array_equal(unmasked.warps, expected.warps)


# -- stitch ----------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("name,restart", [("plain", False), ("burned", True)])
def test_stitch_panorama_is_that_of_the_mask_given_first(clips, held_detection, tmp_path, monkeypatch, name, restart):
    import mosaic_cli.stitch.scan as stitch_scan

    probes = []  # each stitch's `auto` probe, fed by the scan (the discarded one's too)

    class Recorded(stitch_scan.RollingProbe):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            probes.append(self)

    monkeypatch.setattr(stitch_scan, "RollingProbe", Recorded)
    video = clips[name]
    spec = stitch(video, tmp_path / "spec.png", options=StitchOptions(estimator="orb", rolling_shutter="auto"),
                  show_progress=False)
    assert spec.overlay_restart is restart
    given = mask_file(tmp_path, frame_mask(video).use)
    seq = stitch(video, tmp_path / "seq.png", options=StitchOptions(estimator="orb", rolling_shutter="auto", mask=given),
                 show_progress=False)
    assert seq.overlay_restart is False
    assert [i for i, _ in spec.transforms] == [i for i, _ in seq.transforms]
    assert all(np.array_equal(a, b) for (_, a), (_, b) in zip(spec.transforms, seq.transforms))
    for a, b in zip(probes[0].measured(0).arrays(), probes[1].measured(0).arrays()):
        assert np.array_equal(a, b)
    a = cv2.imread(str(tmp_path / "spec.png"), cv2.IMREAD_UNCHANGED)
    b = cv2.imread(str(tmp_path / "seq.png"), cv2.IMREAD_UNCHANGED)
    assert a.shape == b.shape and np.array_equal(a, b)


def test_a_discarded_scan_drops_its_spilled_keyframes(clips, held_detection, tmp_path, monkeypatch):
    from mosaic_cli.stitch.keyframes import FlightScanner

    dropped: list[int] = []
    real = FlightScanner.discard

    def discard(self):
        held = [k.image.path for k in self.keyframes if k.image is not None]
        real(self)
        dropped.append(len(held))
        assert held and not any(path.exists() for path in held)

    monkeypatch.setattr(FlightScanner, "discard", discard)
    result = stitch(clips["burned"], tmp_path / "p.png", options=StitchOptions(estimator="orb"), show_progress=False)
    assert result.overlay_restart and dropped and dropped[0] > 0


# -- errors ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("command", ["track", "stabilize", "stitch"])
def test_a_detection_failure_while_tracking_is_the_one_error(clips, monkeypatch, tmp_path, capsys, command):
    """The detection fails once the tracking has started: its error, as the sequential order
    raised it, one line, no output."""
    started = threading.Event()
    real_frames = Gate.frames

    def frames(self, items):
        for item in real_frames(self, items):
            started.set()
            yield item

    def broken(*args, **kwargs):
        assert started.wait(60)
        raise ProcessingError("overlay detection failed: the samples broke")

    monkeypatch.setattr(Gate, "frames", frames)
    monkeypatch.setattr(overlay_merge, "detect_overlays", broken)
    out = tmp_path / {"track": "t.json", "stitch": "p.png", "stabilize": "s.mp4"}[command]
    args = [command, clips["plain"], out] if command == "stabilize" else [command, clips["plain"], "-o", out]
    code, err = run_cli(capsys, *args, "-e", "orb", "-q")
    assert_one_line_error(code, err, "overlay detection failed: the samples broke", status=ProcessingError.exit_code)
    assert started.is_set() and not out.exists()


def test_a_build_error_waits_for_the_detection_whose_error_comes_first(clips, monkeypatch):
    ended = threading.Event()
    real_detect = overlay_merge.detect_overlays

    def slow(*args, **kwargs):
        time.sleep(0.3)
        try:
            return real_detect(*args, **kwargs)
        finally:
            ended.set()

    def build():
        raise ValueError("no estimator")

    monkeypatch.setattr(overlay_merge, "detect_overlays", slow)
    with pytest.raises(ValueError, match="no estimator"):
        frame_mask_pending(build, clips["plain"])
    assert ended.is_set()  # raised once both had ended

    def broken(*args, **kwargs):
        time.sleep(0.3)
        raise ProcessingError("detection broke")

    monkeypatch.setattr(overlay_merge, "detect_overlays", broken)
    with pytest.raises(ProcessingError, match="detection broke"):
        frame_mask_pending(build, clips["plain"])


def test_a_failed_render_stops_the_detection_and_the_held_tracking(clips, monkeypatch, tmp_path):
    """The render fails while the tracking holds its pairs back and the detection is still
    reading: the render's error at once (not after the detection), no thread left behind."""
    from mosaic_cli.stabilize.render import Renderer

    tracked = threading.Event()
    real_frames = Gate.frames

    def frames(self, items):
        for item in real_frames(self, items):
            tracked.set()
            yield item

    def endless(frames, *args, **kwargs):  # a detection that reads on and on, a frame at a time
        while True:
            for _ in frames:
                time.sleep(0.02)

    def render(self, *args, **kwargs):
        assert tracked.wait(60)
        raise RuntimeError("the encoder broke")

    monkeypatch.setattr(Gate, "frames", frames)
    monkeypatch.setattr(overlay_merge, "detect_overlays", endless)
    monkeypatch.setattr(Renderer, "render", render)
    clock = time.perf_counter()
    with pytest.raises(RuntimeError, match="the encoder broke"):
        stabilize(clips["plain"], tmp_path / "s.mp4", StabilizeOptions(estimator="orb"), show_progress=False)
    assert time.perf_counter() - clock < 30
    alive = {t.name for t in threading.enumerate()}
    assert "mosaic-overlays" not in alive and "mosaic-track" not in alive
