"""GPS as a prior against the slow bending of long flights.

The similarity fit keeps the images' shape exactly; over a flight many frames long that shape
has bent a little (chained registrations drift), and the bending shows as a slow, smooth trend
in the GPS residuals.  Each keyframe gets a ground shift ``d_k`` minimising

    sum_k  w_k |p_k + d_k - g_k|^2 / s_gps^2  +  sum_k |d_(k-1) - 2 d_k + d_(k+1)|^2 / s_k^2
                                            +  sum_(i,j) |d_i - d_j|^2 / s_ij^2

the shifts may bend slowly along the flight (second differences: a steady trend is free, a
kink costs), and keyframes that see the same ground again later (neighbouring survey lines,
loops) move together.  The images say where keyframes lie relative to each other to ``s``
(a fraction of their distance), the GPS (with its robust weights w_k) where they lie.  GPS noise
correlated over a few seconds cannot bend the result: a shift has to be shared by many
keyframes' fixes, over many metres, before it outweighs the images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
from scipy.spatial import cKDTree


@dataclass
class DriftOptions:
    link_fraction: float = 0.002  # how far the images may be off, as a fraction of the distance linked
    link_floor: float = 0.001  # metres
    correlation: float = 2.0  # seconds over which GPS errors are taken as one
    revisit: float = 10.0  # seconds: keyframes this far apart in time over the same ground are a revisit

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """No flag sets these: a bad value is a bug (ValueError), not the user's input."""
        if min(self.link_fraction, self.link_floor, self.correlation, self.revisit) <= 0:
            raise ValueError(f"drift options must be positive: {self}")


def drift_shifts(
    positions: np.ndarray,  # (N, 2) keyframe nadir points on the ground after the global fit
    fixes: np.ndarray,  # (N, 2) GPS positions (NaN: none)
    weights: np.ndarray,  # (N,) robust weights of the fixes (0: outlier or none)
    times: np.ndarray,  # (N,) seconds
    footprint: float,  # metres: the keyframes' ground footprint size (for overlap)
    gps_sigma: float,
    options: DriftOptions | None = None,
) -> np.ndarray:
    """(N, 2) ground shifts, one per keyframe."""
    o = options or DriftOptions()
    n = len(positions)
    has = np.isfinite(fixes).all(1) & (weights > 0)
    if n < 3 or has.sum() < 3:
        return np.zeros((n, 2))
    # GPS errors correlate over o.correlation: fixes within that time share one fix's weight
    t = times[has]
    per_window = np.array([np.sum(np.abs(t - ti) <= o.correlation) for ti in t], dtype=float)
    w = np.zeros(n)
    w[has] = weights[has] / per_window / gps_sigma**2
    rows: list[int] = []
    cols: list[int] = []
    vals: list[float] = []
    rhs_weight: list[float] = []
    # consecutive keyframes: the shift may bend slowly (a second difference per triple) ...
    for i in range(1, n - 1):
        dist = float(np.linalg.norm(positions[i + 1] - positions[i - 1]))
        sigma = max(o.link_floor, o.link_fraction * dist)
        rows += [len(rhs_weight)] * 3
        cols += [i - 1, i, i + 1]
        vals += [1.0 / sigma, -2.0 / sigma, 1.0 / sigma]
        rhs_weight.append(0.0)
    # ... and keyframes over the same ground seen again later (neighbouring lines, loops: drift
    # control registered them to each other) move together
    for i, j in sorted(cKDTree(positions).query_pairs(0.5 * footprint)):
        if abs(times[i] - times[j]) < o.revisit:
            continue
        dist = float(np.linalg.norm(positions[i] - positions[j]))
        sigma = max(o.link_floor, o.link_fraction * dist)
        rows += [len(rhs_weight)] * 2
        cols += [i, j]
        vals += [1.0 / sigma, -1.0 / sigma]
        rhs_weight.append(0.0)
    A_links = scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(len(rhs_weight), n))
    idx = np.nonzero(has)[0]
    A_gps = scipy.sparse.csr_matrix((np.sqrt(w[idx]), (np.arange(len(idx)), idx)), shape=(len(idx), n))
    A = scipy.sparse.vstack([A_links, A_gps]).tocsr()
    # normal equations, solved directly (an iterative solver stalls on the stiff bending terms)
    normal = (A.T @ A + 1e-9 * scipy.sparse.identity(n)).tocsc()
    shifts = np.zeros((n, 2))
    for axis in range(2):
        b = np.concatenate([np.zeros(A_links.shape[0]), np.sqrt(w[idx]) * (fixes[idx, axis] - positions[idx, axis])])
        shifts[:, axis] = scipy.sparse.linalg.spsolve(normal, A.T @ b)
    return shifts
