"""A rolling-shutter video's row bands: their motion frame to frame, the readout, each band's
correction (``--rolling-shutter auto|off|R`` of stabilize, stitch and track).

1. measure: a pass over the video at ``TRACK_WIDTH`` px, gray: corners tracked frame to frame
   (pyramidal Lucas-Kanade, checked backwards, RANSAC homography inliers), and each row band's
   motion fitted to them (:func:`geometry.rolling_shutter.band_motion`);
2. readout: given, or ``auto`` (:func:`geometry.rolling_shutter.estimate_readout`; global-shutter
   footage reads under ``GLOBAL_READOUT`` and is left alone);
3. correct: each band's pose within its frame relative to the frame's mid-time pose
   (:func:`geometry.rolling_shutter.band_corrections`).

What each command does with them: stabilize/rolling.py (the per-row render), stitch/pipeline.py
(keyframes registered and drawn per row band), track.py (the track file's ``rolling_shutter``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Generator, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.geometry import resize_matrix
from mosaic_cli.geometry.rolling_shutter import band_corrections, estimate_readout, fit_bands
from mosaic_cli.progress import progress_task
from mosaic_cli.video import VideoInfo, open_video
from mosaic_cli.video.decode import ImageFilter, gray_at

BANDS = 16
TRACK_WIDTH = 640  # corners tracked at this width: finer than a band's wobble needs
CORNERS = 600  # 1200 cost twice the time (LK is most of this pass) for no better readout
MIN_TRACKS = 40  # a pair with fewer inliers is left out of the path (weight 0)
GLOBAL_READOUT = 0.1  # `auto` below this: global shutter, no correction
# `auto` reads the readout from the first pairs only; a global shutter costs no more than that
# (the whole video is measured only when there is a rolling shutter to take out, and the readout
# then read from all of it).  The probe only tells a rolling shutter from a global one: at 20
# frames readout 0 still costs 530-1360x the best on rolling-shutter flights (readout 0.5-0.9)
# and 1.0-2.8x on global-shutter ones (GLOBAL_COST_RATIO is 10), as at 60 (530-1320x, 1.0-1.9x),
# for a third of the cost (docs/measurements/rolling-shutter.md)
AUTO_PROBE_FRAMES = 20
# The probe rides on frames another pass decodes (RollingProbe: the tracking pass's, 320 px wide
# for the default estimator) and needs less than the measurement: with 200 corners at 320 px and
# readouts 0, 0.2, ..., 1 tried, readout 0 costs 60-299x the best on the rolling-shutter bench
# flights and 1.0-1.6x on the global-shutter ones (at ROUGHNESS 1e-4: 338-896x and 1.0-2.7x;
# 100 corners: 122-157x), for about 5 ms a pair and 13 ms for the readouts instead of 16 and 45.
PROBE_CORNERS = 200
PROBE_READOUTS = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)


def parse_rolling_shutter(value: str | float | None) -> str | float:
    """``off``, ``auto`` or a readout in [0, 1] (0 is off)."""
    if value is None:
        return "off"
    if isinstance(value, str):
        text = value.strip().lower()
        if text in ("off", "auto"):
            return text
        try:
            value = float(text)
        except ValueError:
            raise BadInput(f"--rolling-shutter must be auto, off or a readout in [0, 1], got {text!r}") from None
    if not 0.0 <= float(value) <= 1.0:
        raise BadInput(f"--rolling-shutter must be auto, off or a readout in [0, 1], got {value:g}")
    return "off" if float(value) == 0.0 else float(value)


def track_corners(a: np.ndarray, b: np.ndarray, corners: int = CORNERS) -> tuple[np.ndarray, np.ndarray]:
    """Corners of gray frame ``a`` tracked into ``b`` (forward-backward checked, RANSAC
    homography inliers): (P, 2) and (P, 2) in the frames' pixels."""
    pts = cv2.goodFeaturesToTrack(a, corners, 0.005, max(4, a.shape[1] // 80))
    if pts is None or len(pts) < 8:
        return np.zeros((0, 2)), np.zeros((0, 2))
    params = dict(winSize=(15, 15), maxLevel=3, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    fwd, ok1, _ = cv2.calcOpticalFlowPyrLK(a, b, pts, None, **params)
    back, ok2, _ = cv2.calcOpticalFlowPyrLK(b, a, fwd, None, **params)
    good = (ok1[:, 0] == 1) & (ok2[:, 0] == 1) & (np.linalg.norm((back - pts)[:, 0], axis=1) < 0.5)
    src, dst = pts[good, 0].astype(np.float64), fwd[good, 0].astype(np.float64)
    if len(src) < 8:
        return src, dst
    # a generous threshold: the rolling shutter's wobble is what a single homography misses
    _, inliers = cv2.findHomography(src, dst, cv2.RANSAC, 3.0)
    keep = inliers[:, 0].astype(bool) if inliers is not None else np.ones(len(src), bool)
    return src[keep], dst[keep]


def tracked_corners(video: str | Path, width: int = TRACK_WIDTH, info: VideoInfo | None = None,
                    lens: ImageFilter | None = None) -> Generator[tuple[np.ndarray, np.ndarray], None, None]:
    """For each frame pair t -> t+1 of ``video``, the corners tracked between them
    (:func:`track_corners`, frames decoded ``width`` wide and gray, through ``lens``: ``--lens``'s
    filter, as the tracking sees them): (M, 2) where they are in frame t and (M, 2) in frame t+1,
    in full-resolution pixels."""
    with open_video(video, width=width, gray=True, info=info, lens=lens) as frames:
        full = frames.info.source_size
        prev = None
        for frame in frames:
            if prev is not None:
                src, dst = track_corners(prev, frame)
                up = resize_matrix((frame.shape[1], frame.shape[0]), full)
                scale, shift = np.diag(up)[:2], up[:2, 2]
                yield src * scale + shift, dst * scale + shift
            prev = frame


@dataclass
class BandMotions:
    """Pairs' band motions as they are measured: each pair's (K, 4) motion (full-resolution
    pixels) and weight (1, or 0 where too few corners were tracked), and how many band fits were
    bridged (:func:`~mosaic_cli.geometry.rolling_shutter.fit_bands`)."""

    bands: int
    motion: list[np.ndarray] = field(default_factory=list)
    weights: list[float] = field(default_factory=list)
    bridged: int = 0

    def add(self, src: np.ndarray, dst: np.ndarray, full: tuple[int, int]) -> None:
        """Pair src -> dst (P, 2) full-resolution tracks."""
        if len(src) >= MIN_TRACKS:
            motion, bridged = fit_bands(src, dst, full, self.bands)
            self.motion.append(motion)
            self.weights.append(1.0)
            self.bridged += int(bridged.sum())
        else:
            self.motion.append(np.zeros((self.bands, 4)))
            self.weights.append(0.0)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(P, K, 4) the motions and (P,) the weights."""
        return np.array(self.motion).reshape(-1, self.bands, 4), np.array(self.weights)


def measure_band_motion(video: str | Path, info: VideoInfo, bands: int = BANDS, width: int = TRACK_WIDTH,
                        show_progress: bool = True, max_frames: int | None = None,
                        label: str = "rolling shutter", lens: ImageFilter | None = None) -> BandMotions:
    """Each row band's motion frame t -> t+1 in full-resolution pixels (:class:`BandMotions`), of
    the first ``max_frames`` frames only, if given; ``lens``: the frames' filter (``--lens``)."""
    full = info.source_size
    measured = BandMotions(bands)
    with progress_task(label, info.frame_count, disable=not show_progress) as advance:
        advance(1)  # the first frame makes no pair
        pairs = tracked_corners(video, min(width, full[0]), info, lens)
        for src, dst in pairs:
            measured.add(src, dst, full)
            advance(1)
            if max_frames is not None and len(measured.motion) + 1 >= max_frames:
                pairs.close()  # the decoder stops here
                break
    return measured


class RollingProbe:
    """`auto`'s probe on frames another pass decodes anyway (stabilize's and track's tracking
    pass): fed its gray frames as they come (:meth:`tap`), it tracks corners between consecutive
    ones (no wider than ``TRACK_WIDTH``; at the estimator's width when that is narrower) and
    fits each pair's band motion, for the first ``frames`` frames; :meth:`measured` waits for
    them.  No decoding of its own: what the separate probe pass cost was mostly its decoder."""

    def __init__(self, info: VideoInfo, frames: int = AUTO_PROBE_FRAMES, bands: int = BANDS):
        self.full, self.frames, self.bands = info.source_size, frames, bands
        self._measured = BandMotions(bands)
        self._prev: np.ndarray | None = None
        self._seen = 0
        self._done = threading.Event()
        self.seconds = 0.0  # spent tracking and fitting (in the caller's thread)
        self.cpu_seconds = 0.0  # the same in that thread's CPU time
        self.width = 0  # the width the corners were tracked at

    def push(self, frame: np.ndarray) -> None:
        """The next frame, gray or RGB, of any width (downscaled to ``TRACK_WIDTH`` if wider)."""
        if self._done.is_set():
            return
        clock, cpu = time.perf_counter(), time.thread_time()
        h, w = frame.shape[:2]
        small = gray_at(frame, (TRACK_WIDTH, max(1, round(h * TRACK_WIDTH / w))) if w > TRACK_WIDTH else (w, h))
        # Kept for the next pair: a copy, since the pass that decoded the frame may change it.
        frame = small.copy() if small is frame else small
        self.width = frame.shape[1]
        if self._prev is not None:
            src, dst = track_corners(self._prev, frame, PROBE_CORNERS)
            up = resize_matrix((frame.shape[1], frame.shape[0]), self.full)
            scale, shift = np.diag(up)[:2], up[:2, 2]
            self._measured.add(src * scale + shift, dst * scale + shift, self.full)
        self._prev = frame
        self._seen += 1
        self.seconds += time.perf_counter() - clock
        self.cpu_seconds += time.thread_time() - cpu
        if self._seen >= self.frames:
            self.finish()

    def finish(self) -> None:
        """No more frames (the stream ended, or failed): :meth:`measured` has what there is."""
        self._prev = None
        self._done.set()

    def restart(self) -> None:
        """Forget every frame pushed: the pass that fed them starts again from its first frame
        (an overlay found after tracking had started, :mod:`mosaic_cli.overlay.speculate`).  Only
        before anyone has read :meth:`measured`: the pass that feeds it holds back what would
        let a reader in (stabilize's render waits for the pass's pairs)."""
        self._measured = BandMotions(self.bands)
        self._prev = None
        self._seen = 0
        self._done.clear()
        self.seconds = self.cpu_seconds = 0.0  # the discarded pass's share is counted as the overlays'
        self.width = 0

    def tap(self, frames: Iterable[np.ndarray]) -> Iterator[np.ndarray]:
        """``frames``, each also pushed to the probe; the probe is finished when they end."""
        try:
            for frame in frames:
                self.push(frame)
                yield frame
        finally:
            self.finish()

    def measured(self, timeout: float | None = None) -> BandMotions:
        """The probed pairs' band motions, once the probe has its frames or the stream ended."""
        self._done.wait(timeout)
        return self._measured


@dataclass
class BandPlan:
    """What ``--rolling-shutter`` found: the readout, each band's correction to its frame's
    mid-time pose (N, K, 4), and the bands' pair motions it came from (N-1, K, 4) with each
    pair's weight (N-1,)."""

    readout: float
    corrections: np.ndarray
    motion: np.ndarray
    weights: np.ndarray
    estimated: bool  # auto, not given
    applied: bool = True  # False: `auto` read a global shutter (corrections all 0; motion: the probe's pairs only)
    bridged: int = 0  # band fits bridged over (too few tracks in the band: fit_bands)


def plan_bands(video: str | Path, info: VideoInfo, mode: str | float, show_progress: bool = True, label: str = "rolling shutter",
               max_frames: int | None = None, probe: RollingProbe | None = None, lens: ImageFilter | None = None) -> BandPlan | None:
    """The bands ``mode`` asks for (None: off, or too few frames to tell), of the first
    ``max_frames`` frames if given; under ``GLOBAL_READOUT`` `auto` returns them all 0, not applied.
    ``probe``: `auto`'s probe fed by a pass that decodes the frames anyway (waited for here);
    None: a pass of its own over the first ``AUTO_PROBE_FRAMES`` frames.  ``lens``: the frames'
    filter (``--lens``: the bands measured on the undistorted frames the tracking sees)."""
    if mode == "off":
        return None
    h = info.source_size[1]
    if mode == "auto":
        if probe is not None:
            probed = probe.measured()
        else:
            probe_frames = AUTO_PROBE_FRAMES if max_frames is None else min(AUTO_PROBE_FRAMES, max_frames)
            probed = measure_band_motion(video, info, show_progress=show_progress, max_frames=probe_frames, label=label, lens=lens)
        motion, weights = probed.arrays()
        if len(motion) < 2 or weights.sum() < 2:
            return None
        readout, _ = estimate_readout(motion, h, weights, PROBE_READOUTS)
        if readout < GLOBAL_READOUT:
            frames = max_frames or info.frame_count or len(motion) + 1
            return BandPlan(readout, np.zeros((frames, motion.shape[1], 4)), motion, weights, True, applied=False)
    measured = measure_band_motion(video, info, show_progress=show_progress, max_frames=max_frames, label=label, lens=lens)
    motion, weights = measured.arrays()
    if len(motion) < 2 or weights.sum() < 2:
        return None
    if mode == "auto":
        readout, _ = estimate_readout(motion, h, weights)  # from the whole video, now it is measured
    else:
        readout = float(mode)
    return BandPlan(readout, band_corrections(motion, readout, h, weights), motion, weights, mode == "auto",
                    bridged=measured.bridged)
