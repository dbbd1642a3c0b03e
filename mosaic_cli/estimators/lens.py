"""``--lens auto|none|FILE``: which lens a video is undistorted with, and ``auto``'s estimate.

``auto`` fits one coefficient of the division model (:func:`~mosaic_cli.geometry.lens.division_lens`:
radius r -> r / (1 + lambda r^2), r in half diagonals, centred) to the video itself.  A homography
maps one pinhole view of flat ground onto another exactly; through a lens it cannot, and the
misfit grows toward the corners and with the motion between the two frames.  So: frames sampled
across the video (decoded small, once), ORB matches between samples 1, 2 and 4 apart (pairs
that moved by 3-60% of the width), and a bounded 1-D search (scipy's ``minimize_scalar``) over
lambda for the smallest mean, over the pairs, of the mean reprojection error of each pair's
homography fitted to the undistorted matches.  The lens is applied only where that residual
improves on lambda = 0 by :data:`MIN_GAIN` or more and lambda is not negligible (the corner
displacement above :data:`MIN_CORNER_PX`); otherwise the video is taken as a pinhole's.
"""

from __future__ import annotations

import contextlib
import functools
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.geometry.lens import Lens, corner_displacement, division_lens, remap_frame, undistort_points
from mosaic_cli.geometry.lens_files import read_lens
from mosaic_cli.video import VideoInfo
from mosaic_cli.video.decode import frames_at, seen_through

SAMPLES = 24  # frames decoded for `auto`
SAMPLE_WIDTH = 640  # px: the matches' resolution
GAPS = (1, 2, 4, 8)  # pairs of samples this far apart
MIN_GAIN = 0.15  # the median residual must fall by this fraction over lambda = 0 ...
MIN_CORNER_PX = 0.5  # ... and the lens move the corners this far (px of the sample width) to be applied
CAP = 0.015  # a match's error counts up to this fraction of the width
LAMBDA_RANGE = (-0.7, 0.3)  # the search: a strong fisheye (corners 3.3x further out) to a mild pincushion


@dataclass
class LensChoice:
    """What ``--lens`` resolved to: the lens the frames are undistorted with (None: as they
    are), how it was chosen, and for ``auto`` the evidence (residuals in px at
    :data:`SAMPLE_WIDTH`, pairs used, seconds)."""

    lens: Lens | None
    source: str  # "none", "file" or "auto"
    estimate: Lens | None = None  # auto: the fitted lens, applied or not
    residual_none: float = 0.0
    residual_fit: float = 0.0
    pairs: int = 0
    seconds: float = 0.0

    def describe(self) -> str:
        """The final line's part: what was estimated and whether it was applied."""
        if self.source == "file":
            assert self.lens is not None
            return f"lens: {self.lens.model} from the file, frames undistorted"
        if self.source == "none":
            return "lens: none"
        if self.estimate is None:
            return f"lens: auto, too few matched pairs ({self.pairs}) to tell: taken as a pinhole"
        lam = self.estimate.coefficients[0]
        px = corner_displacement(self.estimate)
        said = (f"lens: auto, division lambda {lam:+.3f} (corners moved {px:.0f} px), residual "
                f"{self.residual_none:.2f} -> {self.residual_fit:.2f} px over {self.pairs} pairs")
        return said + (", frames undistorted" if self.lens is not None else ": a pinhole, left alone")

    def to_meta(self) -> dict:
        doc: dict = {"source": self.source, "applied": self.lens is not None}
        if self.lens is not None:
            doc["lens"] = self.lens.to_json()
        if self.source == "auto":
            doc.update(pairs=self.pairs, residual_none_px=self.residual_none, residual_fit_px=self.residual_fit, seconds=self.seconds)
            if self.estimate is not None:
                doc["estimate"] = self.estimate.to_json()
        return doc


def parse_lens_option(value: str | None) -> str | Path:
    """``--lens``: "auto", "none" or an existing FILE (read later, at the video's size)."""
    if value is None or value.strip().lower() in ("", "none"):
        return "none"
    if value.strip().lower() == "auto":
        return "auto"
    path = Path(value)
    if not path.is_file():
        raise BadInput(f"--lens must be auto, none or a lens file (mosaic, Gyroflow or OpenSfM JSON): no such file {value}")
    return path


def resolve_lens(value: str | None, video: str | Path, info: VideoInfo | None) -> LensChoice:
    """The lens ``--lens value`` asks for, for the video ``video`` (its probe ``info``).  A FILE is
    read and checked against the video's size; ``auto`` is estimated (:func:`estimate_lens`)."""
    spec = parse_lens_option(value)
    if spec == "none":
        return LensChoice(None, "none")
    if info is None:
        raise BadInput("--lens needs a video file or an image folder, not a live input")
    if spec == "auto":
        return estimate_lens(info)
    lens = read_lens(spec)
    try:
        lens.at(info.source_size)
    except ValueError as exc:
        raise BadInput(f"--lens {spec}: {exc}") from None
    return LensChoice(lens, "file")


def estimate_lens(info: VideoInfo, samples: int = SAMPLES) -> LensChoice:
    """``--lens auto`` (see the module doc)."""
    clock = time.perf_counter()
    total = info.frame_count or 0
    n = min(samples, total) if total else samples
    indices = sorted({int(round(v)) for v in np.linspace(0, max(total - 1, 0), n)}) if total else list(range(n))
    width = min(SAMPLE_WIDTH, info.source_size[0])
    frames = [cv2.cvtColor(np.asarray(f), cv2.COLOR_RGB2GRAY) for f in frames_at(info, indices, width)]
    if len(frames) < 2:
        return LensChoice(None, "auto", seconds=time.perf_counter() - clock)
    h, w = frames[0].shape
    pairs = _matched_pairs(frames, w)
    if len(pairs) < 3:
        return LensChoice(None, "auto", pairs=len(pairs), seconds=time.perf_counter() - clock)
    from scipy.optimize import minimize_scalar

    def cost(lam: float) -> float:
        return _residual(division_lens((w, h), lam), pairs)

    best = minimize_scalar(cost, bounds=LAMBDA_RANGE, method="bounded", options={"xatol": 1e-4})
    none, fit = cost(0.0), float(best.fun)
    estimate = division_lens((w, h), float(best.x))
    applied = fit < (1.0 - MIN_GAIN) * none and corner_displacement(estimate) > MIN_CORNER_PX
    return LensChoice(estimate if applied else None, "auto", estimate, none, fit, len(pairs), time.perf_counter() - clock)


def _matched_pairs(frames: list[np.ndarray], width: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """ORB matches (a (M, 2), b (M, 2)) between samples ``GAPS`` apart that moved 3-60% of the
    width, gross outliers dropped by a loose homography (a lens's misfit is well under its
    threshold, a wrong match is not)."""
    orb = cv2.ORB_create(nfeatures=1500, fastThreshold=10)
    feats = [orb.detectAndCompute(f, None) for f in frames]
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    pairs = []
    for gap in GAPS:
        for i in range(len(frames) - gap):
            (ka, da), (kb, db) = feats[i], feats[i + gap]
            if da is None or db is None or len(ka) < 50 or len(kb) < 50:
                continue
            m = matcher.match(da, db)
            if len(m) < 50:
                continue
            a = np.array([ka[x.queryIdx].pt for x in m], dtype=np.float64)
            b = np.array([kb[x.trainIdx].pt for x in m], dtype=np.float64)
            H, inl = cv2.findHomography(a, b, cv2.RANSAC, 0.03 * width)
            if H is None or inl.sum() < 40:
                continue
            keep = inl.ravel().astype(bool)
            shift = float(np.median(np.linalg.norm(a[keep] - b[keep], axis=1)))
            if not 0.03 * width <= shift <= 0.6 * width:
                continue
            # ORB's keypoints sit on its pyramid's coarse grid: the lens's misfit (a fraction of
            # a pixel away from the corners) needs sub-pixel matches, which LK gives, started
            # from ORB's homography and checked forward and back.
            p0 = cv2.goodFeaturesToTrack(frames[i], 1200, 0.005, 6)
            if p0 is None:
                continue
            guess = cv2.perspectiveTransform(p0.astype(np.float32), H)
            lk = {"winSize": (21, 21), "maxLevel": 2, "criteria": (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 0.01)}
            p1, ok, _ = cv2.calcOpticalFlowPyrLK(frames[i], frames[i + gap], p0.astype(np.float32), guess.copy(),
                                                 flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
            back, ok2, _ = cv2.calcOpticalFlowPyrLK(frames[i + gap], frames[i], p1, p0.astype(np.float32).copy(),
                                                    flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
            good = (ok.ravel() == 1) & (ok2.ravel() == 1) & (np.linalg.norm((back - p0).reshape(-1, 2), axis=1) < 0.3)
            a2, b2 = p0.reshape(-1, 2)[good].astype(np.float64), p1.reshape(-1, 2)[good].astype(np.float64)
            if len(a2) < 40:
                continue
            # gross outliers out (a lens's misfit stays well under the threshold)
            H2, inl2 = cv2.findHomography(a2, b2, cv2.RANSAC, 0.02 * width)
            if H2 is None or inl2.sum() < 40:
                continue
            keep = inl2.ravel().astype(bool)
            pairs.append((a2[keep], b2[keep]))
    return pairs


def _residual(lens: Lens, pairs: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """Mean over the pairs of the mean reprojection error (px, undistorted at the lens's own
    scale at the centre, each error capped at :data:`CAP` of the width) of each pair's
    homography fitted to its undistorted matches.  A mean, not a median: the lens's misfit
    lives in the frame's outer parts, which a median overlooks."""
    errors = []
    for a, b in pairs:
        ua, ub = undistort_points(lens, a, lens.K), undistort_points(lens, b, lens.K)
        cap = CAP * lens.size[0]
        H, _ = cv2.findHomography(ua, ub, cv2.RANSAC, cap)
        if H is None:
            continue
        proj = np.concatenate([ua, np.ones((len(ua), 1))], 1) @ H.T
        err = np.linalg.norm(proj[:, :2] / proj[:, 2:3] - ub, axis=1)
        errors.append(float(np.mean(np.minimum(err, cap))))
    return float(np.mean(errors)) if errors else float("inf")


@contextlib.contextmanager
def undistorting(value: str | None, video: str | Path, info: VideoInfo | None = None) -> Iterator[LensChoice]:
    """``--lens value`` resolved for ``video`` (probed here if ``info`` is None and a lens is
    asked for), and while inside, every read of ``video`` undistorted by it, once, where the
    frames are decoded (:func:`mosaic_cli.video.decode.seen_through`): the estimator, the
    stitcher and the renderer all see the pinhole view."""
    if parse_lens_option(value) != "none" and info is None:
        from mosaic_cli.video import probe

        info = probe(video)
    choice = resolve_lens(value, video, info)
    image_filter = None if choice.lens is None else functools.partial(remap_frame, lens=choice.lens)
    with seen_through(video, image_filter):
        yield choice
