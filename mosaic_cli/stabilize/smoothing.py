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

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linprog

from mosaic_cli.errors import BadInput, ProcessingError
from mosaic_cli.geometry import four_point_to_homography
from mosaic_cli.stabilize.crop import largest_inside_zoom, rect_corners_normalized, zoom_matrix, zoomed
from mosaic_cli.stabilize.path import MotionModel, fit_model, gaussian_weights, neighbour_mean, normalized_frame_rect

SMOOTHERS = ("l1", "gaussian")
# Boundary transforms fixed from the previous window: enough to carry D, D^2 and D^3 across.
CARRIED = 3


@dataclass
class L1Smoother:
    """Options of the L1-optimal path.  Costs are per frame, in normalised units."""

    weights: tuple[float, float, float] = (10.0, 1.0, 100.0)  # |D|, |D^2|, |D^3| (Grundmann et al.)
    window: int = 120  # frames per linear program (4 s at 30 fps: time enough to plan ahead)
    overlap: int = 40  # frames re-solved by the next window (only the first part is kept)
    zoom_cost: float = 1.0  # per frame and unit of zoom: keeps the crop as large as it can be
    border_cost: float = 10.0  # per frame and unit of border, when the user fixed the crop ratio
    fixed_zoom_cost: float = 100.0  # per frame and unit of zoom away from a crop ratio the user fixed
    hard_border_cost: float = 1e4  # the same with --crop auto: in effect a hard constraint
    max_zoom: float = 1.25  # --crop auto never zooms in further than this
    max_rotation: float = 0.15  # radians of correction
    max_shift: float = 0.5  # normalised units of correction (0.5 = a quarter of the width)
    max_anisotropy: float = 0.02  # |a - d| and |b + c| of affine and homography corrections
    max_perspective: float = 0.05  # |g|, |h| of homography corrections (normalised)

    def smooth(self, motion: np.ndarray, size: tuple[int, int], model: MotionModel, crop: float | None) -> np.ndarray:
        """``motion`` (N-1, 3, 3): F_{t+1}, frame t+1 -> frame t, normalised (see path.py)."""
        n_frames = len(motion) + 1
        if self.window < 2 * CARRIED + 2 or not 0 <= self.overlap < self.window - CARRIED:
            raise BadInput("the L1 window must hold at least 8 frames and exceed the overlap by 3")
        params = np.empty((n_frames, model.n_params))
        start = 0
        while True:
            end = min(n_frames, start + self.window)
            fixed = params[start:start + CARRIED] if start > 0 else None
            solution = _solve_window(motion[start:end - 1], model, fixed, size, crop, self)
            if end == n_frames:
                params[start:end] = solution
                break
            keep = start + self.window - self.overlap
            params[start:keep] = solution[:keep - start]
            start = keep - CARRIED
        ratio = 1.0 if crop is None else crop
        return model.matrices(params) @ zoom_matrix(ratio)


def _difference(n: int, order: int) -> sp.csr_matrix:
    """The (n - order, n) forward-difference operator of the given order."""
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
        "perspective": (-opts.max_perspective, opts.max_perspective),
    }
    return [limits[kind] for kind in model.kinds]


def _solve_window(motion: np.ndarray, model: MotionModel, fixed: np.ndarray | None, size: tuple[int, int],
                  crop: float | None, opts: L1Smoother) -> np.ndarray:
    """One linear program over L = len(motion) + 1 frames; returns (L, K) parameters of B_t."""
    L, K = len(motion) + 1, model.n_params
    if L == 1:
        return model.identity[None].copy() if fixed is None else fixed[:1].copy()
    rows_e = np.array([r for r, _ in model.entries])
    cols_e = np.array([c for _, c in model.entries])
    E = len(rows_e)
    entry_weights = np.ones(E) if model.entry_weights is None else np.asarray(model.entry_weights)

    # R_j = F_{j+1} M(p_{j+1}) - M(p_j) = A_j p_{j+1} - P p_j + r0_j, over the compared entries.
    A = np.einsum("jrm,kmc->jrck", motion, model.basis)[:, rows_e, cols_e, :]  # (L-1, E, K)
    P = model.basis[:, rows_e, cols_e].T  # (E, K)
    r0 = (motion @ model.offset)[:, rows_e, cols_e] - model.offset[rows_e, cols_e]  # (L-1, E)
    j, e, k = np.meshgrid(np.arange(L - 1), np.arange(E), np.arange(K), indexing="ij")
    R = sp.coo_matrix(
        (np.concatenate([A.ravel(), np.broadcast_to(-P, A.shape).ravel()]),
         (np.concatenate([(j * E + e).ravel()] * 2), np.concatenate([((j + 1) * K + k).ravel(), (j * K + k).ravel()]))),
        shape=((L - 1) * E, L * K),
    ).tocsr()

    # |D^n P| as the sum of a positive and a negative part: D^n (R p + r0) = pos - neg, both >= 0.
    derivatives = []  # (operator on p, constant, weight per row) for D, D^2, D^3 of the path
    for order, weight in enumerate(opts.weights):
        if L - 1 - order <= 0:
            continue
        D = sp.kron(_difference(L - 1, order), sp.identity(E), format="csr")
        derivatives.append((D @ R, D @ r0.ravel(), weight * np.tile(entry_weights, D.shape[0] // E)))

    # Inclusion: every output corner, through B_j (and the fixed crop), inside frame j.
    ratio = 1.0 if crop is None else crop
    x0, y0, x1, y1 = normalized_frame_rect(size)
    corners = np.concatenate([ratio * rect_corners_normalized(size), np.ones((4, 1))], axis=1)  # (4, 3)
    coef, const = [], []
    for row, lo, hi in ((0, x0, x1), (1, y0, y1)):
        num = np.einsum("kc,ic->ik", model.basis[:, row, :], corners)
        den = np.einsum("kc,ic->ik", model.basis[:, 2, :], corners)
        num0, den0 = corners @ model.offset[row], corners @ model.offset[2]
        coef += [num - hi * den, -num + lo * den]  # num <= hi * den and num >= lo * den
        const += [num0 - hi * den0, -num0 + lo * den0]
    coef, const = np.concatenate(coef), np.concatenate(const)  # (16, K), (16,)
    Q = len(coef)
    frame_rows = sp.kron(sp.identity(L), sp.csr_matrix(coef), format="csr")

    # Keep affine corrections close to a similarity: that is what the distortion score sees.
    shape_rows = None
    kinds = list(model.kinds)
    if kinds.count("scale") == 2:
        a, d = [i for i, kind in enumerate(kinds) if kind == "scale"]
        b, c = [i for i, kind in enumerate(kinds) if kind == "rotation"]
        template = np.zeros((4, K))
        template[0, [a, d]] = (1, -1)
        template[1, [a, d]] = (-1, 1)
        template[2, [b, c]] = (1, 1)
        template[3, [b, c]] = (-1, -1)
        shape_rows = sp.kron(sp.identity(L, format="csr"), sp.csr_matrix(template))

    scale = model.scale_weights()
    explicit = crop is not None
    n_p = L * K
    n_slack = [2 * op.shape[0] for op, _, _ in derivatives]
    n_z = L
    n_u = L if explicit else 0
    n_total = n_p + sum(n_slack) + n_z + n_u

    cost = np.zeros(n_total)
    if not explicit:
        cost[:n_p] = -opts.zoom_cost * np.tile(scale, L)
    offset = n_p
    blocks, rhs = [], []
    eq_blocks, eq_rhs = [], []

    def columns(block: sp.spmatrix, at: int) -> sp.csr_matrix:
        """``block`` placed at column ``at`` of the full variable vector."""
        left = sp.csr_matrix((block.shape[0], at))
        right = sp.csr_matrix((block.shape[0], n_total - at - block.shape[1]))
        return sp.hstack([left, block, right], format="csr")

    for (op, c0, weight), m in zip(derivatives, n_slack):
        half = m // 2
        cost[offset:offset + m] = np.tile(weight, 2)
        eye = sp.identity(half, format="csr")
        eq_blocks.append(columns(op, 0) - columns(eye, offset) + columns(eye, offset + half))
        eq_rhs.append(-c0)
        offset += m
    z_at = offset
    cost[z_at:z_at + n_z] = opts.border_cost if explicit else opts.hard_border_cost
    blocks.append(columns(frame_rows, 0) - columns(sp.kron(sp.identity(L), np.ones((Q, 1)), format="csr"), z_at))
    rhs.append(-np.tile(const, L))
    if shape_rows is not None:
        blocks.append(columns(shape_rows, 0))
        rhs.append(np.full(shape_rows.shape[0], opts.max_anisotropy))
    if explicit:
        u_at = z_at + n_z
        cost[u_at:u_at + n_u] = opts.fixed_zoom_cost
        scale_rows = sp.kron(sp.identity(L), scale[None, :], format="csr")
        eye = sp.identity(L, format="csr")
        blocks += [columns(scale_rows, 0) - columns(eye, u_at), columns(-scale_rows, 0) - columns(eye, u_at)]
        rhs += [np.ones(L), -np.ones(L)]

    bounds = _bounds(model, crop, opts) * L + [(0.0, None)] * (n_total - n_p)
    if fixed is not None:
        for t, values in enumerate(fixed[:L]):
            for i, v in enumerate(values):
                bounds[t * K + i] = (float(v), float(v))
    problem = dict(A_ub=sp.vstack(blocks, format="csr"), b_ub=np.concatenate(rhs),
                   A_eq=sp.vstack(eq_blocks, format="csr"), b_eq=np.concatenate(eq_rhs), bounds=bounds)
    # The interior point method is the faster on these banded programs; simplex is the fallback.
    result = linprog(cost, method="highs-ipm", **problem)
    if result.status != 0 or result.x is None:
        result = linprog(cost, method="highs-ds", **problem)
    if result.status != 0 or result.x is None:
        raise ProcessingError(f"the L1 camera path could not be solved ({result.message})")
    return result.x[:n_p].reshape(L, K)


@dataclass
class GaussianSmoother:
    """Each frame's view is the Gaussian-weighted mean of where its neighbours' corners lie
    (within ``radius`` frames, sigma = radius / 3); then one static zoom for the whole video
    that shows no border, unless the crop ratio is fixed."""

    radius: int = 30
    max_zoom: float = 1.25

    def smooth(self, motion: np.ndarray, size: tuple[int, int], model: MotionModel, crop: float | None) -> np.ndarray:
        if self.radius < 1:
            raise BadInput(f"--radius must be at least 1, got {self.radius}")
        corners = rect_corners_normalized(size)
        smoothed = neighbour_mean(motion, corners, gaussian_weights(self.radius))
        V = fit_model(four_point_to_homography(corners, smoothed - corners), model)
        if crop is not None:
            return V @ zoom_matrix(crop)
        zoom = float(largest_inside_zoom(V, size, smallest=1.0 / self.max_zoom).min())
        return zoomed(V, zoom)


def make_smoother(name: str, radius: int = 30) -> L1Smoother | GaussianSmoother:
    name = name.lower()
    if name == "l1":
        return L1Smoother()
    if name == "gaussian":
        if radius < 1:
            raise BadInput(f"--radius must be at least 1, got {radius}")
        return GaussianSmoother(radius=radius)
    raise BadInput(f"--smoothing must be one of {', '.join(SMOOTHERS)}, got {name!r}")
