"""``stabilize --rolling-shutter auto|off|R``: take out the wobble a rolling shutter adds.

1. measure: a pass over the video at ``TRACK_WIDTH`` px, gray: corners tracked frame to frame
   (pyramidal Lucas-Kanade, checked backwards, RANSAC homography inliers), and each row band's
   motion fitted to them (:func:`geometry.rolling_shutter.band_motion`);
2. readout: given, or ``auto`` (:func:`geometry.rolling_shutter.estimate_readout`; global-shutter
   footage reads under ``GLOBAL_READOUT`` and is left alone);
3. correct: each band's pose within its frame relative to the frame's mid-time pose
   (:func:`geometry.rolling_shutter.band_corrections`); the renderer maps each output pixel back
   through the frame's stabilising warp, then through the correction of the input row it lands on.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.geometry import resize_matrix
from mosaic_cli.geometry.rolling_shutter import (
    band_blend,
    band_centres,
    band_corrections,
    band_motion,
    estimate_readout,
    similarity_matrix,
    undo_row_correction,
)
from mosaic_cli.progress import progress_task
from mosaic_cli.video import VideoInfo, open_video

BANDS = 16
TRACK_WIDTH = 640  # corners tracked at this width: finer than a band's wobble needs
CORNERS = 600  # 1200 cost twice the time (LK is most of this pass) for no better readout
MIN_TRACKS = 40  # a pair with fewer inliers is left out of the path (weight 0)
GLOBAL_READOUT = 0.1  # `auto` below this: global shutter, no correction
# `auto` reads the readout from the first pairs only; a global shutter costs no more than that
# (the whole video is measured only when there is a rolling shutter to take out, and the readout
# then read from all of it).  The probe only tells a rolling shutter from a global one: at 20
# frames readout 0 still costs 530-1360x the best on rolling-shutter flights (readout 0.5-0.9)
# and 1.0-2.8x on global-shutter ones (GLOBAL_COST_RATIO is 10), as at 60 (530-1290x, 1.0-1.9x),
# for a third of the cost (docs/measurements/rolling-shutter.md)
AUTO_PROBE_FRAMES = 20


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


def measure_band_motion(video: str | Path, info: VideoInfo, bands: int = BANDS, width: int = TRACK_WIDTH,
                        show_progress: bool = True, max_frames: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(N-1, K, 4) each row band's motion frame t -> t+1 in full-resolution pixels, and (N-1,)
    each pair's weight (1, or 0 where too few corners were tracked); of the first ``max_frames`` frames only, if given."""
    full = info.source_size
    width = min(width, full[0])
    motions: list[np.ndarray] = []
    weights: list[float] = []
    with open_video(video, width=width, gray=True, info=info) as frames, \
            progress_task("stabilize: rolling shutter", info.frame_count, disable=not show_progress) as advance:
        prev = None
        for frame in frames:
            if prev is not None:
                work = (frame.shape[1], frame.shape[0])
                src, dst = track_corners(prev, frame)
                up = resize_matrix(work, full)
                scale, shift = np.diag(up)[:2], up[:2, 2]
                if len(src) >= MIN_TRACKS:
                    motions.append(band_motion(src * scale + shift, dst * scale + shift, full, bands))
                    weights.append(1.0)
                else:
                    motions.append(np.zeros((bands, 4)))
                    weights.append(0.0)
            prev = frame
            advance(1)
            if max_frames is not None and len(motions) + 1 >= max_frames:
                break
    return np.array(motions).reshape(-1, bands, 4), np.array(weights)


@dataclass
class RollingCorrection:
    """Each band's correction to its frame's mid-time pose, (N, K, 4) channels."""

    readout: float
    corrections: np.ndarray
    size: tuple[int, int]
    estimated: bool  # auto, not given
    applied: bool = True  # False: `auto` read a global shutter (corrections all 0, frames rendered as without)

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


def plan_rolling(video: str | Path, info: VideoInfo, mode: str | float, show_progress: bool = True) -> RollingCorrection | None:
    """The corrections ``mode`` asks for (None: off, or too few frames to tell); under
    ``GLOBAL_READOUT`` `auto` returns them all 0, not applied."""
    if mode == "off":
        return None
    h = info.source_size[1]
    if mode == "auto":
        motion, weights = measure_band_motion(video, info, show_progress=show_progress, max_frames=AUTO_PROBE_FRAMES)
        if len(motion) < 2 or weights.sum() < 2:
            return None
        readout, _ = estimate_readout(motion, h, weights)
        if readout < GLOBAL_READOUT:
            return RollingCorrection(readout, np.zeros((info.frame_count or len(motion) + 1, motion.shape[1], 4)), info.source_size, True,
                                     applied=False)
    motion, weights = measure_band_motion(video, info, show_progress=show_progress)
    if len(motion) < 2 or weights.sum() < 2:
        return None
    if mode == "auto":
        readout, _ = estimate_readout(motion, h, weights)  # from the whole video, now it is measured
    else:
        readout = float(mode)
    return RollingCorrection(readout, band_corrections(motion, readout, h, weights), info.source_size, mode == "auto")
