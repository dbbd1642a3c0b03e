"""The DLT, one in numpy (:func:`mosaic_cli.geometry.weighted_dlt`) and its torch twin
(:func:`mosaic_cli.geometry.tensor.weighted_dlt`), against ``cv2.findHomography(method=0)``."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from mosaic_cli.geometry import project, weighted_dlt
from mosaic_cli.geometry import tensor as T

TRUE_H = np.array([[1.02, 0.03, -7.5], [-0.02, 0.98, 4.25], [2e-5, -1e-5, 1.0]])


def correspondences(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points of a 320x180 frame and where TRUE_H sends them, both float32-exact (what
    findHomography reads): exact correspondences but for that rounding of the images."""
    rng = np.random.default_rng(seed)
    src = rng.uniform(0, 320, (n, 2)) * [1, 180 / 320]
    src = src.astype(np.float32).astype(np.float64)
    return src, project(TRUE_H, src).astype(np.float32).astype(np.float64)


def relative(H: np.ndarray, ref: np.ndarray) -> float:
    return float(np.abs(H - ref).max() / np.abs(ref).max())


@pytest.mark.parametrize("n, tolerance", [(4, 1e-9), (25, 1e-6)])  # 4 points: exact whatever the rounding
def test_the_dlt_matches_opencv_in_numpy_and_torch(n, tolerance):
    src, dst = correspondences(n)
    ref = cv2.findHomography(src, dst, 0)[0]
    assert relative(weighted_dlt(src, dst), ref) < tolerance
    batch = T.weighted_dlt(torch.tensor(np.stack([src, src])), torch.tensor(np.stack([dst, dst])))
    assert batch.shape == (2, 3, 3) and all(relative(H, ref) < tolerance for H in batch.numpy())


def test_a_correspondence_of_weight_zero_counts_for_nothing():
    src, dst = correspondences(12, seed=1)
    wrong = dst.copy()
    wrong[3] += 40.0
    weights = np.ones(12)
    weights[3] = 0.0
    clean = weighted_dlt(np.delete(src, 3, 0), np.delete(dst, 3, 0))
    assert relative(weighted_dlt(src, wrong, weights), clean) < 1e-9
    H = T.weighted_dlt(torch.tensor(src), torch.tensor(wrong), torch.tensor(weights)).numpy()
    assert relative(H, clean) < 1e-9
    assert relative(weighted_dlt(src, wrong), clean) > 1e-3  # (the wrong one does count at weight 1)
