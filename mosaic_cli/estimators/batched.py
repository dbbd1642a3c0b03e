"""The learned estimator's polish and correlation check batched over a chunk's pairs in torch, on
any device: the counterpart of :func:`.refine.track_points` and :func:`.correlation.detail_zncc`,
with no host synchronisation until the caller reads the results.

* :func:`track` is OpenCV's pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK`` with
  ``OPTFLOW_USE_INITIAL_FLOW``, lkpyramid.cpp) step for step: the pyramid of ``pyrDown``
  (reflect-101 borders), the images padded by the window (reflect-101) and the Scharr
  derivatives by zeros, the window's samples in OpenCV's fixed point (14-bit bilinear weights,
  images at 5 fractional bits), the minimum-eigenvalue and out-of-image status, at most
  ``iterations`` Gauss-Newton steps a level, stopping at ``epsilon`` or halving an oscillating
  step.  Only the float sums are summed in another order (in float64 here), so tracks agree with
  OpenCV's to a small fraction of a pixel rather than to the bit.
* :func:`fit_homography` is the robust refit of ``cv2.findHomography(RANSAC)``: a fixed number of
  4-point hypotheses drawn from a seeded generator (the same on every device and run), the one
  with the most inliers, then the normalised DLT on its inliers and a Levenberg-Marquardt
  refinement of the reprojection error, as OpenCV finishes.
* :func:`detail_zncc` is :func:`.correlation.detail_zncc` for a batch of pairs, sampling as
  ``cv2.warpPerspective`` samples a float image (bilinear at the exact point, zero outside).
* :func:`polish` chains them as :func:`.refine.track_points` does, to its last check (the fit
  close to the seed and plausible, :func:`settled`).

Batch-first: B pairs, N points a pair (padded; ``counts`` says how many are real).  Images are
gray uint8 (or float holding uint8 values) of one working size.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from mosaic_cli.estimators.refine import PolishConfig
from mosaic_cli.geometry.tensor import four_point_homography, weighted_dlt

W_BITS = 14  # OpenCV's fixed-point bilinear weights (lkpyramid.cpp)
FLT_SCALE = 1.0 / (1 << 20)
MIN_EIGEN = 1e-4  # calcOpticalFlowPyrLK's default minEigThreshold
HYPOTHESES = 300  # RANSAC hypotheses of the refit (the CPU polish's cap: PolishConfig.max_iters)
SAMPLE_SEED = 0x5EED  # the refit's hypotheses: one fixed draw, the same on every device


def _reflect101(index: Tensor, size: int) -> Tensor:
    """``index`` folded into [0, size) as OpenCV's BORDER_REFLECT_101 (gfedcb|abcdefgh|gfedcba)."""
    if size == 1:
        return torch.zeros_like(index)
    period = 2 * size - 2
    i = torch.remainder(index, period)
    return torch.where(i >= size, period - i, i)


def _pad_reflect101(images: Tensor, pad: int) -> Tensor:
    """(B, h, w) -> (B, h + 2 pad, w + 2 pad), reflect-101 however large ``pad`` is."""
    _, h, w = images.shape
    rows = _reflect101(torch.arange(-pad, h + pad, device=images.device), h)
    cols = _reflect101(torch.arange(-pad, w + pad, device=images.device), w)
    return images[:, rows][:, :, cols]


def pyr_down(images: Tensor) -> Tensor:
    """``cv2.pyrDown`` of uint8 images held as float (B, h, w) -> (B, (h+1)//2, (w+1)//2): the 5x5
    binomial kernel over reflect-101 borders, rounded as OpenCV rounds ((sum + 128) >> 8)."""
    k = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0], dtype=torch.float32, device=images.device)
    kernel = (k[:, None] * k[None, :])[None, None]
    padded = _pad_reflect101(images.float(), 2)[:, None]
    total = F.conv2d(padded, kernel, stride=2)[:, 0]  # integer sums below 2^24: exact in float32
    return torch.floor((total + 128.0) / 256.0)


def scharr(images: Tensor) -> Tensor:
    """OpenCV's LK derivatives (calcSharrDeriv) of uint8 images held as float (B, h, w) ->
    (B, 2, h, w): x and y, the 3-10-3 smoothing and central difference, unscaled, reflect-101."""
    kx = torch.tensor([[-3.0, 0.0, 3.0], [-10.0, 0.0, 10.0], [-3.0, 0.0, 3.0]], device=images.device)
    kernel = torch.stack([kx, kx.t()])[:, None]
    return F.conv2d(_pad_reflect101(images.float(), 1)[:, None], kernel)


def pyramid_levels(size: tuple[int, int], window: int, levels: int) -> int:
    """The pyramid levels OpenCV uses above the frame (buildOpticalFlowPyramid stops before a
    level no wider or taller than the window)."""
    w, h = size
    for level in range(levels + 1):
        w, h = (w + 1) // 2, (h + 1) // 2
        if w <= window or h <= window:
            return level
    return levels


def _taps(flat: Tensor, index: Tensor, row: int, w: Tensor) -> Tensor:
    """Fixed-point bilinear samples: ``flat`` (B, L) int32 image rows of ``row`` values, ``index``
    (B, N, K) the top-left taps, ``w`` (B, N, 4) int32 weights -> (B, N, K) int32 sums."""
    B, N, K = index.shape
    index = index.clamp(0, flat.shape[1] - row - 2).reshape(B, N * K)
    total = torch.zeros(B, N * K, dtype=torch.int32, device=flat.device)
    for k, offset in enumerate((0, 1, row, row + 1)):
        total += flat.gather(1, index + offset) * w[:, :, k].repeat_interleave(K, 1)
    return total.view(B, N, K)


def _weights(frac: Tensor) -> Tensor:
    """OpenCV's 14-bit bilinear weights (B, N, 4) int32 from the fractions ``frac`` (B, N, 2) float32."""
    a, b = frac[..., 0], frac[..., 1]
    scale = float(1 << W_BITS)
    w00 = torch.round((1.0 - a) * (1.0 - b) * scale)
    w01 = torch.round(a * (1.0 - b) * scale)
    w10 = torch.round((1.0 - a) * b * scale)
    w11 = scale - w00 - w01 - w10
    return torch.stack([w00, w01, w10, w11], -1).to(torch.int32)


def _window_index(corner: Tensor, pad: int, row: int, offsets: Tensor) -> Tensor:
    """The flat indices (B, N, K) in an image padded by ``pad`` with rows of ``row`` values of the
    windows' taps ``offsets`` (K,) whose top-left pixels are ``corner`` (B, N, 2) long."""
    base = (corner[..., 1] + pad) * row + corner[..., 0] + pad
    return base[..., None] + offsets


def _outside(corner: Tensor, window: int, cols: int, rows: int) -> Tensor:
    """(B, N) bool: OpenCV's test that a window whose top-left pixel is ``corner`` has left a
    ``cols`` x ``rows`` image (the track is lost)."""
    x, y = corner[..., 0], corner[..., 1]
    return (x < -window) | (x >= cols) | (y < -window) | (y >= rows)


def track(prev: Tensor, cur: Tensor, points: Tensor, guess: Tensor, window: int, levels: int,
          iterations: int = 20, epsilon: float = 0.01, min_eigen: float = MIN_EIGEN) -> tuple[Tensor, Tensor]:
    """Track ``points`` (B, N, 2) of ``prev`` (B, h, w) into ``cur`` (B, h, w), starting at ``guess``
    (B, N, 2): ``cv2.calcOpticalFlowPyrLK(prev, cur, points, guess, winSize=(window, window),
    maxLevel=levels, criteria=(EPS | COUNT, iterations, epsilon), flags=OPTFLOW_USE_INITIAL_FLOW)``.
    Returns the tracks (B, N, 2) float32 and their status (B, N) bool: False where the window
    left the image or its gradients were ill-conditioned at the finest level."""
    B, h, w = prev.shape
    device = prev.device
    top = pyramid_levels((w, h), window, levels)
    prev_levels, cur_levels = [prev.float()], [cur.float()]
    for _ in range(top):
        prev_levels.append(pyr_down(prev_levels[-1]))
        cur_levels.append(pyr_down(cur_levels[-1]))
    points = points.float()
    half = (window - 1) * 0.5
    eps2 = float(np.float64(epsilon) ** 2)
    grid = torch.arange(window, device=device)
    status = torch.ones(points.shape[:2], dtype=torch.bool, device=device)
    nxt = guess.float() * (1.0 / (1 << top))
    for level in range(top, -1, -1):
        if level != top:
            nxt = nxt * 2.0
        I_img, J_img = prev_levels[level], cur_levels[level]
        rows, cols = I_img.shape[1:]
        pad = window
        row = cols + 2 * pad
        I_flat = _pad_reflect101(I_img, pad).to(torch.int32).flatten(1)
        J_flat = _pad_reflect101(J_img, pad).to(torch.int32).flatten(1)
        deriv = F.pad(scharr(I_img), (pad, pad, pad, pad)).to(torch.int32).flatten(2)  # zeros outside (BORDER_CONSTANT)
        offsets = (grid[:, None] * row + grid[None, :]).flatten()  # (K,) the window's taps, row by row
        index_of = partial(_window_index, pad=pad, row=row, offsets=offsets)
        outside = partial(_outside, window=window, cols=cols, rows=rows)
        prev_pt = points * (1.0 / (1 << level)) - half
        i_prev = torch.floor(prev_pt)
        lost = outside(i_prev)
        corner = i_prev.long()
        weights = _weights(prev_pt - i_prev)
        index = index_of(corner)
        I_win = (_taps(I_flat, index, row, weights) + (1 << (W_BITS - 6))) >> (W_BITS - 5)
        Ix = (_taps(deriv[:, 0], index, row, weights) + (1 << (W_BITS - 1))) >> W_BITS
        Iy = (_taps(deriv[:, 1], index, row, weights) + (1 << (W_BITS - 1))) >> W_BITS
        Ixd, Iyd = Ix.double(), Iy.double()
        A11 = (Ixd * Ixd).sum(-1).float() * FLT_SCALE
        A12 = (Ixd * Iyd).sum(-1).float() * FLT_SCALE
        A22 = (Iyd * Iyd).sum(-1).float() * FLT_SCALE
        D = A11 * A22 - A12 * A12
        min_eig = (A22 + A11 - torch.sqrt((A11 - A22) * (A11 - A22) + 4.0 * A12 * A12)) / (2 * window * window)
        weak = (min_eig < min_eigen) | (D < float(np.finfo(np.float32).eps))
        if level == 0:
            status &= ~lost & ~weak
        active = ~lost & ~weak
        D_inv = 1.0 / torch.where(active, D, torch.ones_like(D))
        pt = nxt - half  # the window's top-left corner, as OpenCV moves it
        prev_delta = torch.zeros_like(pt)
        for j in range(iterations):
            i_next = torch.floor(pt)
            gone = active & outside(i_next)
            if level == 0:
                status &= ~gone
            active = active & ~gone
            J_win = (_taps(J_flat, index_of(i_next.long()), row, _weights(pt - i_next)) + (1 << (W_BITS - 6))) >> (W_BITS - 5)
            diff = (J_win - I_win).double()
            b1 = (diff * Ixd).sum(-1).float() * FLT_SCALE
            b2 = (diff * Iyd).sum(-1).float() * FLT_SCALE
            delta = torch.stack([(A12 * b2 - A22 * b1) * D_inv, (A12 * b1 - A11 * b2) * D_inv], -1)
            step = active[..., None]
            pt = torch.where(step, pt + delta, pt)
            nxt = torch.where(step, pt + half, nxt)
            d64 = delta.double()
            converged = (d64 * d64).sum(-1) <= eps2
            swing = (delta + prev_delta).abs()
            oscillating = (j > 0) & (swing[..., 0] < 0.01) & (swing[..., 1] < 0.01) & ~converged
            nxt = torch.where((active & oscillating)[..., None], nxt - delta * 0.5, nxt)
            active = active & ~converged & ~oscillating
            prev_delta = delta
        if level == 0:  # OpenCV's last look at the final window (its error measure) loses it too
            status &= ~outside(torch.floor(nxt - half))
    return nxt, status


def _distinct(u: Tensor, n: Tensor) -> Tensor:
    """(B, K, S) distinct indices in [0, n[b]) from uniforms ``u`` (B, K, S): the r-th of those
    not yet drawn, draw after draw."""
    picks: list[Tensor] = []
    for j in range(u.shape[-1]):
        r = torch.floor(u[..., j] * (n[:, None] - j).clamp(min=1)).long()
        if picks:
            drawn = torch.stack(picks, -1).sort(-1).values
            for i in range(drawn.shape[-1]):
                r = r + (r >= drawn[..., i]).long()
        picks.append(r)
    return torch.stack(picks, -1)


def _project(H: Tensor, points: Tensor) -> Tensor:
    """``points`` (..., N, 2) through ``H`` (..., 3, 3) (no guard on the divisor: a degenerate
    hypothesis gives inf or NaN, which never counts as an inlier)."""
    mapped = points @ H[..., :2, :2].transpose(-1, -2) + H[..., None, :2, 2]
    return mapped / (points @ H[..., 2:3, :2].transpose(-1, -2) + H[..., None, 2:3, 2])


def _cross(p: Tensor, a: int, b: int, c: int) -> tuple[Tensor, Tensor]:
    """The cross product of the edges a->b, a->c of the point sets ``p`` (..., 4, 2), and a scale
    of their lengths (OpenCV's collinearity tolerance)."""
    d1, d2 = p[..., b, :] - p[..., a, :], p[..., c, :] - p[..., a, :]
    return d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0], d1.abs().sum(-1) + d2.abs().sum(-1)


def _subset_ok(src: Tensor, dst: Tensor) -> Tensor:
    """OpenCV's check of a 4-point sample (HomographyEstimatorCallback::checkSubset): no three
    points collinear in either set, and every triple turning the same way in both or all the other."""
    eps = float(np.finfo(np.float32).eps)
    ok = torch.ones(src.shape[:-2], dtype=torch.bool, device=src.device)
    negative = torch.zeros(src.shape[:-2], dtype=torch.int64, device=src.device)
    for a, b, c in ((0, 1, 2), (1, 2, 3), (0, 2, 3), (0, 1, 3)):
        cs, ss = _cross(src, a, b, c)
        cd, sd = _cross(dst, a, b, c)
        ok &= (cs.abs() > eps * ss) & (cd.abs() > eps * sd)
        negative += (cs * cd < 0).long()
    return ok & ((negative == 0) | (negative == 4))


def _refine(H: Tensor, src: Tensor, dst: Tensor, weight: Tensor, iterations: int = 10) -> Tensor:
    """Levenberg-Marquardt on the reprojection error of the weighted correspondences, starting
    from ``H`` (B, 3, 3) with h33 = 1 (OpenCV's HomographyRefineCallback, 10 iterations); a step
    is taken only where it lowers the error."""
    h = H.flatten(1)[:, :8]
    lam = torch.full_like(h[:, 0], 1e-3)
    eye = torch.eye(8, dtype=h.dtype, device=h.device)

    def residuals(h: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        x, y = src[..., 0], src[..., 1]
        den = h[:, None, 6] * x + h[:, None, 7] * y + 1.0
        u = (h[:, None, 0] * x + h[:, None, 1] * y + h[:, None, 2]) / den
        v = (h[:, None, 3] * x + h[:, None, 4] * y + h[:, None, 5]) / den
        r = torch.stack([u - dst[..., 0], v - dst[..., 1]], -1) * weight[..., None]
        return r, u, v

    for _ in range(iterations):
        r, u, v = residuals(h)
        x, y = src[..., 0], src[..., 1]
        den = h[:, None, 6] * x + h[:, None, 7] * y + 1.0
        zero = torch.zeros_like(x)
        Ju = torch.stack([x, y, torch.ones_like(x), zero, zero, zero, -u * x, -u * y], -1) / den[..., None]
        Jv = torch.stack([zero, zero, zero, x, y, torch.ones_like(x), -v * x, -v * y], -1) / den[..., None]
        J = torch.cat([Ju, Jv], 1) * torch.cat([weight, weight], 1)[..., None]
        res = torch.cat([r[..., 0], r[..., 1]], 1)
        JtJ = J.transpose(1, 2) @ J
        Jtr = (J.transpose(1, 2) @ res[..., None])[..., 0]
        damped = JtJ + lam[:, None, None] * (JtJ * eye)
        step, info = torch.linalg.solve_ex(damped, -Jtr)
        trial = h + step
        before = (res * res).sum(-1)
        r_trial, _, _ = residuals(trial)
        after = (r_trial * r_trial).sum((-1, -2))
        better = (info == 0) & torch.isfinite(after) & (after < before)
        h = torch.where(better[:, None], trial, h)
        lam = torch.where(better, lam * 0.1, lam * 10.0)
    return torch.cat([h, torch.ones_like(h[:, :1])], -1).unflatten(-1, (3, 3))


def fit_homography(src: Tensor, dst: Tensor, ok: Tensor, threshold: float, hypotheses: int = HYPOTHESES,
                   seed: int = SAMPLE_SEED) -> tuple[Tensor, Tensor]:
    """A robust homography (B, 3, 3) float64 from the correspondences ``src`` -> ``dst`` (B, N, 2)
    that ``ok`` (B, N) allows, and its inliers (B, N) bool: those within ``threshold`` px of the
    best of ``hypotheses`` 4-point fits (the mask ``cv2.findHomography`` returns), the fit then
    refined on them.  Where no hypothesis stands, the inliers are none (H is then meaningless)."""
    B, N = ok.shape
    src, dst = src.double(), dst.double()
    n = ok.sum(-1)
    order = torch.argsort((~ok).to(torch.int8), dim=1, stable=True)  # the allowed points first
    generator = torch.Generator().manual_seed(seed)
    u = torch.rand((B, hypotheses, 4), generator=generator, dtype=torch.float64).to(src.device)
    picks = order.gather(1, _distinct(u, n).flatten(1)).view(B, hypotheses, 4)
    s4 = src.gather(1, picks.flatten(1)[..., None].expand(-1, -1, 2)).view(B, hypotheses, 4, 2)
    d4 = dst.gather(1, picks.flatten(1)[..., None].expand(-1, -1, 2)).view(B, hypotheses, 4, 2)
    Hk = four_point_homography(s4, d4)
    solved = torch.isfinite(Hk).flatten(-2).all(-1)
    usable = solved & _subset_ok(s4, d4) & (n >= 4)[:, None]
    err = ((_project(Hk, src[:, None]) - dst[:, None]) ** 2).sum(-1)  # (B, K, N)
    inlier = (err <= threshold * threshold) & ok[:, None] & usable[..., None]
    score = torch.where(usable, inlier.sum(-1), torch.full_like(n[:, None], -1).expand(-1, hypotheses))
    best = score.argmax(-1)
    H0 = Hk[torch.arange(B, device=src.device), best]
    inliers = inlier[torch.arange(B, device=src.device), best]
    weight = inliers.double()
    H1 = weighted_dlt(src, dst, weight)
    H1 = torch.where(torch.isfinite(H1).all(-1).all(-1)[:, None, None], H1, H0)
    return _refine(H1, src, dst, weight), inliers


def fine_detail(gray: Tensor) -> Tensor:
    """:func:`.correlation.fine_detail` of gray frames (B, h, w): the image minus its 5x5 mean
    (reflect-101 borders, as cv2.blur), float32."""
    g = gray.float()
    mean = F.avg_pool2d(_pad_reflect101(g, 2)[:, None], 5, stride=1)[:, 0]
    return g - mean


def _sample(images: Tensor, x: Tensor, y: Tensor) -> Tensor:
    """``images`` (B, h, w) float at the points (B, P) as cv2.warpPerspective samples a float
    image (bilinear at the exact point, 0 outside) -> (B, P)."""
    B, h, w = images.shape
    x0, y0 = torch.floor(x), torch.floor(y)
    a, b = (x - x0).float(), (y - y0).float()
    flat = images.flatten(1)
    total = torch.zeros(x.shape, dtype=torch.float32, device=images.device)
    for dx, dy, wt in ((0, 0, (1 - a) * (1 - b)), (1, 0, a * (1 - b)), (0, 1, (1 - a) * b), (1, 1, a * b)):
        xi, yi = x0.long() + dx, y0.long() + dy
        inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
        value = flat.gather(1, (yi.clamp(0, h - 1) * w + xi.clamp(0, w - 1)))
        total += torch.where(inside, value * wt, torch.zeros_like(wt))
    return total


def detail_zncc(prev_detail: Tensor, cur_detail: Tensor, H: Tensor, positions: Tensor, patch: int,
                usable: Tensor, work_mask: Tensor | None = None) -> Tensor:
    """:func:`.correlation.detail_zncc` for B pairs: the ZNCC (B,) float64 of the fine detail
    (B, h, w) of frame t's patches (top-left ``positions`` (M, 2), ``patch`` px square) and of
    frame t+1's sampled through ``H`` (B, 3, 3), on the pixels whose every bilinear tap lies on a
    ``usable`` (h, w) pixel of frame t+1 (1 usable, 0 not) and ``work_mask`` (h, w, > 0 use)
    allows in frame t; 0 where they are no more than a quarter of the patches' pixels."""
    B, h, w = prev_detail.shape
    M, P = positions.shape[0], patch
    device = prev_detail.device
    r = torch.arange(P, device=device)
    px = (positions[:, 0, None, None] + r[None, None, :]).expand(M, P, P).reshape(-1)  # (M*P*P,) x in frame t
    py = (positions[:, 1, None, None] + r[None, :, None]).expand(M, P, P).reshape(-1)
    H = H.double()
    pts = torch.stack([px, py], -1).double()
    den = H[:, None, 2, 0] * pts[:, 0] + H[:, None, 2, 1] * pts[:, 1] + H[:, None, 2, 2]
    scale = torch.where(den != 0, 1.0 / den, torch.zeros_like(den))
    x = (H[:, None, 0, 0] * pts[:, 0] + H[:, None, 0, 1] * pts[:, 1] + H[:, None, 0, 2]) * scale
    y = (H[:, None, 1, 0] * pts[:, 0] + H[:, None, 1, 1] * pts[:, 1] + H[:, None, 1, 2]) * scale
    valid = _sample(usable.float().expand(B, h, w), x, y) > 0.999
    if work_mask is not None:
        valid &= (work_mask[py, px] > 0)[None]
    a = prev_detail[:, py, px].double()
    b = _sample(cur_detail.float(), x, y).double()
    count = valid.sum(-1)
    vf = valid.double()
    a_mean = (a * vf).sum(-1) / count.clamp(min=1)
    b_mean = (b * vf).sum(-1) / count.clamp(min=1)
    a0, b0 = (a - a_mean[:, None]) * vf, (b - b_mean[:, None]) * vf
    value = (a0 * b0).sum(-1) / torch.sqrt((a0 * a0).sum(-1) * (b0 * b0).sum(-1) + 1e-12)
    return torch.where(count > 0.25 * M * P * P, value, torch.zeros_like(value))


@dataclass(frozen=True)
class BatchPolish:
    """:func:`polish`'s results for B pairs (tensors on its device)."""

    H: Tensor  # (B, 3, 3) float64: the refit (meaningful where ``found``)
    found: Tensor  # (B,) bool: refitted with at least ``min_inliers`` inliers, close to the seed and plausible
    inliers: Tensor  # (B,) int64: the refit's inliers


def polish(prev: Tensor, cur: Tensor, H: Tensor, points: Tensor, counts: Tensor, config: PolishConfig,
           allowed: Tensor | None = None, hypotheses: int = HYPOTHESES) -> BatchPolish:
    """:func:`.refine.track_points` for B pairs: ``points`` (B, N, 2) of
    ``prev`` (B, h, w, the first ``counts`` (B,) of each real) tracked into ``cur`` from where the
    seeds ``H`` (B, 3, 3) put them, the tracks whose window would reach a pixel ``allowed`` (h, w,
    > 0: use; the mask eroded by the window's half) refuses dropped, and a homography refitted
    to the rest; found where that fit has ``config.min_inliers`` inliers and :func:`settled`
    holds (within ``config.max_shift`` of the seed, plausible)."""
    c = config
    B, N = points.shape[:2]
    real = torch.arange(N, device=points.device)[None] < counts[:, None]
    src = points.float()
    H64 = H.double()
    mapped = src.double() @ H64[:, :2, :2].transpose(1, 2) + H64[:, None, :2, 2]
    w = src.double() @ H64[:, 2:3, :2].transpose(1, 2) + H64[:, None, 2:3, 2]
    guess = torch.where(w.abs() > float(np.finfo(np.float32).eps), mapped / w, torch.zeros_like(mapped)).float()
    seeded = torch.isfinite(guess).all(-1).all(-1) | ~real.any(-1)
    guess = torch.where(torch.isfinite(guess), guess, torch.zeros_like(guess))
    tracked, status = track(prev, cur, src, guess, c.window, c.levels)
    ok = status & real
    if allowed is not None:
        ok &= _allowed(allowed, src) & _allowed(allowed, tracked)
    fitted, inliers = fit_homography(src, tracked, ok, c.threshold, hypotheses)
    count = inliers.sum(-1)
    found = seeded & (counts >= c.min_inliers) & (ok.sum(-1) >= c.min_inliers) & (count >= c.min_inliers)
    found &= settled(fitted, H, (prev.shape[2], prev.shape[1]), c.max_shift)
    return BatchPolish(fitted, found, count)


def settled(H: Tensor, seed: Tensor, size: tuple[int, int], max_shift: float, max_area_ratio: float = 2.0) -> Tensor:
    """(B,) bool: the polished ``H`` (B, 3, 3) moves no corner of a ``size`` (w, h) frame further
    than ``max_shift`` px from where ``seed`` (B, 3, 3) puts it, and is a plausible motion (as
    :func:`mosaic_cli.geometry.is_valid`: finite, in front of the camera, convex and turning as
    the frame, the area changed by less than ``max_area_ratio``): :func:`.refine.track_points`'
    last check."""
    H, seed = H.double(), seed.double()
    w, h = size
    c = torch.tensor([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]], dtype=torch.float64, device=H.device)
    ok = torch.isfinite(H).all(-1).all(-1) & (H[:, 2, 2].abs() >= 1e-12)
    H = torch.where(ok[:, None, None], H, torch.eye(3, dtype=H.dtype, device=H.device).expand_as(H))
    H = H / H[:, 2:3, 2:3]
    ok &= ((c @ H[:, 2, :2].transpose(0, 1)).transpose(0, 1) + H[:, 2:3, 2] > 1e-6).all(-1)
    q = _project(H, c.expand(H.shape[0], 4, 2))
    ok &= torch.isfinite(q).all(-1).all(-1)

    def turns(quad: Tensor) -> Tensor:
        edges = torch.roll(quad, -1, -2) - quad
        nxt = torch.roll(edges, -1, -2)
        return edges[..., 0] * nxt[..., 1] - edges[..., 1] * nxt[..., 0]

    ok &= (torch.sign(turns(q)) == torch.sign(turns(c))).all(-1)
    after = torch.roll(q, -1, -2)
    area = 0.5 * (q[..., 0] * after[..., 1] - after[..., 0] * q[..., 1]).sum(-1).abs() / float(w * h)
    ok &= (area > 1.0 / max_area_ratio) & (area < max_area_ratio)
    shift = (q - _project(seed, c.expand(H.shape[0], 4, 2))).norm(dim=-1).amax(-1)
    return ok & (shift <= max_shift)


def _allowed(mask: Tensor, points: Tensor) -> Tensor:
    """(B, N) bool: the points (B, N, 2) fall, rounded, on pixels of ``mask`` (h, w) > 0."""
    h, w = mask.shape
    finite = torch.isfinite(points).all(-1)
    xy = torch.round(torch.where(finite[..., None], points, torch.full_like(points, -1.0))).long()
    inside = finite & (xy[..., 0] >= 0) & (xy[..., 0] < w) & (xy[..., 1] >= 0) & (xy[..., 1] < h)
    return inside & (mask[xy[..., 1].clamp(0, h - 1), xy[..., 0].clamp(0, w - 1)] > 0)


__all__ = ["BatchPolish", "detail_zncc", "fine_detail", "fit_homography", "polish", "pyr_down", "pyramid_levels", "scharr",
           "settled", "track"]
