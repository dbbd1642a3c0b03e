"""A robust similarity fit: 2-D points (the mosaic's) onto noisy 2-D positions (GPS).

x' = a x - b y + tx,  y' = b x + a y + ty  (scale sqrt(a^2 + b^2), rotation atan2(b, a)).

Least median of squares over point pairs finds a start that bad fixes cannot pull; iteratively
reweighted least squares with Huber weights then uses every point in proportion to how well
it agrees, and the points beyond 3.5 robust sigmas are reported as outliers.  An optional
prior on the scale (from the altitude and field of view) and the rotation (from the compass),
each with its own uncertainty, enters as two equations weighed against the points by their
stated errors: it keeps the fit determined when the track is too short or too straight to fix
them itself, and counts for little where the track is long.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

HUBER = 1.345  # 95% efficiency under Gaussian noise


RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))  # median distance / per-axis sigma of 2-D Gaussian errors
SCATTER = 1.4826  # robust scatter = this x the median distance
OUTLIER = 3.5  # robust sigmas: a residual this far out is a bad fix, not noise


@dataclass
class SimilarityPrior:
    scale: float
    rotation: float | None  # radians; None: no heading known
    sigma: float | None  # relative uncertainty of the scale, e.g. 0.1 = 10%; None: no scale known
    rotation_sigma: float | None = None  # radians; None: as ``sigma`` (the same relative error of (a, b))

    @property
    def heading_sigma(self) -> float | None:
        return self.rotation_sigma if self.rotation_sigma is not None else self.sigma


def axis_sigma(scatter: float) -> float:
    """The per-axis sigma of 2-D Gaussian errors whose robust scatter (1.4826 x the median
    distance) is ``scatter``."""
    return scatter / SCATTER / RAYLEIGH_MEDIAN


def normaliser(points: np.ndarray) -> np.ndarray:
    """The similarity that moves ``points`` (N, 2) to their centroid and scales them to a root
    mean square distance of 1 from it: fitted parameters of order one, a well-conditioned DLT."""
    c = points.mean(0)
    s = float(np.sqrt(((points - c) ** 2).sum(1).mean())) or 1.0
    return np.array([[1 / s, 0, -c[0] / s], [0, 1 / s, -c[1] / s], [0, 0, 1.0]])


def robust_scatter(residuals: np.ndarray, floor: float) -> float:
    """SCATTER x the median of ``residuals`` (distances), at least ``floor`` (``floor`` when there are none)."""
    return max(floor, SCATTER * float(np.median(residuals))) if len(residuals) else floor


def huber_weights(residuals: np.ndarray, sigma: float = 1.0) -> np.ndarray:
    """Huber's weights of ``residuals`` (distances) in units of ``sigma``: 1 within HUBER sigmas, falling as 1/r beyond."""
    k = HUBER * sigma
    return np.where(residuals <= k, 1.0, k / np.maximum(residuals, 1e-12))


def robust_weights(residuals: np.ndarray, sigma: float) -> np.ndarray:
    """Huber's weights, and 0 beyond OUTLIER sigmas: bad fixes out, not merely down-weighted."""
    weights = huber_weights(residuals, sigma)
    weights[residuals > OUTLIER * sigma] = 0.0
    return weights


def fix_weights(times: np.ndarray, used: np.ndarray, correlation: float) -> np.ndarray:
    """What each fix in use is worth, as a share of one independent fix, when GPS errors are
    exponentially correlated over ``correlation`` seconds (a first-order Gauss-Markov process).
    Fixes ``dt`` apart are correlated by rho = exp(-dt / correlation); what n of them tell of a
    mean (or of a slow trend: a scale) is 1 + sum over the gaps of (1 - rho) / (1 + rho), the
    exact figure for such errors, and each fix gets half of each gap beside it (a missing gap,
    at the ends, counting 1).  Ten fixes in two seconds are worth about one; fixes far apart,
    one each.  0 for a fix not in use."""
    times = np.asarray(times, np.float64)
    out = np.zeros(len(times))
    idx = np.nonzero(used)[0]
    if len(idx) == 0:
        return out
    order = idx[np.argsort(times[idx])]
    rho = np.exp(-np.maximum(np.diff(times[order]), 0.0) / correlation)
    gap = (1.0 - rho) / (1.0 + rho)
    out[order] = 0.5 * (np.concatenate([[1.0], gap]) + np.concatenate([gap, [1.0]]))
    return out


def scale_sigma(points: np.ndarray, weights: np.ndarray, sigma: float) -> float:
    """Relative standard error of a similarity's scale fitted by weighted least squares to
    ``points`` (ground, (N, 2)) with per-axis error ``sigma`` and ``weights`` (each fix's
    worth, ``fix_weights``): sigma / sqrt(sum w |p - mean|^2)."""
    w = np.asarray(weights, np.float64)
    if w.sum() <= 0:
        return math.inf
    centred = points - (w[:, None] * points).sum(0) / w.sum()
    spread = float((w * (centred**2).sum(1)).sum())
    return sigma / math.sqrt(spread) if spread > 0 else math.inf


@dataclass
class SimilarityFit:
    matrix: np.ndarray  # 3x3, source -> target
    residuals: np.ndarray  # (N,) target units
    inliers: np.ndarray  # (N,) bool
    sigma: float  # robust scale of the inliers' residuals

    @property
    def scale(self) -> float:
        return float(math.hypot(self.matrix[0, 0], self.matrix[1, 0]))

    @property
    def rotation(self) -> float:
        return float(math.atan2(self.matrix[1, 0], self.matrix[0, 0]))


def _rows(src: np.ndarray) -> np.ndarray:
    """Design matrix of (a, b, tx, ty) for the stacked x' and y' equations."""
    n = len(src)
    A = np.zeros((2 * n, 4))
    A[0::2, 0], A[0::2, 1], A[0::2, 2] = src[:, 0], -src[:, 1], 1.0
    A[1::2, 0], A[1::2, 1], A[1::2, 3] = src[:, 1], src[:, 0], 1.0
    return A


def _matrix(p: np.ndarray) -> np.ndarray:
    a, b, tx, ty = p
    return np.array([[a, -b, tx], [b, a, ty], [0, 0, 1.0]])


def _residuals(p: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    M = _matrix(p)
    return np.linalg.norm(src @ M[:2, :2].T + M[:2, 2] - dst, axis=1)


def _solve(src: np.ndarray, dst: np.ndarray, weights: np.ndarray, prior: SimilarityPrior | None, sigma: float,
           rotation: float) -> np.ndarray:
    """Weighted least squares of (a, b, tx, ty): the points with per-axis error ``sigma``; the
    prior's scale as the length of (a, b) along ``rotation`` (the current estimate's direction:
    at convergence, the scale itself) and its heading as (a, b) across the prior's direction,
    each in units of its own error."""
    A = _rows(src)
    y = dst.reshape(-1)
    w = np.repeat(np.sqrt(weights), 2) / sigma
    A, y = A * w[:, None], y * w
    if prior is not None:
        along = np.array([math.cos(rotation), math.sin(rotation), 0.0, 0.0])
        heading = prior.rotation if prior.rotation is not None else rotation
        across = np.array([-math.sin(heading), math.cos(heading), 0.0, 0.0])
        rows, values = [], []
        if prior.sigma is not None:
            rows.append(along / max(prior.sigma * prior.scale, 1e-12))
            values.append(prior.scale / max(prior.sigma * prior.scale, 1e-12))
        if prior.rotation is not None and prior.heading_sigma is not None:
            rows.append(across / max(prior.heading_sigma * prior.scale, 1e-12))
            values.append(0.0)
        if rows:
            A = np.vstack([A, rows])
            y = np.concatenate([y, values])
    return np.linalg.lstsq(A, y, rcond=None)[0]


def _pair_similarity(s1: np.ndarray, s2: np.ndarray, d1: np.ndarray, d2: np.ndarray) -> np.ndarray | None:
    ds, dd = s2 - s1, d2 - d1
    n = ds @ ds
    if n < 1e-12:
        return None
    a = (ds @ dd) / n
    b = (ds[0] * dd[1] - ds[1] * dd[0]) / n
    tx = d1[0] - (a * s1[0] - b * s1[1])
    ty = d1[1] - (b * s1[0] + a * s1[1])
    return np.array([a, b, tx, ty])


def fit_similarity(
    src: np.ndarray, dst: np.ndarray, prior: SimilarityPrior | None = None, min_sigma: float = 0.05, seed: int = 0,
    times: np.ndarray | None = None, correlation: float = 2.0,
) -> SimilarityFit:
    """Robust similarity ``src`` -> ``dst`` ((N, 2) each, N >= 2).  With ``times`` (seconds) the
    fixes within ``correlation`` of each other share one fix's weight against the prior."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    n = len(src)
    if n < 2:
        raise ValueError("a similarity needs at least two points")
    # Centre both sets: the solve is better conditioned, and translations stay small.
    cs, cd = src.mean(0), dst.mean(0)
    s, d = src - cs, dst - cd

    # 1. least median of squares over pairs (all pairs when few, a deterministic sample else)
    rng = np.random.default_rng(seed)
    if n <= 40:
        pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    else:
        pairs = [tuple(rng.choice(n, 2, replace=False)) for _ in range(600)]
    best, best_score = None, np.inf
    spread = np.linalg.norm(s, axis=1).max()
    for i, j in pairs:
        if np.linalg.norm(s[i] - s[j]) < 0.2 * spread:  # short baselines: the angle is noise
            continue
        p = _pair_similarity(s[i], s[j], d[i], d[j])
        if p is None:
            continue
        score = np.median(_residuals(p, s, d))
        if score < best_score:
            best, best_score = p, score
    if best is None:
        best = _solve(s, d, np.ones(n), None, 1.0, 0.0)

    # 2. IRLS with Huber weights, the prior as two extra equations
    p = best
    for _ in range(30):
        r = _residuals(p, s, d)
        sigma = robust_scatter(r, min_sigma)
        weights = robust_weights(r, sigma)
        if times is not None:
            weights *= fix_weights(times, weights > 0, correlation)
        new = _solve(s, d, weights, prior, axis_sigma(sigma), math.atan2(p[1], p[0]))
        if np.allclose(new, p, rtol=1e-10, atol=1e-10):
            p = new
            break
        p = new
    r = _residuals(p, s, d)
    sigma = robust_scatter(r, min_sigma)
    inliers = r <= OUTLIER * sigma
    M = _matrix(p)
    # back from centred coordinates: x' = M (x - cs) + cd
    T_src = np.array([[1, 0, -cs[0]], [0, 1, -cs[1]], [0, 0, 1.0]])
    T_dst = np.array([[1, 0, cd[0]], [0, 1, cd[1]], [0, 0, 1.0]])
    return SimilarityFit(T_dst @ M @ T_src, r, inliers, sigma)


@dataclass
class HomographyFit:
    matrix: np.ndarray  # 3x3, source -> target
    residuals: np.ndarray
    inliers: np.ndarray
    sigma: float


def refine_homography(src: np.ndarray, dst: np.ndarray, min_sigma: float = 0.05, iterations: int = 30) -> HomographyFit:
    """A robust homography ``src`` -> ``dst`` (N >= 8), started from the identity: meant for
    points already brought close by a similarity, so that only the perspective left over by
    the images' drift remains to be fitted.  Huber-weighted DLT, fixes beyond 3.5 robust sigmas out."""
    from mosaic_cli.geometry import project, weighted_dlt

    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    N = normaliser(dst)
    scale = 1.0 / N[0, 0]  # target units per normalised unit
    s, d = project(N, src), project(N, dst)
    H = np.eye(3)
    for _ in range(iterations):
        r = np.linalg.norm(project(H, s) - d, axis=1) * scale
        weights = robust_weights(r, robust_scatter(r, min_sigma))
        new = weighted_dlt(s, d, weights, conditioned=True)  # (normalised above)
        if np.allclose(new, H, atol=1e-12):
            break
        H = new
    M = np.linalg.inv(N) @ H @ N
    M /= M[2, 2]
    r = np.linalg.norm(project(M, src) - dst, axis=1)
    sigma = robust_scatter(r, min_sigma)
    return HomographyFit(M, r, r <= OUTLIER * sigma, sigma)
