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

from typing import Any

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


# ---------------------------------------------------------------------------------------------
# Estimating the row-dependent motion from point tracks
#
# A band's motion between two frames is a similarity about the frame centre (cx, cy), written
# with four channels p = (dx, dy, rotation, scale) so that it is linear in them:
#     x' - x = dx + scale (x - cx) - rotation (y - cy),  y' - y = dy + rotation (x - cx) + scale (y - cy).
# A global motion gives every band the same p; a rolling shutter makes p vary with the row.

CHANNELS = ("dx", "dy", "rotation", "scale")
BAND_SIGMA = 0.5  # Gaussian row weights of a band's fit: sigma in band heights
# Each band's fit is pulled toward the whole frame's by this share of its weight.  Both flatten
# the motion's variation over the rows, which reads as a shorter readout (at sigma 1 and a pull
# of 0.05 `auto` found 0.7 for 0.9; at 0.5 and 0.01, 0.85) and, under broadband vibration
# (issue 41: noise of 10-25 Hz on the shifts and the rotation, whose motion over the rows is
# no straight line), left the corrections' error against the truth at 0.096, 0.239, 0.487 px
# on readouts 0.5, 0.7, 0.9 (640x360); without the pull 0.065, 0.139, 0.296
# (docs/measurements/rolling-shutter.md).
BAND_PULL = 0.0


def _similarity_rows(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(2P, 4) design matrix of the channels for points (P, 2): x rows then y rows."""
    x, y = points[:, 0] - centre[0], points[:, 1] - centre[1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    return np.concatenate([np.stack([one, zero, -y, x], 1), np.stack([zero, one, x, y], 1)])


# A band fits its own motion only where enough tracks lie near it, spread over enough of its
# width to tell rotation and scale from the shifts: a textureless band (sky, water, a blown
# sky, a uniform field) or a frame whose tracks bunch in a few rows leaves a band's normal
# matrix singular.  Such a band is bridged: its channels are interpolated over the rows between
# the nearest fitted bands (the whole frame's fit where no band could be fitted).
MIN_BAND_SUPPORT = 6.0  # effective tracks (the sum of a band's Gaussian row weights) a band's own fit needs
MAX_BAND_CONDITION = 1e8  # condition number of a band's normal matrix, its channels scaled alike, beyond which it is degenerate


def band_motion(src: np.ndarray, dst: np.ndarray, size: tuple[int, int], bands: int,
                sigma: float = BAND_SIGMA, pull: float = BAND_PULL) -> np.ndarray:
    """(K, 4) each row band's motion channels between two frames, from tracked points src ->
    dst (P, 2) (inliers): :func:`fit_bands`'s motions, bridged bands included."""
    return fit_bands(src, dst, size, bands, sigma, pull)[0]


def fit_bands(src: np.ndarray, dst: np.ndarray, size: tuple[int, int], bands: int,
              sigma: float = BAND_SIGMA, pull: float = BAND_PULL) -> tuple[np.ndarray, np.ndarray]:
    """(K, 4) each row band's motion channels between two frames from tracked points src ->
    dst (P, 2) (inliers), and (K,) which bands were bridged.

    A fitted band's motion is a weighted least-squares similarity, the points weighted by a
    Gaussian of their row's distance to the band centre (``sigma`` band heights), pulled toward
    the whole frame's fit by ``pull`` (a mixture of similarities regularised toward the global
    one).  A band with too little support (:data:`MIN_BAND_SUPPORT`) or a degenerate spread
    (:data:`MAX_BAND_CONDITION`) is bridged: linearly interpolated over the band centres between
    the fitted bands (held flat beyond the outermost), or the whole frame's fit if none was fitted."""
    w, h = size
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    src, dst = np.asarray(src, dtype=np.float64).reshape(-1, 2), np.asarray(dst, dtype=np.float64).reshape(-1, 2)
    tracked = np.isfinite(src).all(1) & np.isfinite(dst).all(1)
    src, dst = src[tracked], dst[tracked]
    A = _similarity_rows(src, centre)
    r = np.concatenate([dst[:, 0] - src[:, 0], dst[:, 1] - src[:, 1]])
    # rotation and scale move the frame's edge by (w / 2) px per unit: weigh them alike in the pull
    D = np.diag([1.0, 1.0, (w / 2.0) ** 2, (w / 2.0) ** 2])
    alike = np.diag([1.0, 1.0, 2.0 / w, 2.0 / w])  # the channels at the same scale, for the condition number
    everyone = np.linalg.lstsq(A, r, rcond=None)[0] if len(src) else np.zeros(4)
    centres = band_centres(h, bands)
    out = np.zeros((bands, 4))
    fitted = np.zeros(bands, dtype=bool)
    for k, yk in enumerate(centres):
        wt = np.exp(-0.5 * ((src[:, 1] - yk) / (sigma * h / bands)) ** 2)
        support = float(wt.sum())
        if support < MIN_BAND_SUPPORT:
            continue
        wt2 = np.concatenate([wt, wt])
        lam = pull * support
        N = A.T @ (wt2[:, None] * A) + lam * D
        if not np.isfinite(N).all() or not np.linalg.cond(alike @ N @ alike) <= MAX_BAND_CONDITION:
            continue
        out[k] = np.linalg.solve(N, A.T @ (wt2 * r) + lam * D @ everyone)
        fitted[k] = np.isfinite(out[k]).all()
    if not fitted.any():
        out[:] = everyone
    elif not fitted.all():
        for c in range(4):
            out[~fitted, c] = np.interp(centres[~fitted], centres[fitted], out[fitted, c])
    return out, ~fitted


def similarity_matrix(channels: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(..., 3, 3) the motion x -> x + displacement of channels (..., 4) about the frame centre."""
    w, h = size
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    p = np.asarray(channels, dtype=np.float64)
    dx, dy, rot, sc = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    M = np.zeros(p.shape[:-1] + (3, 3))
    M[..., 0, 0], M[..., 0, 1], M[..., 0, 2] = 1 + sc, -rot, dx - sc * cx + rot * cy
    M[..., 1, 0], M[..., 1, 1], M[..., 1, 2] = rot, 1 + sc, dy - rot * cx - sc * cy
    M[..., 2, 2] = 1.0
    return M


# ---------------------------------------------------------------------------------------------
# From the bands' frame-to-frame motions to each band's pose within its frame
#
# Band k of pair t measures D(tau) = u(tau + 1) - u(tau) at tau = t + R y_k / h, where u(tau) is
# the camera's (similarity channels) at time tau: the samples of all bands interleave in time.
# u is solved on a grid of GRID_STEPS nodes a frame by least squares: the measured differences,
# plus a small penalty on its second derivative, which fixes what the one-frame differences
# leave free (a constant per band: exactly the rolling-shutter offsets).  A band's correction is
# then u(mid time) - u(band time): what takes its rows to the frame's mid-time pose.

GRID_STEPS = 24  # nodes per frame interval of the reconstructed path
# Weight of the integral of u''^2 (px^2 frames^3), against 1 per measured px^2.  The corrections'
# error against the simulator's truth is mostly this prior's, not the trackers' noise (1200 corners
# instead of 600 change nothing): at 1e-4 (before) 0.30 px on the 0.9 readout, 8 Hz 5 px `fast`
# flight and 0.05-0.18 px on the 640x360 stabilize bench flights; at 1e-3 0.24 and 0.04-0.10 (the
# auto readouts closer too), at 3e-3 worse again on the 15 and 20 Hz flights
# (docs/measurements/rolling-shutter.md).
ROUGHNESS = 1e-3
# A global shutter unless readout 0 costs this many times the best: rolling-shutter flights
# (readout 0.5-0.9, 8-20 Hz vibration) cost 500-1700 times more at 0, global-shutter ones 1-2.1
# (at ROUGHNESS 1e-4; `auto`'s probe at 1e-3: 60-299x and 1.0-1.6x)
# (a 'shaky' flight's 3-8 Hz shake read as 0.44 without this test).
GLOBAL_COST_RATIO = 10.0
READOUTS = tuple(np.round(np.arange(0.0, 1.0001, 0.05), 2))  # the grid `auto` tries


def _interp_rows(times: np.ndarray, steps: int, nodes: int) -> Any:
    """Sparse (len(times), nodes): linear interpolation of grid values at ``times`` (frames)."""
    from scipy import sparse

    g = np.clip(np.asarray(times, dtype=np.float64) * steps, 0.0, nodes - 1 - 1e-9)
    j = np.floor(g).astype(int)
    a = g - j
    n = len(g)
    rows = np.repeat(np.arange(n), 2)
    cols = np.stack([j, j + 1], 1).ravel()
    vals = np.stack([1.0 - a, a], 1).ravel()
    return sparse.csr_matrix((vals, (rows, cols)), shape=(n, nodes))


def solve_path(motion: np.ndarray, readout: float, height: int, weights: np.ndarray | None = None,
               steps: int = GRID_STEPS, roughness: float = ROUGHNESS) -> tuple[np.ndarray, float]:
    """Reconstruct the path u on its grid from ``motion`` (N-1, K, C), the bands' pair motions;
    returns (u at the nodes (nodes, C), the least-squares cost per measurement).  ``weights``
    (N-1,): each pair's (0 for a pair without a measurement)."""
    from scipy import sparse
    from scipy.sparse.linalg import splu

    pairs, K, C = motion.shape
    frames = pairs + 1
    nodes = frames * steps + 1  # the last frame's late rows and the frame after it
    offsets = row_times(band_centres(height, K), height, readout)
    tau = (np.arange(pairs)[:, None] + offsets[None]).ravel()
    wt = np.ones(pairs) if weights is None else np.asarray(weights, dtype=np.float64)
    sqrt_w = np.sqrt(np.repeat(wt, K))
    A = sparse.diags(sqrt_w) @ (_interp_rows(tau + 1.0, steps, nodes) - _interp_rows(tau, steps, nodes))
    b = sqrt_w[:, None] * motion.reshape(-1, C)
    h = 1.0 / steps
    second = sparse.diags([np.ones(nodes - 2), -2 * np.ones(nodes - 2), np.ones(nodes - 2)], [0, 1, 2], shape=(nodes - 2, nodes))
    R = second * (np.sqrt(roughness * h) / h**2)
    anchor = sparse.csr_matrix(([1e-3], ([0], [0])), shape=(1, nodes))  # u(0) = 0: the constant left free
    normal = (A.T @ A + R.T @ R + anchor.T @ anchor).tocsc()
    u = splu(normal).solve(np.asarray(A.T @ b))
    cost = float(np.sum((A @ u - b) ** 2) + np.sum((R @ u) ** 2)) / max(float(wt.sum()) * K, 1.0)
    return u, cost


def band_corrections(motion: np.ndarray, readout: float, height: int, weights: np.ndarray | None = None) -> np.ndarray:
    """(N, K, C) the channels that take each band of each frame to its frame's mid-time pose,
    u(mid) - u(band time), from the bands' pair motions (N-1, K, C) and the readout."""
    pairs, K, C = motion.shape
    if readout <= 0 or pairs < 1:
        return np.zeros((pairs + 1, K, C))
    u, _ = solve_path(motion, readout, height, weights)
    nodes = len(u)
    frames = np.arange(pairs + 1, dtype=np.float64)
    band_tau = frames[:, None] + row_times(band_centres(height, K), height, readout)[None]
    mid_tau = frames + float(row_times(np.array([mid_row(height)]), height, readout)[0])
    at_bands = (_interp_rows(band_tau.ravel(), GRID_STEPS, nodes) @ u).reshape(pairs + 1, K, C)
    at_mid = _interp_rows(mid_tau, GRID_STEPS, nodes) @ u
    return at_mid[:, None, :] - at_bands


def estimate_readout(motion: np.ndarray, height: int, weights: np.ndarray | None = None,
                     readouts: tuple[float, ...] = READOUTS) -> tuple[float, np.ndarray]:
    """The readout under which the bands' pair motions are samples of one smooth path: the
    least-squares cost of :func:`solve_path` over ``readouts``, its minimum refined by a
    parabola through the log costs around it; 0 (a global shutter) unless readout 0 costs
    ``GLOBAL_COST_RATIO`` times the best.  Returns (readout, costs)."""
    costs = np.array([solve_path(motion, r, height, weights)[1] for r in readouts])
    i = int(np.argmin(costs))
    if readouts[0] == 0.0 and costs[0] < GLOBAL_COST_RATIO * costs[i]:
        return 0.0, costs
    if i == 0 or i == len(costs) - 1:
        return float(readouts[i]), costs
    a, b, c = np.log(np.maximum(costs[i - 1:i + 2], 1e-300))
    bend = a - 2 * b + c
    shift = 0.5 * (a - c) / bend if bend > 0 else 0.0
    step = readouts[i + 1] - readouts[i]
    return float(np.clip(readouts[i] + np.clip(shift, -0.5, 0.5) * step, 0.0, 1.0)), costs


def undo_row_correction(table: np.ndarray, size: tuple[int, int], x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where the frame's own pixels are that a row correction moved to (x, y): ``table`` (h, 4)
    holds each row's correction channels (a similarity about the frame centre, small), looked up
    at the row (x, y) lies on and undone to first order (exact but for the correction's change
    over the pixel's few px of travel)."""
    w, h = size
    r = np.clip(np.rint(y), 0, h - 1).astype(np.intp)
    dx, dy, rot, sc = (table[r, i] for i in range(4))
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    # the correction moves row pixels by (dx + sc (x - cx) - rot (y - cy), ...); undo it
    return x - (dx + sc * (x - cx) - rot * (y - cy)), y - (dy + rot * (x - cx) + sc * (y - cy))

