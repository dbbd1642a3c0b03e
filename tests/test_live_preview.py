"""``stitch --live --preview``: previews are drawn in a background thread, one at a time, from a
snapshot of the keyframes, and written atomically; the scan goes on meanwhile."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from mosaic_cli.errors import ProcessingError
from mosaic_cli.stitch.keyframes import Keyframe
from mosaic_cli.stitch.live import LivePreview, PreviewOptions

pytestmark = pytest.mark.alone  # wall-clock bounds: run with no other test beside it (conftest.py)

RUN_LIMIT = 300


def keyframes(n: int) -> list[Keyframe]:
    return [Keyframe(i, np.eye(3), None, None) for i in range(n)]  # type: ignore[arg-type]


class BlockedDraw:
    """Stands in for LivePreview.update: blocks until released, and counts the drawings at once."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.active = 0
        self.most = 0
        self.calls: list[int] = []

    def __call__(self, preview: LivePreview, shots: list[Keyframe]) -> None:
        self.active += 1
        self.most = max(self.most, self.active)
        self.calls.append(len(shots))
        self.release.wait(RUN_LIMIT)
        self.active -= 1


def test_a_preview_due_while_one_is_drawn_waits_and_the_scan_does_not(tmp_path, monkeypatch):
    draw = BlockedDraw()
    monkeypatch.setattr(LivePreview, "update", lambda self, shots: draw(self, shots))
    preview = LivePreview(PreviewOptions(tmp_path / "p.png", every=1e-6), (320, 180))
    assert preview.maybe_update(keyframes(1))  # started in the background: this call returned
    assert preview.busy
    for n in range(2, 6):  # more keyframes, due, but the first is still being drawn
        assert not preview.maybe_update(keyframes(n))
    draw.release.set()
    preview.wait()
    assert not preview.busy
    assert preview.maybe_update(keyframes(5))  # due again once written
    preview.finish(keyframes(6))  # waits for it, then the last one here
    assert draw.calls == [1, 5, 6] and draw.most == 1


def test_a_failed_preview_is_raised_in_the_scans_thread(tmp_path, monkeypatch):
    def fail(preview, shots):
        raise ProcessingError("p.png: OpenCV could not write the preview")

    monkeypatch.setattr(LivePreview, "update", fail)
    preview = LivePreview(PreviewOptions(tmp_path / "p.png", every=1e-6), (320, 180))
    assert preview.maybe_update(keyframes(1))
    with pytest.raises(ProcessingError, match="could not write the preview"):
        preview.wait()


@pytest.fixture(scope="module")
def survey(survey_320x180) -> Path:
    return survey_320x180  # (conftest: test_live streams the same flight)


@pytest.mark.slow
def test_previews_are_drawn_beside_the_scan_one_at_a_time_and_always_readable(tmp_path, survey, monkeypatch):
    from mosaic_cli.estimators import make_estimator
    from mosaic_cli.stitch import StitchOptions
    from mosaic_cli.stitch.live import stitch_live

    update = LivePreview.update
    spans: list[tuple[float, float]] = []
    active = [0, 0]  # now, most at once

    def slow_update(self, shots):
        active[0] += 1
        active[1] = max(active)
        start = time.monotonic()
        try:
            update(self, shots)
            if threading.current_thread() is not threading.main_thread():
                time.sleep(0.3)  # a slow preview: the scan must not wait for it
        finally:
            active[0] -= 1
            spans.append((start, time.monotonic()))

    monkeypatch.setattr(LivePreview, "update", slow_update)
    target = tmp_path / "preview.png"
    seen, done = [], threading.Event()

    def watch() -> None:  # a viewer reloading the preview never sees half an image
        while not done.is_set():
            if target.exists():
                seen.append(cv2.imread(str(target), cv2.IMREAD_UNCHANGED))
            time.sleep(0.01)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        result = stitch_live(str(survey), tmp_path / "pano.png", make_estimator("orb"), StitchOptions(),
                             preview=PreviewOptions(target, 0.01), show_progress=False)
    finally:
        done.set()
        watcher.join(RUN_LIMIT)
    assert active[1] == 1 and len(spans) >= result.previews >= 2
    assert seen and all(image is not None and image.shape[2] == 4 for image in seen)
    final = cv2.imread(str(target), cv2.IMREAD_UNCHANGED)
    assert final is not None and (final[..., 3] > 0).any()
    assert not list(tmp_path.glob(".*.part*"))
    # While the background previews were drawn, the scan went on.
    scanned = result.timeline.times("scanned")
    assert any(((scanned > a) & (scanned < b)).any() for a, b in spans[:-1])
