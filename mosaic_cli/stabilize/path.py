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
    # The perspective terms of the camera's motion are taken only as far as the estimates
    # support them (:func:`perspective_support`); where they do not, the model is a similarity.
    gated: bool = False

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
    # A similarity and the perspective terms of a camera's pitch and roll (no shear, no stretch).
    "tilt": MotionModel(
        "tilt",
        np.stack([_unit(0, 0) + _unit(1, 1), _unit(1, 0) - _unit(0, 1), _unit(0, 2), _unit(1, 2), _unit(2, 0), _unit(2, 1)]),
        _LIFT,
        np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0]),
        ((0, 0), (1, 0), (0, 2), (1, 2), (2, 0), (2, 1)),
        ("scale", "rotation", "shift", "shift", "perspective", "perspective"),
        entry_weights=(2.0, 2.0, 1.0, 1.0, 1.0, 1.0),
        gated=True,
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
    if np.any(model.basis[:, 2, :]):
        return _fit_perspective(dst, homog, model)
    # Design rows: the x and y of M(p) @ point for each basis matrix.
    cols = np.einsum("kij,pj->pik", model.basis[:, :2, :], homog)  # (P, 2, K)
    A = cols.reshape(-1, model.n_params)
    offset = np.einsum("ij,pj->pi", model.offset[:2, :], homog).reshape(-1)
    rhs = dst.reshape(*dst.shape[:-2], -1) - offset
    params = np.linalg.lstsq(A, rhs.reshape(-1, A.shape[0]).T, rcond=None)[0].T
    return model.matrices(params.reshape(*H.shape[:-2], model.n_params))


def _fit_perspective(dst: np.ndarray, homog: np.ndarray, model: MotionModel) -> np.ndarray:
    """:func:`fit_model` for a model with perspective terms: the linear (algebraic) fit
    ``M(p)[0] . x - x' M(p)[2] . x = 0`` (and the same for y) over the grid points."""
    batch = dst.shape[:-2]
    d = dst.reshape(-1, len(homog), 2)  # (B, P, 2)
    top = np.einsum("kij,pj->pik", model.basis[:, :2, :], homog)  # (P, 2, K)
    bottom = np.einsum("kj,pj->pk", model.basis[:, 2, :], homog)  # (P, K)
    A = top[None] - d[..., None] * bottom[None, :, None, :]  # (B, P, 2, K)
    b = d * (homog @ model.offset[2])[None, :, None] - (homog @ model.offset[:2].T)[None]  # (B, P, 2)
    A, b = A.reshape(len(d), -1, model.n_params), b.reshape(len(d), -1)
    params = np.linalg.solve(np.einsum("bpk,bpl->bkl", A, A), np.einsum("bpk,bp->bk", A, b)[..., None])[..., 0]
    return normalize(model.matrices(params.reshape(*batch, model.n_params)))


def reduce_motion(H: np.ndarray, model: MotionModel) -> np.ndarray:
    """Normalised homographies ``H`` (..., 3, 3) as the smoother takes them: fitted to ``model``,
    or, for a gated model, whole (the smoother decides, a window at a time, how much of their
    perspective to believe: :func:`supported_motion`)."""
    return normalize(H) if model.gated else fit_model(H, model)


def camera_motion(pairwise: np.ndarray, size: tuple[int, int], model: MotionModel,
                  confidence: np.ndarray | None = None) -> np.ndarray:
    """(N-1, 3, 3): the motion from frame t+1 back to frame t in normalised coordinates,
    reduced to ``model`` (:func:`reduce_motion`).  This is Grundmann et al.'s F_{t+1}; the
    camera path is their chain."""
    forward = fill_failed(pairwise, confidence)
    if len(forward) == 0:
        return np.zeros((0, 3, 3))
    backward = np.linalg.inv(to_normalized(forward, size))
    return reduce_motion(backward, model)


# What tells a camera's pitch and roll shake from noise in the estimates' perspective terms.
SUPPORT_SIGMA = 9.0  # frames (0.3 s at 30 fps): the slow part of the motion, left out of the comparison
SUPPORT_RANGE = (0.05, 0.25)  # share of the perspective shake that moves with the shift: none taken / all taken
SUPPORT_MIN_FRAMES = 24  # fewer motions than this: a similarity


def perspective_support(motion: np.ndarray) -> float:
    """How far the perspective terms of ``motion`` (N, 3, 3, normalised) are to be believed, 0..1.

    A camera turning about its centre by a small pitch or roll shifts the view by f * angle and
    changes its perspective by -angle / f (f: the focal length, normalised): the perspective
    terms' shake (g, h) moves with the shift's (x, y) as g = c x, h = c y with one c = -1/f^2 < 0
    for both.  Noise of the estimates does not.  The support is the squared correlation of
    the two shakes (the share of the perspective shake that c x, c y explain; 0 when the best c
    is not negative), mapped from :data:`SUPPORT_RANGE` onto 0..1."""
    motion = np.asarray(motion, dtype=np.float64).reshape(-1, 3, 3)
    if len(motion) < SUPPORT_MIN_FRAMES:
        return 0.0
    motion = fit_model(motion, MODELS["tilt"])
    radius = int(np.ceil(3 * SUPPORT_SIGMA))
    weights = gaussian_weights(radius, SUPPORT_SIGMA)

    def shake(x: np.ndarray) -> np.ndarray:
        padded = np.concatenate([np.repeat(x[:1], radius, axis=0), x, np.repeat(x[-1:], radius, axis=0)])
        low = np.stack([np.convolve(padded[:, i], weights, mode="valid") for i in range(x.shape[1])], axis=1)
        return x - low

    shift, perspective = shake(motion[:, :2, 2]), shake(motion[:, 2, :2])
    sxx, syy, sxy = float(np.sum(shift ** 2)), float(np.sum(perspective ** 2)), float(np.sum(shift * perspective))
    if sxy >= 0 or sxx <= 0 or syy <= 0:
        return 0.0
    share = sxy ** 2 / (sxx * syy)
    lo, hi = SUPPORT_RANGE
    return float(np.clip((share - lo) / (hi - lo), 0.0, 1.0))


def supported_motion(motion: np.ndarray, model: MotionModel, support: float) -> np.ndarray:
    """``motion`` (N, 3, 3, normalised homographies) fitted to a gated ``model`` with its
    perspective taken at ``support`` (0..1): the similarity fit at 0, the model's own fit at 1,
    linear in the parameters between."""
    motion = np.asarray(motion, dtype=np.float64).reshape(-1, 3, 3)
    own = fit_model(motion, model)
    if support >= 1.0 or len(motion) == 0:
        return own
    basis = model.basis.reshape(model.n_params, 9).T
    own_p = np.linalg.lstsq(basis, (own - model.offset).reshape(-1, 9).T, rcond=None)[0].T
    base_p = np.linalg.lstsq(basis, (fit_model(motion, MODELS["similarity"]) - model.offset).reshape(-1, 9).T, rcond=None)[0].T
    return model.matrices(base_p + support * (own_p - base_p))


def gated_motion(motion: np.ndarray, model: MotionModel, window: int = 120) -> np.ndarray:
    """:func:`supported_motion` over a whole clip, each run of ``window`` motions with its own support
    (for smoothers without windows of their own)."""
    motion = np.asarray(motion, dtype=np.float64).reshape(-1, 3, 3)
    if not model.gated:
        return motion
    parts = [motion[k:k + window] for k in range(0, len(motion), window)]
    return np.concatenate([supported_motion(part, model, perspective_support(part)) for part in parts]) if parts else motion


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
