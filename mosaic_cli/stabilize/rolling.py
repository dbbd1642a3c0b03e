"""``stabilize --rolling-shutter auto|off|R``: take out the wobble a rolling shutter adds.

The bands' motion, the readout and each band's correction to its frame's mid-time pose come from
:mod:`mosaic_cli.estimators.rolling` (shared with stitch and track); here the renderer maps each
output pixel back through the frame's stabilising warp, then through the correction of the input
row it lands on.  The path is planned from the same frames: each pair is told to the path
(:class:`MidTimeFeed`) as the motion between the two frames' mid-time poses (the bands' measured
motions moved by their rows' corrections: :meth:`RollingCorrection.pair_motion`), so that the
warp steadies the frame the rows are corrected to, not the raw one (whose one-homography fit
reads part of the rows' shear as rotation and their stretch as zoom: issue 41).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.estimators.rolling import (
    AUTO_PROBE_FRAMES,
    BANDS,
    GLOBAL_READOUT,
    TRACK_WIDTH,
    RollingProbe,
    measure_band_motion,
    parse_rolling_shutter,
    plan_bands,
    track_corners,
)
from mosaic_cli.geometry import project
from mosaic_cli.geometry.rolling_shutter import band_blend, band_centres, similarity_matrix, undo_row_correction
from mosaic_cli.stabilize.stream import WAIT_SLICE, Cancelled, PathFeed
from mosaic_cli.video import VideoInfo
from mosaic_cli.video.lens_filter import ImageFilter

__all__ = ["AUTO_PROBE_FRAMES", "BANDS", "GLOBAL_READOUT", "TRACK_WIDTH", "RollingCorrection", "MidTimeFeed", "RollingProbe", "RowWarpLater",
           "measure_band_motion", "parse_rolling_shutter", "bridged_bands", "plan_rolling", "track_corners"]


PAIR_GRID = 9  # points a side of the grid a pair's homography is refitted on (:meth:`RollingCorrection.mid_time_pair`)


@dataclass
class RollingCorrection:
    """Each band's correction to its frame's mid-time pose, (N, K, 4) channels."""

    readout: float
    corrections: np.ndarray
    size: tuple[int, int]
    estimated: bool  # auto, not given
    applied: bool = True  # False: `auto` read a global shutter (corrections all 0, frames rendered as without)
    # The measurement's pairs (None: not measured): (N-1, K, 4) the bands' motions and (N-1,) the
    # pairs' weights: the path's motion under a rolling shutter (:meth:`pair_motion`).
    motion: np.ndarray | None = None
    weights: np.ndarray | None = None
    bridged: int = 0  # band fits bridged over (too few tracks in the band)

    def row_channels(self, t: int, rows: np.ndarray) -> np.ndarray:
        """(R, 4) the correction of frame t at each of ``rows`` (bands blended as the truth's rule)."""
        C = self.corrections[min(t, len(self.corrections) - 1)]
        k, a = band_blend(rows, band_centres(self.size[1], len(C)))
        return (1.0 - a)[:, None] * C[k] + a[:, None] * C[np.minimum(k + 1, len(C) - 1)]

    def correct_points(self, t: int, points: np.ndarray) -> np.ndarray:
        """(P, 2) points of frame t (P, 2) moved by their row's correction to the frame's mid-time pose."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        S = similarity_matrix(self.row_channels(t, pts[:, 1]), self.size)  # (P, 3, 3)
        return np.einsum("pij,pj->pi", S[:, :2, :2], pts) + S[:, :2, 2]

    def mid_time_pair(self, t: int, H: np.ndarray) -> np.ndarray:
        """Pair t's homography ``H`` (frame t -> t+1, full-resolution pixels, fitted to the rows
        as exposed) as the motion from frame t's mid-time pose to frame t+1's: a grid of frame
        t's points and their images under ``H``, each moved by its row's correction, refitted."""
        w, h = self.size
        gx, gy = np.meshgrid(np.linspace(0.0, w - 1.0, PAIR_GRID), np.linspace(0.0, h - 1.0, PAIR_GRID))
        src = np.stack([gx.ravel(), gy.ravel()], 1)
        dst = project(np.asarray(H, dtype=np.float64), src)
        if not np.all(np.isfinite(dst)):
            return H
        M, _ = cv2.findHomography(self.correct_points(t, src), self.correct_points(t + 1, dst), 0)
        return H if M is None else M / M[2, 2]

    def pair_motion(self, t: int, H: np.ndarray) -> np.ndarray:
        """The motion from frame t's mid-time pose to frame t+1's that the path is planned from:
        points along each band's centre row moved by the band's measured motion, then both ends
        by their rows' corrections, refitted; where the pair was not measured, :meth:`mid_time_pair`
        of the estimator's ``H``.  Not the estimator's homography corrected: it is no fit of the
        rows' motion (the default estimator's, at 320 px, is 2.5 px RMS at the corners from the
        least-squares fit of the true rows' motion on a 0.7 readout, 10-25 Hz noise flight, and
        corrected still 2.5 px from the true mid-time motion; this, 0.13 px), nor is a least-squares
        homography of the measurement's corners (its affine and perspective parts beyond the
        similarity take up the rows' wobble: corrected, 1.3 px; docs/measurements/rolling-shutter.md).
        The bands are similarities: the pair's perspective is left out."""
        if self.motion is None or self.weights is None or t >= len(self.motion) or not self.weights[t] > 0:
            return self.mid_time_pair(t, H)
        w, h = self.size
        S = similarity_matrix(self.motion[t], self.size)  # (K, 3, 3)
        xs = np.linspace(0.0, w - 1.0, PAIR_GRID)
        src = np.stack(np.broadcast_arrays(xs[None, :], band_centres(h, len(S))[:, None]), -1)  # (K, X, 2)
        dst = np.einsum("kij,kxj->kxi", S[:, :2, :2], src) + S[:, None, :2, 2]
        M, _ = cv2.findHomography(self.correct_points(t, src.reshape(-1, 2)), self.correct_points(t + 1, dst.reshape(-1, 2)), 0)
        return self.mid_time_pair(t, H) if M is None else M / M[2, 2]

    def band_warps(self, warps: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(N, R, 3, 3) input -> output of the rows ``rows`` of each frame: the stabilising warp
        after the row's correction (for scoring against the ground truth's bands)."""
        return np.stack([warps[t] @ similarity_matrix(self.row_channels(t, rows), self.size) for t in range(len(warps))])

    def warper(self, border: int, black: tuple[int, int, int]) -> Callable[[np.ndarray, int, np.ndarray], np.ndarray]:
        """``warp(frame, t, warp)``: the output frame, per row, for RGB (h, w, 3) or yuv420p
        (h * 3 // 2, w) frames (``border``: an OpenCV border mode)."""
        w, h = self.size
        rows = np.arange(h, dtype=np.float64)

        def coords(t: int, warp: np.ndarray, grid_x: np.ndarray, grid_y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            """Input (x, y) of output points: back through the warp, then the row's correction undone."""
            Wi = np.linalg.inv(warp)
            z = Wi[2, 0] * grid_x + Wi[2, 1] * grid_y + Wi[2, 2]
            x = (Wi[0, 0] * grid_x + Wi[0, 1] * grid_y + Wi[0, 2]) / z
            y = (Wi[1, 0] * grid_x + Wi[1, 1] * grid_y + Wi[1, 2]) / z
            u, v = undo_row_correction(self.row_channels(t, rows).astype(np.float32), self.size, x, y)
            return u.astype(np.float32), v.astype(np.float32)

        cw, ch = w // 2, h // 2
        # The maps are smooth (a homography and corrections that vary over tens of rows): they are
        # computed on the chroma grid, whose pixel centres sit at luma x = 2 j + 0.5, and resized to
        # the luma grid (cv2.resize's convention is that very grid: exact but for the outermost
        # row and column, extrapolated flat, off by at most half the map's slope).
        cgx, cgy = np.meshgrid(np.arange(cw, dtype=np.float32) * 2 + 0.5, np.arange(ch, dtype=np.float32) * 2 + 0.5)

        def maps(t: int, warp: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
            u, v = coords(t, warp, cgx, cgy)
            full_u = cv2.resize(u, (w, h), interpolation=cv2.INTER_LINEAR)
            full_v = cv2.resize(v, (w, h), interpolation=cv2.INTER_LINEAR)
            return full_u, full_v, (u + 0.5) / 2 - 0.5, (v + 0.5) / 2 - 0.5

        def warp_frame(frame: np.ndarray, t: int, warp: np.ndarray) -> np.ndarray:
            u, v, cu, cv_ = maps(t, warp)
            if frame.ndim == 3:
                return cv2.remap(frame, u, v, cv2.INTER_LINEAR, borderMode=border, borderValue=(0, 0, 0))
            out = np.empty_like(frame)
            flat_in, flat_out = frame.reshape(-1), out.reshape(-1)
            flat_out[:w * h] = cv2.remap(flat_in[:w * h].reshape(h, w), u, v, cv2.INTER_LINEAR, borderMode=border,
                                         borderValue=black[0]).reshape(-1)
            q = cw * ch
            for i, start in enumerate((w * h, w * h + q)):
                plane = flat_in[start:start + q].reshape(ch, cw)
                flat_out[start:start + q] = cv2.remap(plane, cu, cv_, cv2.INTER_LINEAR, borderMode=border,
                                                      borderValue=black[1 + i]).reshape(-1)
            return out

        return warp_frame


def bridged_bands(count: int) -> str:
    """The summary's note of the band fits bridged over (nothing when none was)."""
    return f" ({count} band fits bridged over: too few tracks in the band)" if count else ""


def plan_rolling(video: str | Path, info: VideoInfo, mode: str | float, show_progress: bool = True,
                 label: str = "stabilize: rolling shutter", probe: RollingProbe | None = None,
                 lens: ImageFilter | None = None) -> RollingCorrection | None:
    """The corrections ``mode`` asks for (None: off, or too few frames to tell); under
    ``GLOBAL_READOUT`` `auto` returns them all 0, not applied (:func:`estimators.rolling.plan_bands`;
    ``probe``: `auto`'s, fed by another pass; ``lens``: the frames' filter, ``--lens``)."""
    plan = plan_bands(video, info, mode, show_progress, label, probe=probe, lens=lens)
    if plan is None:
        return None
    return RollingCorrection(plan.readout, plan.corrections, info.source_size, plan.estimated, plan.applied,
                             plan.motion, plan.weights, plan.bridged)


class RowWarpLater:
    """The render's ``per_row``, planned at the render's first frame rather than before the
    tracking pass starts: by then (the path's first window is solved after 120 pairs) `auto`'s
    probe, fed by the tracking pass (:class:`RollingProbe`), has its frames, so a global shutter
    costs no pass of its own; a rolling shutter (or a given readout) is then measured over the
    whole video beside the tracking.  Returns None for a frame rendered as without (a global shutter)."""

    def __init__(self, video: str | Path, info: VideoInfo, mode: str | float, border: int, black: tuple[int, int, int],
                 show_progress: bool = True, probe: RollingProbe | None = None, lens: ImageFilter | None = None):
        self.video, self.info, self.mode, self.border, self.black = video, info, mode, border, black
        self.show_progress, self.probe = show_progress, probe
        self.lens = lens  # --lens: the bands measured on the frames the tracking sees
        self.rolling: RollingCorrection | None = None
        self.seconds = 0.0  # planning in the render's thread, and the probe's share of the tracking's
        self.cpu_seconds = 0.0  # the same in CPU time
        self._planned = False
        self._warp: Callable[[np.ndarray, int, np.ndarray], np.ndarray] | None = None

    def plan(self) -> RollingCorrection | None:
        if not self._planned:
            clock, cpu = time.perf_counter(), time.thread_time()
            self._planned = True
            self.rolling = plan_rolling(self.video, self.info, self.mode, self.show_progress, probe=self.probe, lens=self.lens)
            if self.rolling is not None and self.rolling.applied:
                self._warp = self.rolling.warper(self.border, self.black)
            self.seconds = time.perf_counter() - clock + (self.probe.seconds if self.probe is not None else 0.0)
            self.cpu_seconds = time.thread_time() - cpu + (self.probe.cpu_seconds if self.probe is not None else 0.0)
        return self.rolling

    def __call__(self, frame: np.ndarray, t: int, warp: np.ndarray) -> np.ndarray | None:
        self.plan()
        return None if self._warp is None else self._warp(frame, t, warp)

    def correction(self) -> RollingCorrection | None:
        """The correction the frames are rendered with, row by row (a device's render warps with
        it); None for a global shutter (the usual warp)."""
        self.plan()
        return self.rolling if self._warp is not None else None


class MidTimeFeed:
    """The path's feed (:class:`~.stream.PathFeed`) behind a gate that tells it each pair as the
    motion between the frames' mid-time poses (:meth:`RollingCorrection.pair_motion`) once the
    rows' corrections are known, and as estimated where there are none (`auto` read a global
    shutter: bit-identical to ``off``).  The tracking pass's side (:meth:`add_pair`,
    :meth:`finish`, :meth:`fail`) never waits: pairs are held until the corrections are planned,
    which :meth:`warp` (the render's) does at its first frame, after the first pair is in (the
    overlays' mask then settled, so `auto`'s probe is fed for good)."""

    def __init__(self, feed: PathFeed, per_row: RowWarpLater):
        self.feed, self.per_row = feed, per_row
        self._lock = threading.Lock()
        self._started = threading.Event()  # a pair is in, or the pass ended or failed
        self._held: list[tuple[np.ndarray, float]] = []
        self._rolling: RollingCorrection | None = None
        self._ready = self._finished = self._failed = self._cancelled = False
        self._pairs = 0

    # -- the tracking side -------------------------------------------------------------------

    def add_pair(self, H: np.ndarray, confidence: float) -> None:
        if self._cancelled:
            raise Cancelled
        with self._lock:
            if self._ready:
                self._forward(H, confidence)
            else:
                self._held.append((np.asarray(H, dtype=np.float64), confidence))
        self._started.set()

    def finish(self) -> None:
        with self._lock:
            if self._ready:
                self.feed.finish()
            else:
                self._finished = True
        self._started.set()

    def fail(self, error: BaseException) -> None:
        self._failed = True
        self.feed.fail(error)
        self._started.set()

    # -- the render side ---------------------------------------------------------------------

    def settle(self) -> None:
        """The corrections planned (once the first pair is in) and the pairs held handed on."""
        if self._ready:
            return
        while not self._started.wait(WAIT_SLICE):
            pass
        if self._failed:
            return  # the feed raises the pass's error
        rolling = self.per_row.plan()
        with self._lock:
            self._rolling = rolling if rolling is not None and rolling.applied else None
            held, self._held = self._held, []
            for H, confidence in held:
                self._forward(H, confidence)
            self._ready = True
            if self._finished:
                self.feed.finish()

    def warp(self, t: int) -> np.ndarray:
        self.settle()
        return self.feed.warp(t)

    def cancel(self) -> None:
        self._cancelled = True
        self.feed.cancel()

    def _forward(self, H: np.ndarray, confidence: float) -> None:
        t, self._pairs = self._pairs, self._pairs + 1
        if self._rolling is not None and confidence > 0:
            H = self._rolling.pair_motion(t, H)
        self.feed.add_pair(H, confidence)
