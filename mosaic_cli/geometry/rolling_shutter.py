"""Rolling shutter geometry (numpy, pure): row bands, their times, and the per-row mapping.

A rolling-shutter camera reads its sensor row by row: with readout ``R`` (a fraction of the
frame interval), row y of frame t sees the camera at time ``t + R * y / h`` (in frames).  A
frame is then described by one homography per band of rows rather than one per frame.

Bands: ``K`` bands of equal height; band k holds rows [k h/K, (k+1) h/K) and its pose is the
camera's at its centre row ``(k + 0.5) h / K - 0.5``.  A row between two band centres maps to
the map (or to any reference) by the two bands' frame -> reference homographies blended
linearly in the row (each normalised to [2, 2] = 1); rows beyond the first or last centre take
that band's.  That rule is the simulator's truth and every scorer's (:func:`row_frame_to_ref`).

The "mid" pose of a frame is the camera's at its centre row, ``(h - 1) / 2``: the time
``t + R * (h - 1) / (2 h)``.
"""

from __future__ import annotations

import numpy as np

from mosaic_cli.geometry.homography import normalize

ROW_BANDS = 16  # the simulator's bands: 45 rows each at 720 p


def band_centres(height: int, bands: int) -> np.ndarray:
    """(K,) the centre row of each of ``bands`` equal bands over ``height`` rows (pixel centres)."""
    return (np.arange(bands) + 0.5) * height / bands - 0.5


def mid_row(height: int) -> float:
    """The row whose time is the frame's mid time: the centre row."""
    return (height - 1) / 2.0


def row_times(rows: np.ndarray, height: int, readout: float) -> np.ndarray:
    """Time of each row, in frames after the frame's first row: ``readout * row / height``."""
    return readout * np.asarray(rows, dtype=np.float64) / float(height)


def band_blend(rows: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each row, (index k of the band centre at or above it, weight a of band k + 1):
    the row's value is ``(1 - a) v[k] + a v[k + 1]``, clamped outside the centres."""
    rows = np.asarray(rows, dtype=np.float64)
    K = len(centres)
    if K == 1:
        return np.zeros(rows.shape, int), np.zeros(rows.shape)
    k = np.clip(np.searchsorted(centres, rows, side="right") - 1, 0, K - 2)
    a = np.clip((rows - centres[k]) / (centres[k + 1] - centres[k]), 0.0, 1.0)
    return k, a


def row_frame_to_ref(frame_to_ref: np.ndarray, rows: np.ndarray, height: int) -> np.ndarray:
    """(..., R, 3, 3) the frame -> reference homography of each of ``rows`` (R,), from the
    bands' (..., K, 3, 3) by the module's rule (linear blend between band centres)."""
    F = normalize(np.asarray(frame_to_ref, dtype=np.float64))
    k, a = band_blend(rows, band_centres(height, F.shape[-3]))
    return (1.0 - a)[:, None, None] * F[..., k, :, :] + a[:, None, None] * F[..., np.minimum(k + 1, F.shape[-3] - 1), :, :]


def project_rows(frame_to_ref: np.ndarray, points: np.ndarray, height: int) -> np.ndarray:
    """(P, 2) reference positions of frame points (P, 2), each through its own row's
    homography (frame_to_ref: the bands' (K, 3, 3))."""
    pts = np.asarray(points, dtype=np.float64)
    Hr = row_frame_to_ref(frame_to_ref, pts[:, 1], height)  # (P, 3, 3)
    v = Hr @ np.concatenate([pts, np.ones((len(pts), 1))], 1)[:, :, None]
    return v[:, :2, 0] / v[:, 2:3, 0]
