"""ORB features + robust homography fitting: the paper's classical baseline and mosaic's
fallback.  Features of the previous frame are kept, so each frame is described once."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mosaic_cli.estimators.base import Estimator
from mosaic_cli.geometry import is_valid

ROBUST_METHODS = {"usac": cv2.USAC_MAGSAC, "ransac": cv2.RANSAC}


@dataclass
class OrbConfig:
    n_features: int = 1000
    fast_threshold: int = 10  # lower than OpenCV's 20: aerial ground is often weakly textured
    ratio: float = 0.8  # Lowe's ratio test
    method: str = "usac"
    reproj_threshold: float = 1.5  # pixels at working resolution
    min_inliers: int = 12
    confident_inliers: int = 60  # inlier count at which confidence saturates


class OrbEstimator(Estimator):
    name = "orb"

    def __init__(self, work_width: int = 320, config: OrbConfig | None = None):
        super().__init__(work_width)
        self.config = config or OrbConfig()
        if self.config.method not in ROBUST_METHODS:
            raise ValueError(f"method must be one of {', '.join(ROBUST_METHODS)}")
        self._orb = cv2.ORB_create(
            nfeatures=self.config.n_features, fastThreshold=self.config.fast_threshold, edgeThreshold=15, patchSize=15
        )
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self._prev_features = None

    def reset(self, full_size):
        super().reset(full_size)
        self._prev_features = None

    def _describe(self, gray: np.ndarray):
        keypoints, descriptors = self._orb.detectAndCompute(gray, None)
        points = np.float32([k.pt for k in keypoints]) if keypoints else np.zeros((0, 2), np.float32)
        return points, descriptors

    def _estimate(self, prev: np.ndarray, cur: np.ndarray):
        if self._prev_features is None:
            self._prev_features = self._describe(prev)
        prev_pts, prev_desc = self._prev_features
        cur_pts, cur_desc = self._describe(cur)
        self._prev_features = (cur_pts, cur_desc)
        return fit_homography(prev_pts, prev_desc, cur_pts, cur_desc, self._matcher, self.config, self.work_size)


def fit_homography(prev_pts, prev_desc, cur_pts, cur_desc, matcher, config: OrbConfig, size):
    """Ratio-test matches, then a robust fit; (None, 0) when anything is insufficient."""
    c = config
    if prev_desc is None or cur_desc is None or len(prev_pts) < c.min_inliers or len(cur_pts) < c.min_inliers:
        return None, 0.0
    pairs = matcher.knnMatch(prev_desc, cur_desc, k=2)
    good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < c.ratio * m[1].distance]
    if len(good) < c.min_inliers:
        return None, 0.0
    src = prev_pts[[m.queryIdx for m in good]]
    dst = cur_pts[[m.trainIdx for m in good]]
    H, mask = cv2.findHomography(src, dst, ROBUST_METHODS[c.method], c.reproj_threshold, maxIters=2000, confidence=0.999)
    if H is None or mask is None:
        return None, 0.0
    inliers = int(mask.sum())
    if inliers < c.min_inliers or not is_valid(H, size, max_area_ratio=2.0):
        return None, 0.0
    confidence = min(1.0, inliers / c.confident_inliers) * np.sqrt(inliers / len(good))
    return H, confidence
