"""The crop window: which part of each input frame becomes the output frame.

Smoothers describe the result as ``V_t``, the map from normalised output coordinates to
normalised coordinates of input frame t; :func:`output_warps` turns that into the pixel warps
the renderer and ``--warps`` use (input pixels -> output pixels).
"""

from __future__ import annotations

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.geometry import normalize, project
from mosaic_cli.stabilize.path import normalized_frame_rect, normalizer

AUTO = "auto"
MIN_CROP = 0.5


def parse_crop(value: str | float | None) -> float | None:
    """``auto`` (None: the smoother chooses the zoom so that no border shows) or a ratio in
    [0.5, 1] of the frame's width and height kept in the output."""
    if value is None or (isinstance(value, str) and value.strip().lower() == AUTO):
        return None
    try:
        ratio = float(value)
    except (TypeError, ValueError):
        raise BadInput(f"--crop must be 'auto' or a ratio in [{MIN_CROP}, 1], got {value!r}") from None
    if not MIN_CROP <= ratio <= 1.0:
        raise BadInput(f"--crop must be 'auto' or a ratio in [{MIN_CROP}, 1], got {value!r}")
    return ratio


def zoom_matrix(ratio: float) -> np.ndarray:
    """Scaling about the (normalised) frame centre."""
    return np.diag([ratio, ratio, 1.0])


def rect_corners_normalized(size: tuple[int, int]) -> np.ndarray:
    """The four frame corners (pixel edges) in normalised coordinates, (4, 2)."""
    x0, y0, x1, y1 = normalized_frame_rect(size)
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])


def inside_margin(V: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(N,) the smallest distance (normalised units) by which the output frame's corners, mapped
    through ``V`` (N, 3, 3) into the input frame, stay inside it; negative where a border shows."""
    x0, y0, x1, y1 = normalized_frame_rect(size)
    q = project(V, rect_corners_normalized(size))
    margins = np.stack([q[..., 0] - x0, x1 - q[..., 0], q[..., 1] - y0, y1 - q[..., 1]], axis=-1)
    return margins.min(axis=(-1, -2))


def zoomed(V: np.ndarray, ratios: np.ndarray | float) -> np.ndarray:
    """V_t @ zoom_matrix(ratio_t) for every t, (N, 3, 3)."""
    out = np.array(V, dtype=np.float64)
    out[..., :, :2] *= np.reshape(ratios, (-1, 1, 1)) if np.ndim(ratios) else ratios
    return out


def largest_inside_zoom(V: np.ndarray, size: tuple[int, int], smallest: float = MIN_CROP, steps: int = 40) -> np.ndarray:
    """(N,) the largest ratio z in [smallest, 1] with V_t @ zoom(z) showing no border (bisection;
    ``smallest`` where even that shows one)."""
    lo = np.full(len(V), float(smallest))
    hi = np.ones(len(V))
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        ok = inside_margin(zoomed(V, mid), size) >= 0
        lo = np.where(ok, mid, lo)
        hi = np.where(ok, hi, mid)
    return np.where(inside_margin(V, size) >= 0, 1.0, lo)


def output_warps(V: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Pixel warps (N, 3, 3), input frame t -> output frame t, from normalised ``V``
    (output -> input).  The output has the input's size."""
    N = normalizer(size)
    return normalize(np.linalg.inv(N) @ np.linalg.inv(V) @ N)


BORDER_CHUNK = 256  # frames measured at a time: the sample grid costs about 90 KB a frame


def border_fraction(warps: np.ndarray, size: tuple[int, int], grid: int = 64) -> np.ndarray:
    """(N,) the fraction of each output frame that no input pixel covers, sampled on a grid of
    pixel centres (so a border thinner than half a pixel does not count).  Measured in chunks
    of frames, so that memory does not grow with the length of the video."""
    w, h = size
    xs = np.linspace(0, w - 1, grid)
    ys = np.linspace(0, h - 1, max(2, int(round(grid * h / w))))
    pts = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    warps = np.asarray(warps, dtype=np.float64).reshape(-1, 3, 3)
    out = np.empty(len(warps))
    for start in range(0, len(warps), BORDER_CHUNK):
        src = project(np.linalg.inv(warps[start:start + BORDER_CHUNK]), pts)
        inside = (src[..., 0] >= -0.5) & (src[..., 0] <= w - 0.5) & (src[..., 1] >= -0.5) & (src[..., 1] <= h - 0.5)
        out[start:start + BORDER_CHUNK] = 1.0 - inside.mean(axis=-1)
    return out
