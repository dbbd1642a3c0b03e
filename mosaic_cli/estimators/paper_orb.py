"""The paper's classical baseline, ORB2+RANSAC, exactly as the authors' code runs it: ORB (500
features, WTA_K=2) on the whole gray working frame (320x180 for 1280x720 video), brute-force
Hamming matching with cross-check, ``findHomography`` RANSAC at 5 working px (20 px at
1280x720), identity on failure; confidence = RANSAC inlier fraction.

``benchmarks/baseline_orb.py`` (``python -m benchmarks estimators orb-baseline``) is the same method written independently of mosaic_cli (OpenCV
decodes the video); ``tests/test_bench.py`` checks that both give the same homographies.  The
only difference is the resolution change: mosaic's exact pixel-centre one
(:func:`mosaic_cli.geometry.to_resolution`) instead of the script's diag(s, s, 1) scaling.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mosaic_cli.estimators.base import Estimator


@dataclass
class PaperOrbConfig:
    n_features: int = 500
    wta_k: int = 2
    reproj_threshold: float = 5.0  # working pixels

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """No flag sets these (the baseline runs as the paper's code does): a bad value is a bug."""
        if self.n_features < 4 or self.wta_k not in (2, 3, 4) or self.reproj_threshold <= 0:
            raise ValueError(f"n_features >= 4, wta_k in 2..4, reproj_threshold > 0 expected: {self}")


class PaperOrbEstimator(Estimator):
    name = "orb-paper"

    def __init__(self, work_width: int = 320, config: PaperOrbConfig | None = None):
        super().__init__(work_width)
        self.config = config or PaperOrbConfig()
        self._orb = cv2.ORB_create(nfeatures=self.config.n_features, WTA_K=self.config.wta_k)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        self._prev_features: tuple | None = None

    def reset(self, full_size):
        super().reset(full_size)
        self._prev_features = None

    def _estimate(self, prev: np.ndarray, cur: np.ndarray):
        # ORB is deterministic: the previous frame's features are those the script recomputes.
        if self._prev_features is None:
            self._prev_features = self._orb.detectAndCompute(prev, None)
        (kp1, d1), (kp2, d2) = self._prev_features, self._orb.detectAndCompute(cur, None)
        self._prev_features = (kp2, d2)
        if d1 is None or d2 is None or len(kp1) < 4 or len(kp2) < 4:
            return np.eye(3), 0.0
        matches = self._matcher.match(d1, d2)
        if len(matches) < 4:
            return np.eye(3), 0.0
        src = np.array([kp1[m.queryIdx].pt for m in matches], np.float32)
        dst = np.array([kp2[m.trainIdx].pt for m in matches], np.float32)
        H, mask = cv2.findHomography(src, dst, cv2.RANSAC, self.config.reproj_threshold)
        if H is None or not np.all(np.isfinite(H)):
            return np.eye(3), 0.0
        return H, float(mask.sum()) / len(matches)
