"""Smoothers: from the camera's frame-to-frame motion to the stabilised view of every frame.

Both return ``V`` (N, 3, 3): for each frame, the map from normalised output coordinates to
normalised coordinates of the input frame (see :mod:`.crop`).

* :class:`L1Smoother` is Grundmann, Kwatra and Essa's L1-optimal camera path (CVPR 2011): the
  update transforms B_t (the crop window placed in frame t) minimise
  w1|D P| + w2|D^2 P| + w3|D^3 P| of the smoothed path P_t = C_t B_t, where
  D P_t ~ R_t = F_{t+1} B_{t+1} - B_t, subject to the crop window staying inside every frame.
  It is a linear program (HiGHS), solved over overlapping windows of frames whose first three
  transforms are fixed to the previous window's solution, so time and memory per frame stay
  bounded however long the video is.
* :class:`GaussianSmoother` averages, for each frame, where its neighbours' corners lie in its
  own coordinates (Gaussian weights), and crops by one static zoom chosen so that no border
  shows (as vid.stab's ``optzoom=1``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # scipy is imported where it is used: a live stabilize listens sooner (python -m benchmarks live listen --cold)
    import scipy.sparse as sp

from mosaic_cli.errors import BadInput, ProcessingError
from mosaic_cli.geometry import four_point_to_homography
from mosaic_cli.stabilize.crop import largest_inside_zoom, rect_corners_normalized, zoom_matrix, zoomed
from mosaic_cli.stabilize.path import (
    MODELS,
    MotionModel,
    fit_model,
    gated_motion,
    gaussian_weights,
    neighbour_mean,
    normalized_frame_rect,
    perspective_support,
    supported_motion,
)

SMOOTHERS = ("l1", "gaussian")
# Boundary transforms fixed from the previous window: enough to carry D, D^2 and D^3 across.
CARRIED = 3


@dataclass
class L1Smoother:
    """Options of the L1-optimal path.  Costs are per frame, in normalised units."""

    # |D|, |D^2|, |D^3|.  Grundmann et al. use (10, 1, 100); in normalised units a jerk weight
    # of 3000 leaves 0.017-0.051 of the shake on the benchmark flights where 100 leaves
    # 0.048-0.075 (docs/measurements/stabilize.md): an L1 path's jerks are what a viewer still sees as shake.
    weights: tuple[float, float, float] = (10.0, 1.0, 3000.0)
    window: int = 120  # frames per linear program (4 s at 30 fps: time enough to plan ahead)
    overlap: int = 40  # frames re-solved by the next window (only the first part is kept)
    zoom_cost: float = 1.0  # per frame and unit of zoom: keeps the crop as large as it can be
    # With a crop ratio the user fixed, the zoom stays put and a border costs this per frame and
    # unit: none shows while the margin suffices; at --crop 1 a thin one (a few px) does.
    border_cost: float = 100.0
    fixed_zoom_cost: float = 1e4
    hard_border_cost: float = 1e4  # the same with --crop auto: in effect a hard constraint
    max_zoom: float = 1.25  # --crop auto never zooms in further than this
    max_rotation: float = 0.15  # radians of correction
    max_shift: float = 0.5  # normalised units of correction (0.5 = a quarter of the width)
    max_anisotropy: float = 0.02  # |a - d| and |b + c| of affine and homography corrections
    max_perspective: float = 0.05  # |g|, |h| of homography corrections (normalised)
    # |g|, |h| of the tilt model's corrections (angle / focal length, normalised): a pitch or roll of
    # 0.6 degrees at a 90-degree field of view, 1.1 at 53 degrees (the simulator's)
    max_tilt: float = 0.01
    # per frame and unit of |g|, |h| of the tilt model's corrections: none where the camera's
    # motion has no perspective shake (it would only buy a larger crop)
    tilt_cost: float = 10.0
    # HiGHS's interior point method is the faster on the long offline windows; the dual simplex
    # on the short windows of a live path (stabilize/online.py).
    method: str = "highs-ipm"

    def smooth(self, motion: np.ndarray, size: tuple[int, int], model: MotionModel, crop: float | None,
               advance: Callable[[int], None] | None = None) -> np.ndarray:
        """``motion`` (N-1, 3, 3): F_{t+1}, frame t+1 -> frame t, normalised (see path.py);
        ``advance(n)`` is told of every n frames whose view is settled."""
        planner = self.planner(size, model, crop)
        views = [planner.push(motion), planner.finish()]
        if advance:
            advance(sum(len(v) for v in views))
        return np.concatenate(views)

    def planner(self, size: tuple[int, int], model: MotionModel, crop: float | None) -> L1Planner:
        """The path planned as the motions arrive (:class:`L1Planner`)."""
        if self.window < 2 * CARRIED + 2 or not 0 <= self.overlap < self.window - CARRIED:
            raise BadInput("the L1 window must hold at least 8 frames and exceed the overlap by 3")
        return L1Planner(self, size, model, crop)


class L1Planner:
    """The L1 path of :class:`L1Smoother`, a window at a time as the motions arrive.

    A window's program sees only its own motions and the previous window's last transforms, so
    the views a window settles are final as soon as its last motion is known: a video's render
    can start while the rest is still being tracked, with the views a plan of the whole clip
    gives (:meth:`L1Smoother.smooth` is this planner fed everything at once)."""

    def __init__(self, options: L1Smoother, size: tuple[int, int], model: MotionModel, crop: float | None):
        self.options, self.size, self.model, self.crop = options, size, model, crop
        self._motion: list[np.ndarray] = []  # F_{t+1}, normalised, in the model
        self._params: list[np.ndarray] = []  # the settled frames' parameters of B_t
        self._start = 0  # the first frame of the next window
        self._last: tuple[int, np.ndarray] | None = None  # (start, solution) of the window solved last
        self.solve_seconds = 0.0

    def push(self, motion: np.ndarray) -> np.ndarray:
        """Take the next motions (M, 3, 3); return the views (K, 3, 3) they settle, in order."""
        self._motion.extend(np.asarray(motion, dtype=np.float64).reshape(-1, 3, 3))
        settled = len(self._params)
        window, overlap = self.options.window, self.options.overlap
        while len(self._motion) + 1 >= self._start + window:
            end = self._start + window
            solution = self._solve(end)
            keep = end - overlap
            self._settle(self._start, solution[:keep - self._start])
            self._last = (self._start, solution)
            self._start = keep - CARRIED
        return self._views(settled)

    def finish(self) -> np.ndarray:
        """The views of the frames left after the last motion."""
        settled = len(self._params)
        n_frames = len(self._motion) + 1
        if self._last is not None and self._last[0] + self.options.window == n_frames:
            self._settle(*self._last)  # the last window ended with the video: all of it stands
        else:
            self._settle(self._start, self._solve(n_frames))
        return self._views(settled)

    def _solve(self, end: int) -> np.ndarray:
        start = self._start
        fixed = np.array(self._params[start:start + CARRIED]) if start > 0 else None
        clock = time.perf_counter()
        solution = solve_window(np.array(self._motion[start:end - 1]).reshape(-1, 3, 3), self.model, fixed, self.size,
                                self.crop, self.options)
        self.solve_seconds += time.perf_counter() - clock
        return solution

    def _settle(self, start: int, solution: np.ndarray) -> None:
        """Keep the rows of a window's ``solution`` (its first frame ``start``) not yet settled:
        the carried ones were, and the program held them to those values."""
        self._params.extend(solution[len(self._params) - start:])

    def _views(self, since: int) -> np.ndarray:
        if len(self._params) == since:
            return np.zeros((0, 3, 3))
        ratio = 1.0 if self.crop is None else self.crop
        return self.model.matrices(np.array(self._params[since:])) @ zoom_matrix(ratio)


def _difference(n: int, order: int) -> sp.csr_matrix:
    """The (n - order, n) forward-difference operator of the given order."""
    import scipy.sparse as sp
    D = sp.identity(n, format="csr")
    for _ in range(order):
        m = D.shape[0]
        D = (sp.eye(m - 1, m, k=1) - sp.eye(m - 1, m)) @ D
    return D.tocsr()


def _bounds(model: MotionModel, crop: float | None, opts: L1Smoother) -> list[tuple[float, float]]:
    top_scale = 1.0 if crop is None else 1.0 / crop  # never look beyond the frame edge
    limits = {
        "scale": (1.0 / opts.max_zoom, top_scale),
        "rotation": (-opts.max_rotation - opts.max_anisotropy, opts.max_rotation + opts.max_anisotropy),
        "shift": (-opts.max_shift, opts.max_shift),
        "perspective": (-opts.max_tilt, opts.max_tilt) if model.gated else (-opts.max_perspective, opts.max_perspective),
    }
    return [limits[kind] for kind in model.kinds]


class _Program:
    """A linear program assembled from blocks of variables and sparse constraint blocks."""

    def __init__(self) -> None:
        self.costs: list[np.ndarray] = []
        self.bounds: list[tuple[float | None, float | None]] = []
        self.rows: dict[str, list] = {"ub": [], "eq": []}
        self.size = 0

    def variables(self, n: int, cost, bounds=(0.0, None)) -> slice:
        """``n`` new variables with per-variable ``cost`` and one (lo, hi) or a list of them."""
        self.costs.append(np.broadcast_to(np.asarray(cost, dtype=np.float64), (n,)))
        self.bounds += list(bounds) if isinstance(bounds, list) else [bounds] * n
        block = slice(self.size, self.size + n)
        self.size += n
        return block

    def at_most(self, terms: list[tuple[slice, sp.spmatrix]], rhs: np.ndarray) -> None:
        """sum of block @ variables <= rhs."""
        self.rows["ub"].append((terms, np.asarray(rhs, dtype=np.float64)))

    def equal(self, terms: list[tuple[slice, sp.spmatrix]], rhs: np.ndarray) -> None:
        self.rows["eq"].append((terms, np.asarray(rhs, dtype=np.float64)))

    def _matrix(self, kind: str):
        import scipy.sparse as sp
        if not self.rows[kind]:
            return None, None
        mats = []
        for terms, rhs in self.rows[kind]:
            m = sp.csr_matrix((len(rhs), self.size))
            for block, coef in terms:
                m = m + sp.hstack([sp.csr_matrix((len(rhs), block.start)), sp.csr_matrix(coef),
                                   sp.csr_matrix((len(rhs), self.size - block.stop))], format="csr")
            mats.append(m)
        return sp.vstack(mats, format="csr"), np.concatenate([rhs for _, rhs in self.rows[kind]])

    def solve(self, method: str = "highs-ipm") -> np.ndarray:
        from scipy.optimize import linprog
        A_ub, b_ub = self._matrix("ub")
        A_eq, b_eq = self._matrix("eq")
        problem = dict(c=np.concatenate(self.costs), A_ub=A_ub, b_ub=b_ub, A_eq=A_eq, b_eq=b_eq, bounds=self.bounds)
        # The method asked for first (L1Smoother.method); the dual simplex the fallback.
        result = linprog(method=method, **problem)
        if result.status != 0 or result.x is None:
            result = linprog(method="highs-ds", **problem)
        if result.status != 0 or result.x is None:
            raise ProcessingError(f"the L1 camera path could not be solved ({result.message})")
        return result.x


def solve_window(motion: np.ndarray, model: MotionModel, fixed: np.ndarray | None, size: tuple[int, int],
                  crop: float | None, opts: L1Smoother) -> np.ndarray:
    """One linear program over L = len(motion) + 1 frames; returns (L, K) parameters of B_t."""
    import scipy.sparse as sp
    L, K = len(motion) + 1, model.n_params
    if L == 1:
        return model.identity[None].copy() if fixed is None else fixed[:1].copy()
    tilt = [k for k, kind in enumerate(model.kinds) if kind == "perspective"] if model.gated else []
    if model.gated:  # the camera's perspective shake as far as the estimates support it
        support = perspective_support(motion)
        if support == 0 and (fixed is None or not np.any(fixed[:, tilt])):
            # none: the similarity's own program (the tilt model's first parameters are a similarity's)
            similar = MODELS["similarity"]
            params = solve_window(fit_model(motion, similar), similar, None if fixed is None else fixed[:, :similar.n_params],
                                  size, crop, opts)
            return np.pad(params, ((0, 0), (0, K - similar.n_params)))
        motion = supported_motion(motion, model, support)
    explicit = crop is not None
    scale = model.scale_weights()
    lp = _Program()

    bounds = _bounds(model, crop, opts) * L
    if fixed is not None:  # the previous window's last transforms: the path continues from them
        for t, values in enumerate(fixed[:L]):
            bounds[t * K:(t + 1) * K] = [(float(v), float(v)) for v in values]
    # With --crop auto every frame pays for its zoom: the crop stays as large as the shake allows.
    p = lp.variables(L * K, 0.0 if explicit else -opts.zoom_cost * np.tile(scale, L), bounds)

    # |D^n P| as the sum of a positive and a negative part: D^n (R p + r0) = pos - neg.
    for operator, constant, weight in _derivatives(motion, model, opts.weights):
        m = len(constant)
        pos, neg = lp.variables(m, weight), lp.variables(m, weight)
        lp.equal([(p, operator), (pos, -sp.identity(m)), (neg, sp.identity(m))], -constant)

    coef, const = _inclusion(model, size, 1.0 if crop is None else crop)
    z = lp.variables(L, opts.border_cost if explicit else opts.hard_border_cost)  # border shown in frame t
    lp.at_most([(p, sp.kron(sp.identity(L), coef)), (z, sp.kron(sp.identity(L), np.ones((len(coef), 1))) * -1)],
               -np.tile(const, L))

    shape = _similarity_rows(model)
    if shape is not None:  # affine corrections close to a similarity: what the distortion score sees
        lp.at_most([(p, sp.kron(sp.identity(L), shape))], np.full(L * len(shape), opts.max_anisotropy))

    if tilt:  # v >= |g|, |h| of each correction, paid for
        v = lp.variables(L * len(tilt), opts.tilt_cost)
        pick = sp.csr_matrix((np.ones(len(tilt)), (np.arange(len(tilt)), tilt)), shape=(len(tilt), K))
        rows, eye = sp.kron(sp.identity(L), pick), sp.identity(L * len(tilt))
        lp.at_most([(p, rows), (v, -eye)], np.zeros(L * len(tilt)))
        lp.at_most([(p, -rows), (v, -eye)], np.zeros(L * len(tilt)))

    if explicit:  # the zoom stays at the ratio the user chose: u >= |scale - 1|
        u = lp.variables(L, opts.fixed_zoom_cost)
        scale_rows, eye = sp.kron(sp.identity(L), scale[None, :]), sp.identity(L)
        lp.at_most([(p, scale_rows), (u, -eye)], np.ones(L))
        lp.at_most([(p, -scale_rows), (u, -eye)], -np.ones(L))

    params = lp.solve(opts.method)[p].reshape(L, K)
    if tilt:  # the solver's round-off (1e-11) would send every frame to the slower perspective warp
        params[:, tilt] = np.where(np.abs(params[:, tilt]) < 1e-9, 0.0, params[:, tilt])
    return params


def _derivatives(motion: np.ndarray, model: MotionModel, weights) -> list[tuple[sp.csr_matrix, np.ndarray, np.ndarray]]:
    """(operator on the parameters p, constant, weight per row) of the path's D, D^2 and D^3.

    R_j = F_{j+1} M(p_{j+1}) - M(p_j) over the compared entries is linear in p:
    A_j p_{j+1} - P p_j + r0_j.  D^2 and D^3 are its first and second differences."""
    import scipy.sparse as sp
    L, K = len(motion) + 1, model.n_params
    rows_e = np.array([r for r, _ in model.entries])
    cols_e = np.array([c for _, c in model.entries])
    E = len(rows_e)
    entry_weights = np.ones(E) if model.entry_weights is None else np.asarray(model.entry_weights)
    A = np.einsum("jrm,kmc->jrck", motion, model.basis)[:, rows_e, cols_e, :]  # (L-1, E, K)
    P = model.basis[:, rows_e, cols_e].T  # (E, K)
    r0 = (motion @ model.offset)[:, rows_e, cols_e] - model.offset[rows_e, cols_e]  # (L-1, E)
    j, e, k = np.meshgrid(np.arange(L - 1), np.arange(E), np.arange(K), indexing="ij")
    R = sp.coo_matrix(
        (np.concatenate([A.ravel(), np.broadcast_to(-P, A.shape).ravel()]),
         (np.concatenate([(j * E + e).ravel()] * 2), np.concatenate([((j + 1) * K + k).ravel(), (j * K + k).ravel()]))),
        shape=((L - 1) * E, L * K),
    ).tocsr()
    terms = []
    for order, weight in enumerate(weights):
        if L - 1 - order <= 0:
            continue
        D = sp.kron(_difference(L - 1, order), sp.identity(E), format="csr")
        terms.append((D @ R, D @ r0.ravel(), weight * np.tile(entry_weights, D.shape[0] // E)))
    return terms


def _inclusion(model: MotionModel, size: tuple[int, int], ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """(16, K) coefficients and (16,) constants with ``coef @ p + const <= 0`` exactly when the
    four corners of the crop window, through M(p), lie inside the frame.  For a homography
    x' = num / den with den > 0, so lo <= x' <= hi is linear: lo den <= num <= hi den."""
    x0, y0, x1, y1 = normalized_frame_rect(size)
    corners = np.concatenate([ratio * rect_corners_normalized(size), np.ones((4, 1))], axis=1)  # (4, 3)
    den = np.einsum("kc,ic->ik", model.basis[:, 2, :], corners)
    den0 = corners @ model.offset[2]
    coef, const = [], []
    for row, lo, hi in ((0, x0, x1), (1, y0, y1)):
        num = np.einsum("kc,ic->ik", model.basis[:, row, :], corners)
        num0 = corners @ model.offset[row]
        coef += [num - hi * den, -num + lo * den]
        const += [num0 - hi * den0, -num0 + lo * den0]
    return np.concatenate(coef), np.concatenate(const)


def _similarity_rows(model: MotionModel) -> np.ndarray | None:
    """Rows bounding |a - d| and |b + c| (4, K), for models with two scale parameters."""
    kinds = list(model.kinds)
    if kinds.count("scale") != 2:
        return None
    a, d = [i for i, kind in enumerate(kinds) if kind == "scale"]
    b, c = [i for i, kind in enumerate(kinds) if kind == "rotation"]
    rows = np.zeros((4, model.n_params))
    rows[0, [a, d]] = (1, -1)
    rows[1, [a, d]] = (-1, 1)
    rows[2, [b, c]] = (1, 1)
    rows[3, [b, c]] = (-1, -1)
    return rows


@dataclass
class GaussianSmoother:
    """Each frame's view is the Gaussian-weighted mean of where its neighbours' corners lie
    (within ``radius`` frames, sigma = radius / 3); then one static zoom for the whole video
    that shows no border, unless the crop ratio is fixed."""

    radius: int = 30
    max_zoom: float = 1.25

    def smooth(self, motion: np.ndarray, size: tuple[int, int], model: MotionModel, crop: float | None,
               advance: Callable[[int], None] | None = None) -> np.ndarray:
        corners = rect_corners_normalized(size)
        motion = gated_motion(motion, model)
        smoothed = neighbour_mean(motion, corners, gaussian_weights(self.radius))
        V = fit_model(four_point_to_homography(corners, smoothed - corners), model)
        if crop is not None:
            if advance:
                advance(len(V))
            return V @ zoom_matrix(crop)
        zoom = float(largest_inside_zoom(V, size, smallest=1.0 / self.max_zoom).min())
        if advance:
            advance(len(V))
        return zoomed(V, zoom)


def make_smoother(name: str, radius: int = 30) -> L1Smoother | GaussianSmoother:
    name = name.lower()
    if name == "l1":
        return L1Smoother()
    if name == "gaussian":
        return GaussianSmoother(radius=radius)  # --radius: checked by StabilizeOptions
    raise BadInput(f"--smoothing must be one of {', '.join(SMOOTHERS)}, got {name!r}")


def load_solver() -> None:
    """Import the LP solver now rather than at the first solve: scipy.optimize's import is half
    a second of Python on a 2-core machine, holding the interpreter lock, and a live run that met
    it at its first window stalled every stage in its busiest seconds."""
    import scipy.optimize  # noqa: F401
