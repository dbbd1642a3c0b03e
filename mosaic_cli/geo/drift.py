"""GPS and heights as a prior against the slow bending of long flights.

The similarity fit keeps the images' shape exactly; over a flight many frames long that shape
has bent a little (chained registrations drift), and the bending shows as a slow, smooth trend
in the GPS residuals.  Each keyframe gets a ground shift ``d_k`` minimising

    sum_k  w_k |p_k + d_k - g_k|^2 / s_gps^2  +  sum_k |b_(k-1) - b_k|^2 / s_k^2
                                            +  sum_(i,j) |d_i - d_j - e_ij (p_i - p_j)|^2 / s_ij^2

with ``b_k = d_(k+1) - d_k - e_k (p_(k+1) - p_k)``: the shifts may bend slowly along the flight
(second differences: a steady trend is free, a kink costs), and keyframes that see the same
ground again later (neighbouring survey lines, loops: drift control registered them to each
other) move together.  The images say where keyframes lie relative to each other to ``s`` (a
fraction of their distance), the GPS (with its robust weights w_k) where they lie.  GPS noise
correlated over a few seconds cannot bend the result: a shift has to be shared by many
keyframes' fixes, over many metres, before it outweighs the images.  What the shifts share
with a change of the whole map's scale and heading is taken off them: the global fit weighed
those against the height and the compass (on a short flight the GPS alone would take them).

The chained registrations also drift in scale: along a survey line the keyframes grow or
shrink by a few percent, and neighbouring lines shrink alike (the loops between them see no
difference), so neither the loops nor GPS noise of metres notice it.  A keyframe's height
does: ``h_k / f`` metres per pixel below it.  With heights, each keyframe also gets a log
scale ``e_k`` about its nadir point (``e_ij``, ``e_k`` above: the mean of the two linked),

    +  sum_k (e_k - r_k)^2 / s_h^2  +  sum_(k, k+1 and i, j) (e_i - e_j)^2 / s_e^2

where ``r_k`` is the log of the height's scale over the mosaic's at keyframe k, less its median
(the whole map's scale is the global fit's, prior.py: a barometer's offset is one figure for
the flight), ``s_h`` the heights' own scatter from keyframe to keyframe, and ``s_e`` how much the
images' scale may change between linked keyframes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mosaic_cli.geo.fit import SCATTER


@dataclass
class DriftOptions:
    link_fraction: float = 0.002  # how far the images may be off, as a fraction of the distance linked
    link_floor: float = 0.001  # metres
    correlation: float = 2.0  # seconds over which GPS errors are taken as one
    revisit: float = 10.0  # seconds: keyframes this far apart in time over the same ground are a revisit
    scale_step: float = 0.005  # relative: how much the images' scale may differ between linked keyframes
    height_floor: float = 0.001  # relative: the heights' scatter is never taken as smaller than this

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """No flag sets these: a bad value is a bug (ValueError), not the user's input."""
        if min(self.link_fraction, self.link_floor, self.correlation, self.revisit, self.scale_step, self.height_floor) <= 0:
            raise ValueError(f"drift options must be positive: {self}")


@dataclass
class DriftCorrection:
    shifts: np.ndarray  # (N, 2) metres
    scales: np.ndarray  # (N,) factors about each keyframe's nadir point (1: none)


class _Rows:
    """A sparse least-squares system assembled row by row (unknowns: dx, dy, then e)."""

    def __init__(self, n: int, with_scale: bool):
        self.n, self.with_scale = n, with_scale
        self.rows: list[int] = []
        self.cols: list[int] = []
        self.vals: list[float] = []
        self.rhs: list[float] = []

    def add(self, terms: dict[int, float], value: float, sigma: float) -> None:
        row = len(self.rhs)
        for col, coeff in terms.items():
            self.rows.append(row)
            self.cols.append(col)
            self.vals.append(coeff / sigma)
        self.rhs.append(value / sigma)

    def shift(self, k: int, axis: int) -> int:
        return axis * self.n + k

    def scale(self, k: int) -> int:
        return 2 * self.n + k

    def displacement(self, i: int, j: int, dp: np.ndarray, axis: int, sign: float = 1.0) -> dict[int, float]:
        """``sign`` x (d_i - d_j - e_ij dp) on ``axis``, as terms."""
        terms = {self.shift(i, axis): sign, self.shift(j, axis): -sign}
        if self.with_scale:
            for k in (i, j):
                terms[self.scale(k)] = terms.get(self.scale(k), 0.0) - sign * 0.5 * dp[axis]
        return terms

    def solve(self) -> np.ndarray:
        import scipy.sparse
        import scipy.sparse.linalg
        unknowns = (3 if self.with_scale else 2) * self.n
        A = scipy.sparse.csr_matrix((self.vals, (self.rows, self.cols)), shape=(len(self.rhs), unknowns))
        # normal equations, solved directly (an iterative solver stalls on the stiff bending terms)
        normal = (A.T @ A + 1e-9 * scipy.sparse.identity(unknowns)).tocsc()
        return np.asarray(scipy.sparse.linalg.spsolve(normal, A.T @ np.asarray(self.rhs)))


def drift_correction(
    positions: np.ndarray,  # (N, 2) keyframe nadir points on the ground after the global fit
    fixes: np.ndarray,  # (N, 2) GPS positions (NaN: none)
    weights: np.ndarray,  # (N,) robust weights of the fixes (0: outlier or none)
    times: np.ndarray,  # (N,) seconds
    footprint: float,  # metres: the keyframes' ground footprint size (for overlap)
    gps_sigma: float,
    options: DriftOptions | None = None,
    height_scales: np.ndarray | None = None,  # (N,) log(height's metres per pixel / the mosaic's) (NaN: none)
) -> DriftCorrection:
    """Per-keyframe ground shifts, and with ``height_scales`` scales (module doc)."""
    from scipy.spatial import cKDTree
    o = options or DriftOptions()
    n = len(positions)
    has = np.isfinite(fixes).all(1) & (weights > 0)
    if n < 3 or has.sum() < 3:
        return DriftCorrection(np.zeros((n, 2)), np.ones(n))
    heights = _centred(height_scales, n)
    system = _Rows(n, heights is not None)
    # GPS errors correlate over o.correlation: fixes within that time share one fix's weight
    t = times[has]
    per_window = np.array([np.sum(np.abs(t - ti) <= o.correlation) for ti in t], dtype=float)
    for k, weight, count in zip(np.nonzero(has)[0], weights[has], per_window):
        sigma = gps_sigma * float(np.sqrt(count / weight))
        for axis in range(2):
            system.add({system.shift(int(k), axis): 1.0}, float(fixes[k, axis] - positions[k, axis]), sigma)
    # consecutive keyframes: the shift may bend slowly (a second difference per triple) ...
    for i in range(1, n - 1):
        dist = float(np.linalg.norm(positions[i + 1] - positions[i - 1]))
        sigma = max(o.link_floor, o.link_fraction * dist)
        for axis in range(2):
            terms = system.displacement(i + 1, i, positions[i + 1] - positions[i], axis)
            for col, coeff in system.displacement(i, i - 1, positions[i] - positions[i - 1], axis, -1.0).items():
                terms[col] = terms.get(col, 0.0) + coeff
            system.add(terms, 0.0, sigma)
    # ... and keyframes over the same ground seen again later (neighbouring lines, loops: drift
    # control registered them to each other) move together
    revisits = [(i, j) for i, j in sorted(cKDTree(positions).query_pairs(0.5 * footprint)) if abs(times[i] - times[j]) >= o.revisit]
    for i, j in revisits:
        dist = float(np.linalg.norm(positions[i] - positions[j]))
        sigma = max(o.link_floor, o.link_fraction * dist)
        for axis in range(2):
            system.add(system.displacement(i, j, positions[i] - positions[j], axis), 0.0, sigma)
    if heights is not None:
        scatter = _height_scatter(heights, o)
        for k in np.nonzero(np.isfinite(heights))[0]:
            system.add({system.scale(int(k)): 1.0}, float(heights[k]), scatter)
        for i, j in [(k, k + 1) for k in range(n - 1)] + revisits:
            system.add({system.scale(i): 1.0, system.scale(j): -1.0}, 0.0, o.scale_step)
    solution = system.solve()
    shifts = _without_similarity(np.stack([solution[:n], solution[n : 2 * n]], 1), positions)
    scales = np.exp(solution[2 * n :]) if heights is not None else np.ones(n)
    return DriftCorrection(shifts, scales)


def _without_similarity(shifts: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """The shifts less the change of scale and heading about the keyframes' centre that fits
    them best.  The global fit owns the map's scale and heading, weighing the GPS against the
    height and the compass; a steady trend along the flight costs the bending terms nothing,
    so without this the shifts would hand them to the GPS alone (on a short flight, its noise)."""
    z = positions[:, 0] + 1j * positions[:, 1]
    z = z - z.mean()
    if not np.any(z):
        return shifts
    d = shifts[:, 0] + 1j * shifts[:, 1]
    design = np.stack([np.ones_like(z), z], 1)
    (_, turn), *_ = np.linalg.lstsq(design, d, rcond=None)
    trend = turn * z
    return shifts - np.stack([trend.real, trend.imag], 1)


def _centred(height_scales: np.ndarray | None, n: int) -> np.ndarray | None:
    """The heights' log scales less their median (the global fit owns the map's scale); None
    when fewer than three keyframes have one."""
    if height_scales is None:
        return None
    r = np.asarray(height_scales, np.float64).reshape(n)
    known = np.isfinite(r)
    if known.sum() < 3:
        return None
    return r - float(np.median(r[known]))


def _height_scatter(heights: np.ndarray, o: DriftOptions) -> float:
    """The heights' own scatter from one keyframe to the next (robust; relative): what the
    barometer's noise leaves in each keyframe's scale, the slow changes the images' drift."""
    r = heights[np.isfinite(heights)]
    steps = np.abs(np.diff(r))
    return max(SCATTER * float(np.median(steps)) / math.sqrt(2.0), o.height_floor)
