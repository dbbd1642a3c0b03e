"""Use masks (uint8, 255 = ground to use, 0 = keep out: burned-in overlays, the user's
``--mask``), as every stage takes them: a ``--mask`` image read at a video's size
(:func:`load_mask`), a mask at another resolution (:func:`work_mask`), masked pixels filled
with the ground around them (:func:`fill_masked`).  Pure image operations, below every layer
that estimates or composes (:mod:`mosaic_cli.overlay` finds the overlays)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.errors import BadInput


def load_mask(path: str | Path, full_size: tuple[int, int]) -> np.ndarray:
    """A ``--mask`` image as a use mask at ``full_size``: white (>= 128) = use.  A mask of
    another size but the same aspect ratio is scaled; any other is refused (BadInput).  The
    path itself was checked by :class:`MaskOptions`."""
    p = Path(path)
    image = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise BadInput(f"--mask {p}: not an image OpenCV can read")
    if image.ndim == 3:
        # Transparent pixels count as black (not to use); colour is judged by its gray level.
        alpha = image[..., 3] if image.shape[2] == 4 else None
        image = cv2.cvtColor(image[..., :3], cv2.COLOR_BGR2GRAY)
        if alpha is not None:
            image = np.minimum(image, alpha)
    if image.dtype != np.uint8:
        image = cv2.convertScaleAbs(image, alpha=255.0 / max(1.0, float(np.iinfo(image.dtype).max)))
    h, w = image.shape
    W, H = full_size
    if (w, h) != (W, H):
        if abs(w * H - h * W) > 0.01 * W * H or min(w, h) < 2:
            raise BadInput(f"--mask {p} is {w}x{h}, the video {W}x{H}: a mask must have the video's size or at least its aspect ratio")
        image = cv2.resize(image, (W, H), interpolation=cv2.INTER_AREA)
    use = np.where(image >= 128, 255, 0).astype(np.uint8)
    if w < W:
        # A smaller mask places an edge only to within one of its pixels, (W / w) of the
        # frame's: its black areas grow by that much, so that no overlay pixel slips out.
        r = int(np.ceil(W / w - 1))
        use = cv2.erode(use, cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1)),
                        borderType=cv2.BORDER_CONSTANT, borderValue=255)
    if np.count_nonzero(use) < 0.05 * use.size:
        raise BadInput(f"--mask {p} leaves less than 5% of the frame to use (white = use, black = ignore)")
    return use


def fill_masked(image: np.ndarray, use: np.ndarray) -> np.ndarray:
    """``image`` with the pixels ``use`` excludes replaced by a smooth fill from the pixels
    around them (normalised convolution), so that filters reaching across the mask's edge (a
    multi-band blend's pyramid) see plausible ground, never the overlay's colours."""
    valid = (work_mask(use, (image.shape[1], image.shape[0])) > 0).astype(np.float32)
    if valid.all():
        return image
    sigma = max(4.0, 0.02 * max(image.shape[:2]))
    f = image.astype(np.float32)
    weight = cv2.GaussianBlur(valid, (0, 0), sigma)
    filled = cv2.GaussianBlur(f * (valid[..., None] if f.ndim == 3 else valid), (0, 0), sigma)
    filled /= np.maximum(weight, 1e-6)[..., None] if f.ndim == 3 else np.maximum(weight, 1e-6)
    mean = f[valid > 0].mean(axis=0)
    far = weight < 1e-3  # no valid pixel within reach: the mean of the ground
    filled[far] = mean
    out = image.copy()
    out[valid == 0] = np.clip(filled[valid == 0], 0, 255).astype(image.dtype)
    return out


def work_mask(use: np.ndarray | None, size: tuple[int, int], margin: int = 0) -> np.ndarray | None:
    """A full-resolution use mask at ``size`` (w, h): a pixel is usable only when all of it is,
    shrunk by ``margin`` px (a feature's descriptor or an LK window must not reach the overlay)."""
    if use is None:
        return None
    small = use if (use.shape[1], use.shape[0]) == tuple(size) else cv2.resize(use, tuple(size), interpolation=cv2.INTER_AREA)
    small = np.where(small >= 255, 255, 0).astype(np.uint8)
    if margin > 0:
        small = cv2.erode(small, cv2.getStructuringElement(cv2.MORPH_RECT, (2 * margin + 1, 2 * margin + 1)),
                          borderType=cv2.BORDER_CONSTANT, borderValue=255)
    return small


__all__ = ["fill_masked", "load_mask", "work_mask"]
