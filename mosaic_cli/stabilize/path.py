"""The camera path, as the smoothers see it: frame-to-frame motions in normalised coordinates,
reduced to the chosen motion model.

Normalised coordinates put the frame centre at the origin and divide by half the longer side,
so a 1280x720 frame spans [-1, 1] x [-0.5625, 0.5625].  In them a change of 0.01 in any matrix
entry (translation, linear or perspective) moves the frame corners by roughly 1% of the half
width, which lets the smoothers weigh all entries alike.  The scaling is isotropic, so a
similarity stays a similarity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.geometry import normalize, project


@dataclass(frozen=True)
class MotionModel:
    """A motion model as a linear parametrisation ``M(p) = M0 + sum_k p_k E_k`` of 3x3 matrices.

    ``entries`` are the matrix entries the smoothness terms compare; ``identity`` the
    parameters of the identity matrix.
    """

    name: str
    basis: np.ndarray  # (K, 3, 3)
    offset: np.ndarray  # (3, 3)
    identity: np.ndarray  # (K,)
    entries: tuple[tuple[int, int], ...]
    kinds: tuple[str, ...]  # per parameter: "scale", "rotation", "shift" or "perspective"
    projective: bool = False
    entry_weights: tuple[float, ...] | None = None  # default 1 per compared entry

    @property
    def n_params(self) -> int:
        return len(self.basis)

    def matrices(self, params: np.ndarray) -> np.ndarray:
        """(..., K) parameters -> (..., 3, 3) matrices."""
        return self.offset + np.einsum("...k,kij->...ij", np.asarray(params, dtype=np.float64), self.basis)

    def scale_weights(self) -> np.ndarray:
        """Weights w such that ``w @ p`` is the mean scale of the linear part, (a + d) / 2."""
        weights = np.zeros(self.n_params)
        for k, E in enumerate(self.basis):
            weights[k] = 0.5 * (E[0, 0] + E[1, 1])
        return weights


def _unit(i: int, j: int, value: float = 1.0) -> np.ndarray:
    E = np.zeros((3, 3))
    E[i, j] = value
    return E


_LIFT = np.diag([0.0, 0.0, 1.0])
_TOP = ((0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2))

MODELS: dict[str, MotionModel] = {
    "similarity": MotionModel(
        "similarity",
        np.stack([_unit(0, 0) + _unit(1, 1), _unit(1, 0) - _unit(0, 1), _unit(0, 2), _unit(1, 2)]),
        _LIFT,
        np.array([1.0, 0.0, 0.0, 0.0]),
        # a and b each fill two entries of the matrix: compare them once, weighted twice.
        ((0, 0), (1, 0), (0, 2), (1, 2)),
        ("scale", "rotation", "shift", "shift"),
        entry_weights=(2.0, 2.0, 1.0, 1.0),
    ),
    "affine": MotionModel(
        "affine",
        np.stack([_unit(i, j) for i, j in _TOP]),
        _LIFT,
        np.array([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]),
        _TOP,
        ("scale", "rotation", "shift", "rotation", "scale", "shift"),
    ),
    "homography": MotionModel(
        "homography",
        np.stack([_unit(i, j) for i, j in _TOP + ((2, 0), (2, 1))]),
        _LIFT,
        np.array([1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]),
        _TOP + ((2, 0), (2, 1)),
        ("scale", "rotation", "shift", "rotation", "scale", "shift", "perspective", "perspective"),
        projective=True,
    ),
}


def motion_model(name: str) -> MotionModel:
    try:
        return MODELS[name.lower()]
    except KeyError:
        raise BadInput(f"--model must be one of {', '.join(MODELS)}, got {name!r}") from None


def normalizer(size: tuple[int, int]) -> np.ndarray:
    """The matrix taking pixel coordinates of a (w, h) frame to normalised coordinates."""
    w, h = size
    s = max(w, h) / 2.0
    return np.array([[1 / s, 0, -(w - 1) / 2 / s], [0, 1 / s, -(h - 1) / 2 / s], [0, 0, 1.0]])


def normalized_frame_rect(size: tuple[int, int]) -> tuple[float, float, float, float]:
    """(x_min, y_min, x_max, y_max) of the whole frame (pixel edges) in normalised coordinates."""
    w, h = size
    s = max(w, h) / 2.0
    return (-w / 2 / s, -h / 2 / s, w / 2 / s, h / 2 / s)


def to_normalized(H: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Pixel-coordinate homographies (..., 3, 3) of frames of ``size`` -> normalised coordinates."""
    N = normalizer(size)
    return normalize(N @ np.asarray(H, dtype=np.float64) @ np.linalg.inv(N))


def fill_failed(pairwise: np.ndarray, confidence: np.ndarray | None) -> np.ndarray:
    """Replace failed estimates (confidence 0) by the nearest successful one.

    A failure reported as the identity would read as the drone stopping dead for one frame; the
    neighbour's motion is the better guess and keeps the path free of jumps."""
    pairwise = np.array(pairwise, dtype=np.float64).reshape(-1, 3, 3)
    if confidence is None or len(pairwise) == 0:
        return pairwise
    ok = np.asarray(confidence) > 0
    if ok.all() or not ok.any():
        return pairwise
    good = np.flatnonzero(ok)
    for t in np.flatnonzero(~ok):
        pairwise[t] = pairwise[good[np.argmin(np.abs(good - t))]]
    return pairwise


def fit_model(H: np.ndarray, model: MotionModel, grid: int = 5) -> np.ndarray:
    """The matrices of ``model`` closest (least squares over a grid of points spanning the
    normalised frame) to normalised homographies ``H`` (..., 3, 3)."""
    H = normalize(H)
    if model.projective:
        return H
    u = np.linspace(-1.0, 1.0, grid)
    pts = np.stack(np.meshgrid(u, 0.6 * u), axis=-1).reshape(-1, 2)
    dst = project(H, pts)  # (..., P, 2)
    homog = np.concatenate([pts, np.ones((len(pts), 1))], axis=1)
    # Design rows: the x and y of M(p) @ point for each basis matrix.
    cols = np.einsum("kij,pj->pik", model.basis[:, :2, :], homog)  # (P, 2, K)
    A = cols.reshape(-1, model.n_params)
    offset = np.einsum("ij,pj->pi", model.offset[:2, :], homog).reshape(-1)
    rhs = dst.reshape(*dst.shape[:-2], -1) - offset
    params = np.linalg.lstsq(A, rhs.reshape(-1, A.shape[0]).T, rcond=None)[0].T
    return model.matrices(params.reshape(*H.shape[:-2], model.n_params))


def camera_motion(pairwise: np.ndarray, size: tuple[int, int], model: MotionModel,
                  confidence: np.ndarray | None = None) -> np.ndarray:
    """(N-1, 3, 3): the motion from frame t+1 back to frame t in normalised coordinates,
    reduced to ``model``.  This is Grundmann et al.'s F_{t+1}; the camera path is their chain."""
    forward = fill_failed(pairwise, confidence)
    if len(forward) == 0:
        return np.zeros((0, 3, 3))
    backward = np.linalg.inv(to_normalized(forward, size))
    return fit_model(backward, model)


def gaussian_weights(radius: int, sigma: float | None = None) -> np.ndarray:
    """Normalised Gaussian weights over offsets -radius..radius (sigma = radius / 3 by default)."""
    sigma = radius / 3.0 if sigma is None else sigma
    w = np.exp(-0.5 * (np.arange(-radius, radius + 1) / max(sigma, 1e-9)) ** 2)
    return w / w.sum()


def neighbour_mean(motion: np.ndarray, points: np.ndarray, weights: np.ndarray, block: int = 256) -> np.ndarray:
    """(N, P, 2): for every frame t, the weighted sum (weights summing to 1) of the positions
    of ``points`` (P, 2) in frames t-r..t+r, seen in frame t's own coordinates
    (r = len(weights) // 2).

    ``motion`` (N-1, 3, 3) maps frame t+1 -> frame t.  Positions are chained through an anchor
    frame shared by a block of frames, so chains stay short (well conditioned on long videos).
    Beyond either end of the video the path is mirrored through its end point, which keeps a
    steady pan steady instead of pulling the ends towards the middle."""
    n_frames = len(motion) + 1
    r = len(weights) // 2
    points = np.asarray(points, dtype=np.float64)
    out = np.empty((n_frames,) + points.shape)
    offsets = np.arange(-r, r + 1)
    for anchor in range(0, n_frames, block):
        stop = min(n_frames, anchor + block)
        lo, hi = max(0, anchor - r), min(n_frames, stop + r)
        to_anchor = _chain_to(motion, anchor, lo, hi)
        Q = project(to_anchor, points)  # (hi - lo, P, 2) in anchor coordinates
        s = np.arange(anchor, stop)[:, None] + offsets[None, :]  # (B, 2r + 1)
        below, above = s < 0, s > n_frames - 1
        mirror = np.where(below, -s, np.where(above, 2 * (n_frames - 1) - s, s)).clip(lo, hi - 1)
        pts = Q[mirror - lo]  # (B, 2r + 1, P, 2)
        if below.any():
            pts[below] = 2 * Q[0 - lo] - pts[below]
        if above.any():
            pts[above] = 2 * Q[n_frames - 1 - lo] - pts[above]
        mean = np.einsum("s,bspi->bpi", weights, pts)
        out[anchor:stop] = project(np.linalg.inv(to_anchor[anchor - lo:stop - lo]), mean)
    return out


def _chain_to(motion: np.ndarray, anchor: int, lo: int, hi: int) -> np.ndarray:
    """(hi - lo, 3, 3): frame s -> frame ``anchor`` for s in [lo, hi), from motion[t]: t+1 -> t."""
    out = np.empty((hi - lo, 3, 3))
    out[anchor - lo] = np.eye(3)
    for s in range(anchor + 1, hi):
        out[s - lo] = normalize(out[s - 1 - lo] @ motion[s - 1])
    for s in range(anchor - 1, lo - 1, -1):
        out[s - lo] = normalize(out[s + 1 - lo] @ np.linalg.inv(motion[s]))
    return out
