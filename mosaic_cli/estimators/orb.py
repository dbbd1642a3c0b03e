"""ORB features + robust homography fitting: the paper's classical baseline and mosaic's
fallback.  Features of the previous frame are kept, so each frame is described once.

Stages per frame pair: describe (ORB), match (ratio test), fit (USAC/RANSAC), refine
(Lucas-Kanade tracking of the inliers, or ECC alignment of the pixels, started from the
feature fit), score (confidence from the inliers).  The defaults were chosen by measurement; see
docs/measurements/estimators.md for the numbers and the commands that reproduce them.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np

from mosaic_cli.estimators.base import Estimator
from mosaic_cli.estimators.options import check_choices, option
from mosaic_cli.estimators.refine import PolishConfig, Polisher, align_pixels, erode_mask, track_points
from mosaic_cli.geometry import is_valid

ROBUST_METHODS = {"usac": cv2.USAC_MAGSAC, "ransac": cv2.RANSAC}


@dataclass
class OrbConfig:
    n_features: int = 500  # as many as the paper's baseline: with the LK polish, 1000 add cost, not accuracy
    fast_threshold: int = 10  # lower than OpenCV's 20: aerial ground is often weakly textured
    scale_factor: float = 1.2
    n_levels: int = 8
    ratio: float = 0.8  # Lowe's ratio test
    method: str = "usac"  # MAGSAC++: fewer failures than RANSAC on fast and shaky flights
    reproj_threshold: float = 1.5  # pixels at working resolution
    max_iters: int = 2000
    min_inliers: int = 12
    confident_inliers: int = 60  # inlier count at which confidence saturates
    # Keypoints are located to about a pixel, with errors that do not average out over a chain
    # of frames; "lk" (Lucas-Kanade tracking of the inliers) and "ecc" (direct alignment)
    # polish the fit to a small fraction of a pixel.  LK is both cheaper and more accurate.
    refine: Polisher | None = option("lk")  # -e orb:refine=VALUE, track --refine
    lk_window: int = 15  # Lucas-Kanade window (pixels at working resolution)
    lk_threshold: float = 0.5  # reprojection threshold of the refit on tracked points
    ecc_iterations: int = 20
    # A polished fit further than this (working pixels, at any corner) from the feature fit is
    # taken for a divergence and dropped.
    max_refine_shift: float = 2.0

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        # The method is the estimator's name (orb: usac, orb-ransac: ransac), never a user's value.
        if self.method not in ROBUST_METHODS:
            raise ValueError(f"method must be one of {', '.join(ROBUST_METHODS)}, got {self.method!r}")
        check_choices(self)

    @property
    def polish(self) -> PolishConfig:
        return PolishConfig(window=self.lk_window, levels=1, threshold=self.lk_threshold, max_iters=self.max_iters,
                            min_inliers=self.min_inliers, ecc_iterations=self.ecc_iterations, max_shift=self.max_refine_shift)


class OrbEstimator(Estimator):
    name = "orb"

    def __init__(self, work_width: int = 320, config: OrbConfig | None = None):
        super().__init__(work_width)
        self.config = config or OrbConfig()
        # The learned estimator calls ``features_of`` and ``register`` from the threads of its pool:
        # each thread has a detector and a matcher of its own (same settings, same results), so
        # no OpenCV object is shared between threads.  Nothing else here changes after ``reset``.
        self._per_thread = threading.local()
        self._prev_features = None

    def _tools(self) -> tuple[cv2.ORB, cv2.DescriptorMatcher]:
        """This thread's ORB detector and matcher, made at its first call."""
        tools = getattr(self._per_thread, "tools", None)
        if tools is None:
            c = self.config
            orb = cv2.ORB_create(nfeatures=c.n_features, scaleFactor=c.scale_factor, nlevels=c.n_levels,
                                 fastThreshold=c.fast_threshold, edgeThreshold=15, patchSize=15)
            tools = self._per_thread.tools = (orb, cv2.BFMatcher(cv2.NORM_HAMMING))
        return tools

    @property
    def _orb(self) -> cv2.ORB:
        """This thread's ORB detector."""
        return self._tools()[0]

    def reset(self, full_size):
        super().reset(full_size)
        self._prev_features = None
        # Keypoints whose descriptor patch would reach a masked pixel are not detected.
        self._detect_mask = None if self.work_mask is None else erode_mask(self.work_mask, self._orb.getPatchSize() // 2 + 1)

    def features_of(self, gray: np.ndarray):
        keypoints, descriptors = self._orb.detectAndCompute(gray, self._detect_mask)
        points = np.array([k.pt for k in keypoints], np.float32) if keypoints else np.zeros((0, 2), np.float32)
        return points, descriptors

    def _estimate(self, prev: np.ndarray, cur: np.ndarray):
        if self._prev_features is None:
            self._prev_features = self.features_of(prev)
        cur_features = self.features_of(cur)
        prev_features, self._prev_features = self._prev_features, cur_features
        return self.register(prev, cur, prev_features, cur_features)

    def register(self, prev: np.ndarray, cur: np.ndarray, prev_features=None, cur_features=None):
        """Homography prev -> cur of two working-size gray frames, not necessarily consecutive
        (the learned estimator's fallback), from their features (described here when not given)."""
        prev_pts, prev_desc = prev_features if prev_features is not None else self.features_of(prev)
        cur_pts, cur_desc = cur_features if cur_features is not None else self.features_of(cur)
        H, confidence, src = fit_homography(prev_pts, prev_desc, cur_pts, cur_desc, self._tools()[1], self.config, self.work_size)
        if H is not None and self.config.refine == "ecc":
            H = align_pixels(prev, cur, H, self.config.polish, self.work_mask).H
        elif H is not None and self.config.refine == "lk":
            H = track_points(prev, cur, H, src, self.config.polish, self.work_mask).H
        return H, confidence


def fit_homography(prev_pts, prev_desc, cur_pts, cur_desc, matcher, config: OrbConfig, size):
    """Ratio-test matches, then a robust fit: (H, confidence, inlier points of prev), or
    (None, 0, None) when anything is insufficient."""
    c = config
    if prev_desc is None or cur_desc is None or len(prev_pts) < c.min_inliers or len(cur_pts) < c.min_inliers:
        return None, 0.0, None
    pairs = matcher.knnMatch(prev_desc, cur_desc, k=2)
    good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < c.ratio * m[1].distance]
    if len(good) < c.min_inliers:
        return None, 0.0, None
    src = prev_pts[[m.queryIdx for m in good]]
    dst = cur_pts[[m.trainIdx for m in good]]
    try:
        H, mask = cv2.findHomography(src, dst, ROBUST_METHODS[c.method], c.reproj_threshold, maxIters=c.max_iters, confidence=0.999)
    except cv2.error:  # degenerate point sets (all collinear, all equal)
        return None, 0.0, None
    if H is None or mask is None:
        return None, 0.0, None
    inliers = int(mask.sum())
    if inliers < c.min_inliers or not is_valid(H, size, max_area_ratio=2.0):
        return None, 0.0, None
    confidence = min(1.0, inliers / c.confident_inliers) * np.sqrt(inliers / len(good))
    return H, confidence, src[mask.ravel() > 0]
