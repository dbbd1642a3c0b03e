"""How well two working frames agree once registered, and how much detail a frame has: the checks
by which the learned estimator confirms a pair (:func:`detail_zncc`), chooses between its own
registration and the fallback's (:func:`band_agreement`) and tells a spoilt frame
(:func:`detail_level`).  Pure functions of numpy images; the masks are the estimator's use masks
at the working size (None: every pixel)."""

from __future__ import annotations

import cv2
import numpy as np


def fine_detail(gray: np.ndarray) -> np.ndarray:
    """The fine detail of a working frame: the image minus its 5x5 mean (float32)."""
    g = gray.astype(np.float32)
    return g - cv2.blur(g, (5, 5))


def detail_zncc(prev_detail: np.ndarray, cur_detail: np.ndarray, H: np.ndarray, positions: np.ndarray, patch: int,
                usable: np.ndarray, work_mask: np.ndarray | None) -> float:
    """Zero-normalised cross-correlation between the fine detail (:func:`fine_detail`) of the
    patches of frame t (top-left corners ``positions``, ``patch`` px square) and of frame t+1
    sampled through ``H``, on pixels whose every bilinear tap lies inside frame t+1, over all
    patches.  Detail decorrelates within a pixel or two of misregistration, where raw intensities
    still correlate, and a textureless patch scores low, as it should (docs in models/README.md).
    Overlays are left out: no tap on a pixel ``usable`` (1 where the mask allows, 0 elsewhere)
    excludes in frame t+1, no pixel ``work_mask`` excludes in frame t."""
    P = patch
    target, warped = [], []
    for x, y in positions:
        to_next = np.asarray(H, np.float64) @ np.array([[1.0, 0, x], [0, 1.0, y], [0, 0, 1.0]])
        valid = sample_patch(usable, to_next, P) > 0.999  # every bilinear tap inside frame t+1 (and unmasked)
        if work_mask is not None:  # nor on an overlay of frame t
            valid &= work_mask[y : y + P, x : x + P] > 0
        target.append(prev_detail[y : y + P, x : x + P][valid])
        warped.append(sample_patch(cur_detail, to_next, P)[valid])
    return zncc(np.concatenate(target), np.concatenate(warped), len(positions) * P * P)


def band_agreement(prev_aligned: np.ndarray, cur_aligned: np.ndarray, H: np.ndarray, usable: np.ndarray,
                   work_mask: np.ndarray | None) -> float:
    """ZNCC of the images the polish aligns (band-passed), frame t against frame t+1 sampled
    through ``H``, over the pixels both frames see (and the mask allows): to choose between
    two registrations of one pair.  Band-passed frames keep the coarse detail that noise and
    compression spare, where the fine detail of :func:`detail_zncc` is mostly noise."""
    size = (usable.shape[1], usable.shape[0])
    a = prev_aligned.astype(np.float32)
    inside = cv2.warpPerspective(usable, H, size, flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP)
    b = cv2.warpPerspective(cur_aligned.astype(np.float32), H, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    use = inside > 0
    if work_mask is not None:
        use &= work_mask > 0
    return zncc(a[use], b[use], a.size)


def detail_level(gray: np.ndarray) -> float:
    """RMS of the band-passed detail of a working frame (difference of Gaussians of sigmas 1.5 and
    6 working px, taken at half size): what glare, a heavy blur, darkness or featureless ground
    take away, and sensor noise mostly leaves alone (over nearly textureless ground the noise is
    most of it, and a blur there counts as spoilt only when it takes a fifth of that away)."""
    half = cv2.pyrDown(gray).astype(np.float32)
    return float((cv2.GaussianBlur(half, (0, 0), 0.75) - cv2.GaussianBlur(half, (0, 0), 3.0)).std())


def sample_patch(image: np.ndarray, patch_to_image: np.ndarray, size: int) -> np.ndarray:
    """The ``size`` x ``size`` patch whose pixel (x, y) is ``image`` at ``patch_to_image @ (x, y, 1)``
    (bilinear, 0 outside)."""
    return cv2.warpPerspective(image, patch_to_image, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_CONSTANT)


def zncc(a: np.ndarray, b: np.ndarray, total: int) -> float:
    """ZNCC of the samples ``a`` and ``b``; 0 when they are fewer than a quarter of ``total``."""
    if len(a) <= 0.25 * total:
        return 0.0
    a, b = a.astype(np.float64), b.astype(np.float64)
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum() + 1e-12))
