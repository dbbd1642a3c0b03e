"""Sub-pixel polish of a frame-to-frame homography, seeded by a coarser estimate.

Shared by the ORB estimator (seeded by its feature fit) and the learned estimator (seeded by
the network).  Both seeds are good to about a working pixel, with errors that are correlated
from frame to frame and so add up over a chain; the image gradients locate the motion to a
small fraction of a pixel.  Two polishers:

* :func:`track_points`: pyramidal Lucas-Kanade tracks points of the previous frame into the
  current one, starting where the seed puts them, then a robust refit with a tight threshold.
* :func:`align_pixels`: OpenCV's ECC (Gauss-Newton on a correlation score) over all pixels.

Either keeps the seed when it fails or wanders further than ``max_shift`` from it, and says so
(:class:`Polish`), with a score of how well the frames agreed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import cv2
import numpy as np

from mosaic_cli.geometry import frame_corners, is_valid, project

Polisher = Literal["lk", "ecc"]
POLISHERS: tuple[Polisher, ...] = get_args(Polisher)


@dataclass
class PolishConfig:
    window: int = 15  # Lucas-Kanade window (working pixels)
    levels: int = 1  # LK pyramid levels above the frame itself (1: displacements of a few px)
    threshold: float = 0.5  # reprojection threshold (working px) of the refit on tracked points
    # RANSAC iterations of the refit at most.  A pair the seed put in the right basin has mostly
    # inlying tracks, and RANSAC stops after a few dozen; only a pair where few tracks agree (a
    # blurred, noisy or low-texture one) runs to the cap, which then was most of the cost of a
    # degraded flight.  At the cap, a third of the tracks agreeing is still found 99 times in 100.
    max_iters: int = 300
    min_inliers: int = 12
    ecc_iterations: int = 20
    max_shift: float = 2.0  # a polished fit further than this (working px, at any corner) from the seed is a divergence

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """No flag sets these: a bad value is a bug (ValueError), not the user's input."""
        if self.window < 3 or self.levels < 0 or self.max_iters < 1 or self.min_inliers < 4 or self.ecc_iterations < 1:
            raise ValueError(f"window >= 3, levels >= 0, max_iters, ecc_iterations >= 1, min_inliers >= 4 expected: {self}")
        if self.threshold <= 0 or self.max_shift <= 0:
            raise ValueError(f"threshold and max_shift must be positive: {self}")


@dataclass(frozen=True)
class Polish:
    H: np.ndarray  # the polished homography, or the seed when ``refined`` is False
    refined: bool
    score: float  # LK: refit inliers / points asked to track; ECC: its correlation; 0 when not refined


def track_points(prev: np.ndarray, cur: np.ndarray, H: np.ndarray, points: np.ndarray, config: PolishConfig,
                 mask: np.ndarray | None = None) -> Polish:
    """Track ``points`` (N, 2) of ``prev`` into ``cur`` with pyramidal LK, starting at ``H @ points``,
    and refit a homography to the tracks (RANSAC at ``config.threshold``).  With a ``mask``
    (working size, 255 = use), tracks whose window would reach a masked pixel of either frame
    are dropped: an overlay that stays put pulls a window toward zero motion."""
    c = config
    n = len(points)
    kept = Polish(H, False, 0.0)
    if n < c.min_inliers:
        return kept
    src = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 1, 2)
    guess = cv2.perspectiveTransform(src, np.asarray(H, dtype=np.float64))
    if not np.all(np.isfinite(guess)):
        return kept
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)
    tracked, status, _ = cv2.calcOpticalFlowPyrLK(prev, cur, src, guess.copy(), winSize=(c.window, c.window), maxLevel=c.levels,
                                                  criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    ok = status.ravel() == 1
    if mask is not None:
        inside = erode_mask(mask, c.window // 2 + 1)
        ok &= _allowed(inside, src.reshape(-1, 2)) & _allowed(inside, tracked.reshape(-1, 2))
    if ok.sum() < c.min_inliers:
        return kept
    try:
        refined, mask = cv2.findHomography(src.reshape(-1, 2)[ok], tracked.reshape(-1, 2)[ok], cv2.RANSAC, c.threshold,
                                           maxIters=c.max_iters, confidence=0.999)
    except cv2.error:  # degenerate tracks (all collinear, all equal)
        return kept
    if refined is None or mask is None or mask.sum() < c.min_inliers:
        return kept
    if not _close_and_valid(refined, H, prev.shape, c.max_shift):
        return kept
    return Polish(refined, True, float(mask.sum()) / n)


def align_pixels(prev: np.ndarray, cur: np.ndarray, H: np.ndarray, config: PolishConfig, mask: np.ndarray | None = None) -> Polish:
    """Align ``cur`` onto ``prev`` with ECC, starting from ``H``, over the pixels of ``cur`` that
    ``mask`` allows (working size, 255 = use; None: all)."""
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, config.ecc_iterations, 1e-4)
    kept = Polish(H, False, 0.0)
    # ECC's warp maps template (cur) pixels to input (prev) pixels: the inverse of H.
    try:
        warp = np.linalg.inv(H / H[2, 2]).astype(np.float32)
        correlation, warp = cv2.findTransformECC(cur, prev, warp, cv2.MOTION_HOMOGRAPHY, criteria, mask, 3)
    except (cv2.error, np.linalg.LinAlgError):
        return kept
    refined = np.linalg.inv(warp.astype(np.float64))
    if not np.all(np.isfinite(refined)):
        return kept
    refined /= refined[2, 2]
    if not _close_and_valid(refined, H, prev.shape, config.max_shift):
        return kept
    return Polish(refined, True, float(np.clip(correlation, 0.0, 1.0)))


def erode_mask(mask: np.ndarray, radius: int) -> np.ndarray:
    """``mask`` (255 = use) shrunk by ``radius`` px, so that a window or a descriptor patch
    centred on a remaining pixel sees no masked pixel; the frame border is not a mask edge."""
    if radius <= 0:
        return mask
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * radius + 1, 2 * radius + 1))
    return cv2.erode(mask, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=255)


def _allowed(mask: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,) bool: the points (x, y) fall on usable pixels of ``mask`` (outside the frame: no)."""
    h, w = mask.shape
    finite = np.all(np.isfinite(points), axis=1)
    xy = np.where(finite[:, None], np.rint(points), -1).astype(np.int64)
    inside = finite & (xy[:, 0] >= 0) & (xy[:, 0] < w) & (xy[:, 1] >= 0) & (xy[:, 1] < h)
    ok = np.zeros(len(points), bool)
    ok[inside] = mask[xy[inside, 1], xy[inside, 0]] > 0
    return ok


def _close_and_valid(refined: np.ndarray, seed: np.ndarray, shape: tuple[int, ...], max_shift: float) -> bool:
    size = (shape[1], shape[0])
    corners = frame_corners(*size)
    shift = np.linalg.norm(project(refined, corners) - project(seed, corners), axis=-1).max()
    return bool(shift <= max_shift and is_valid(refined, size, max_area_ratio=2.0))


def band_pass(gray: np.ndarray, fine: float, coarse: float, gain: float = 3.0) -> np.ndarray:
    """Difference of Gaussians of ``gray`` (sigmas ``fine`` < ``coarse``, pixels) as uint8 around
    128 (LK wants 8 bits): what a polish should align when the finest detail is unreliable
    (compression) and the brightness drifts (exposure).  ``gain`` keeps the quantisation step
    well under a gray level of the original."""
    f = gray.astype(np.float32)
    smooth = cv2.GaussianBlur(f, (0, 0), fine)
    # The coarse base has no detail finer than a few pixels, so it is blurred at half size (a
    # kernel of a quarter the taps on a quarter the pixels) and brought back up.  The frame is
    # first padded as GaussianBlur pads it (reflect-101), so that the borders match too.  The
    # 2x2 average down and the linear interpolation up blur too (variances 1/4 and 2/3 px^2).
    h, w = smooth.shape
    pad = 2 * int(np.ceil(1.5 * coarse))  # even: the halving keeps the pixel grid
    if min(w, h) > pad:
        padded = cv2.copyMakeBorder(smooth, pad, pad + h % 2, pad, pad + w % 2, cv2.BORDER_REFLECT_101)
        half = cv2.resize(padded, (padded.shape[1] // 2, padded.shape[0] // 2), interpolation=cv2.INTER_AREA)
        sigma = float(np.sqrt(max(coarse**2 - fine**2 - 0.25 - 2 / 3, 0.25))) / 2
        up = cv2.resize(cv2.GaussianBlur(half, (0, 0), sigma), (padded.shape[1], padded.shape[0]), interpolation=cv2.INTER_LINEAR)
        base = up[pad : pad + h, pad : pad + w]
    else:
        base = cv2.GaussianBlur(smooth, (0, 0), float(np.sqrt(coarse**2 - fine**2)))
    return cv2.addWeighted(smooth, gain, base, -gain, 128.0, dtype=cv2.CV_8U)


@dataclass
class CornerConfig:
    max_points: int = 300  # a few hundred: the refit is over-determined many times, LK stays cheap
    quality: float = 0.01  # of the strongest corner's response (cv2.goodFeaturesToTrack)
    min_distance: int = 8  # spread the points over the frame
    block_size: int = 5
    # Below this strongest Shi-Tomasi response (OpenCV's scale for 8-bit frames) a frame has no
    # texture: measured 0.004-0.018 on the development flights (the 'hard' ones included),
    # 2e-5-3e-5 on flat, heavily blurred (sigma 8) or nearly black (3 %) frames.
    min_response: float = 2e-4

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """No flag sets these: a bad value is a bug (ValueError), not the user's input."""
        if self.max_points < 4 or not 0 < self.quality < 1 or self.min_distance < 0 or self.block_size < 1 or self.min_response < 0:
            raise ValueError(f"max_points >= 4, 0 < quality < 1, min_distance >= 0, block_size >= 1, min_response >= 0 expected: {self}")


def points_to_track(gray: np.ndarray, config: CornerConfig, mask: np.ndarray | None = None) -> np.ndarray:
    """Well-spread Shi-Tomasi corners of ``gray`` (N, 2); none on a textureless frame (where the
    relative quality threshold would otherwise pick up compression noise).  ``mask`` (255 =
    use, same size) keeps corners to the pixels it allows."""
    c = config
    found, quality = cv2.goodFeaturesToTrackWithQuality(gray, c.max_points, c.quality, c.min_distance, mask, blockSize=c.block_size)
    if found is None or float(quality.max()) < c.min_response:  # quality: the Shi-Tomasi response itself
        return np.zeros((0, 2), np.float32)
    return found.reshape(-1, 2)


__all__ = ["POLISHERS", "Polisher", "CornerConfig", "Polish", "PolishConfig", "align_pixels", "band_pass", "erode_mask", "points_to_track",
           "track_points"]
