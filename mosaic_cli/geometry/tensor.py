"""Homography algebra on torch tensors: the counterpart of :mod:`mosaic_cli.geometry.homography`
(numpy) with the same names, conventions and shapes, batched, differentiable and on any device.

Conventions (those of :mod:`mosaic_cli.geometry`):

* Pixel coordinates are OpenCV's: pixel (i, j) has its centre at x = j, y = i; a w x h image
  spans [-0.5, w - 0.5] x [-0.5, h - 0.5].
* A homography ``H`` maps column vectors ``x_dst ~ H @ [x, y, 1]``.
* ``pairwise[..., t, :, :]`` maps frame t to frame t+1; :func:`cumulative` gives H_[0,t].
* Batch-first: leading dimensions ``...`` are batch dimensions and broadcast where said so; a
  tensor of the wrong trailing shape raises ``ValueError`` (never a silent broadcast).

Not a module of mosaic's I/O: importing it needs torch and kornia, so ``mosaic_cli.geometry``
does not import it (``from mosaic_cli.geometry import tensor``).
"""

from __future__ import annotations

import torch
from torch import Tensor

# Smallest |w| a projective divisor may have: a wild early-training estimate then gives large but
# finite points and gradients, never inf/NaN (kornia's transform_points instead returns the
# undivided point below its epsilon, a discontinuity, so mosaic keeps its own).
DIVISOR_EPS = 1e-6


def _check_matrices(H: Tensor, name: str = "H") -> None:
    if H.dim() < 2 or tuple(H.shape[-2:]) != (3, 3):
        raise ValueError(f"{name} must have shape (..., 3, 3), got {tuple(H.shape)}")


def _check_points(points: Tensor, count: int | None = None, name: str = "points") -> None:
    if points.dim() < 2 or points.shape[-1] != 2 or (count is not None and points.shape[-2] != count):
        want = f"(..., {count}, 2)" if count is not None else "(..., N, 2)"
        raise ValueError(f"{name} must have shape {want}, got {tuple(points.shape)}")


def normalize(H: Tensor) -> Tensor:
    """``H`` (..., 3, 3) scaled so that H[..., 2, 2] == 1."""
    _check_matrices(H)
    return H / H[..., 2:3, 2:3]


def project(H: Tensor, points: Tensor) -> Tensor:
    """Map ``points`` (..., N, 2) through ``H`` (..., 3, 3) -> (..., N, 2); the leading
    dimensions broadcast.  The divisor is kept at |w| >= :data:`DIVISOR_EPS` (sign kept)."""
    _check_matrices(H)
    _check_points(points)
    mapped = points @ H[..., :2, :2].transpose(-1, -2) + H[..., None, :2, 2]
    w = points @ H[..., 2:3, :2].transpose(-1, -2) + H[..., None, 2:3, 2]
    w = torch.where(w.abs() < DIVISOR_EPS, torch.where(w < 0, -DIVISOR_EPS, DIVISOR_EPS), w)
    return mapped / w


def weighted_dlt(src: Tensor, dst: Tensor, weight: Tensor | None = None) -> Tensor:
    """The direct linear transform: the homographies (..., 3, 3), H[2, 2] = 1, mapping ``src``
    (..., N, 2) onto ``dst`` (..., N, 2), N >= 4, that minimise the algebraic error, each
    correspondence's squared error weighted by ``weight`` (..., N) (None: all 1; a robust fit's
    inliers: 0 or 1); through 4 points in general position, exact.  Batched over the leading
    dimensions, in the points' dtype (float64 for pixel coordinates: float32 loses ~1e-3 px).

    As :func:`mosaic_cli.geometry.weighted_dlt` (numpy) and OpenCV's
    ``HomographyEstimatorCallback::runKernel``: each point set conditioned (moved to its weighted
    centroid, each axis scaled by its weighted mean absolute deviation from it), the eigenvector
    of the smallest eigenvalue of LtL, taken back; NaN where degenerate (no spread).  A value, not
    a gradient, where eigenvalues repeat (symmetric points): :func:`four_point_homography` for those."""
    _check_points(src, name="src")
    _check_points(dst, name="dst")
    if weight is None:
        weight = torch.ones_like(src[..., 0])
    count = weight.sum(-1, keepdim=True).clamp(min=1)[..., None]  # (..., 1, 1)
    wt = weight[..., None]

    def conditioning(p: Tensor) -> tuple[Tensor, Tensor]:
        centre = (p * wt).sum(-2, keepdim=True) / count
        spread = ((p - centre).abs() * wt).sum(-2, keepdim=True)
        return centre, count / spread

    cM, sM = conditioning(src)
    cm, sm = conditioning(dst)
    X, Y = ((src - cM) * sM).unbind(-1)
    x, y = ((dst - cm) * sm).unbind(-1)
    one, zero = torch.ones_like(X), torch.zeros_like(X)
    rows = wt.sqrt()  # (0 or 1: the weight itself)
    Lx = torch.stack([X, Y, one, zero, zero, zero, -x * X, -x * Y, -x], -1) * rows
    Ly = torch.stack([zero, zero, zero, X, Y, one, -y * X, -y * Y, -y], -1) * rows
    LtL = Lx.transpose(-1, -2) @ Lx + Ly.transpose(-1, -2) @ Ly
    LtL = torch.where(torch.isfinite(LtL), LtL, torch.zeros_like(LtL))
    H0 = torch.linalg.eigh(LtL).eigenvectors[..., 0].unflatten(-1, (3, 3))
    z = torch.zeros_like(cm[..., 0, 0])
    o = torch.ones_like(z)
    inv_dst = torch.stack([1 / sm[..., 0, 0], z, cm[..., 0, 0], z, 1 / sm[..., 0, 1], cm[..., 0, 1], z, z, o], -1).unflatten(-1, (3, 3))
    src_norm = torch.stack([sM[..., 0, 0], z, -cM[..., 0, 0] * sM[..., 0, 0], z, sM[..., 0, 1], -cM[..., 0, 1] * sM[..., 0, 1], z, z, o],
                           -1).unflatten(-1, (3, 3))
    H = inv_dst @ H0 @ src_norm
    return H / H[..., 2:3, 2:3]


def four_point_homography(src: Tensor, dst: Tensor) -> Tensor:
    """The homography (..., 3, 3), H[2, 2] = 1, through the 4 correspondences ``src`` -> ``dst``
    (..., 4, 2), in their dtype; the leading dimensions broadcast.  Kornia's closed form (two
    unit-square decompositions, ``get_perspective_transform``): no solver and no host
    synchronisation, a gradient wherever the quads are proper; inf or NaN where one is degenerate.

    Not :func:`weighted_dlt`: through its eigenvectors the gradient is NaN where the points are
    symmetric (a patch's square corners), and the network learns through this one."""
    _check_points(src, 4, "src")
    _check_points(dst, 4, "dst")
    src, dst = torch.broadcast_tensors(src, dst)
    # kornia is imported with the first pair, not at start-up (a quarter of a second).
    from kornia.geometry.transform import get_perspective_transform

    H = get_perspective_transform(src.reshape(-1, 4, 2), dst.reshape(-1, 4, 2))
    return normalize(H).reshape(*src.shape[:-2], 3, 3)


def four_point_to_homography(corners: Tensor, offsets: Tensor) -> Tensor:
    """4-point DLT: the homography (..., 3, 3) mapping ``corners`` (..., 4, 2) onto
    ``corners + offsets`` (..., 4, 2), normalised to H[2, 2] = 1; the leading dimensions broadcast.

    Solved by :func:`four_point_homography` in float64 (pixel coordinates of a few hundred make
    float32 lose ~1e-3 px at the frame corners) and returned in ``offsets``' dtype (float32 for
    half-precision offsets, which cannot even hold the corners exactly); autocast never lowers
    its precision.
    """
    _check_points(corners, 4, "corners")
    _check_points(offsets, 4, "offsets")
    dtype = torch.float32 if offsets.dtype in (torch.float16, torch.bfloat16) else offsets.dtype
    src, offsets = torch.broadcast_tensors(corners.to(dtype), offsets.to(dtype))
    src64 = src.double()
    return four_point_homography(src64, src64 + offsets.double()).to(dtype)


def homography_to_four_point(H: Tensor, corners: Tensor) -> Tensor:
    """Offsets (..., 4, 2) that ``H`` (..., 3, 3) gives ``corners`` (..., 4, 2):
    ``project(H, corners) - corners``."""
    _check_points(corners, 4, "corners")
    corners = corners.to(H.dtype)
    return project(H, corners) - corners


def cumulative(pairwise: Tensor) -> Tensor:
    """H_[0,t] for t = 0..T: ``pairwise`` (..., T, 3, 3), ``pairwise[..., k, :, :]`` frame k ->
    k+1, gives (..., T + 1, 3, 3) whose entry t maps frame 0 to frame t (entry 0 the identity),
    each normalised to H[2, 2] = 1, as :func:`mosaic_cli.geometry.cumulative`."""
    _check_matrices(pairwise, "pairwise")
    if pairwise.dim() < 3:
        raise ValueError(f"pairwise must have shape (..., T, 3, 3), got {tuple(pairwise.shape)}")
    acc = torch.eye(3, dtype=pairwise.dtype, device=pairwise.device).expand(*pairwise.shape[:-3], 3, 3)
    out = [acc]
    for k in range(pairwise.shape[-3]):
        acc = normalize(pairwise[..., k, :, :] @ acc)
        out.append(acc)
    return torch.stack(out, dim=-3)


def rect_corners(origin: Tensor, width: float, height: float) -> Tensor:
    """Corners (..., 4, 2), TL, TR, BR, BL, of the axis-aligned ``width`` x ``height``
    rectangles whose top-left corner is at ``origin`` (..., 2) = (x, y)."""
    if origin.shape[-1:] != (2,):
        raise ValueError(f"origin must have shape (..., 2), got {tuple(origin.shape)}")
    origin = origin if origin.is_floating_point() else origin.to(torch.float32)
    unit = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], dtype=origin.dtype, device=origin.device)
    size = torch.tensor([width, height], dtype=origin.dtype, device=origin.device)
    return origin.unsqueeze(-2) + unit * size


def frame_corners(width: float, height: float, device: torch.device | str | None = None,
                  dtype: torch.dtype = torch.float32) -> Tensor:
    """The outer corners (4, 2) of a ``width`` x ``height`` image (pixel-centre convention):
    TL, TR, BR, BL."""
    return rect_corners(torch.tensor([-0.5, -0.5], dtype=dtype, device=device), width, height)


__all__ = [
    "DIVISOR_EPS",
    "normalize",
    "project",
    "weighted_dlt",
    "four_point_homography",
    "four_point_to_homography",
    "homography_to_four_point",
    "cumulative",
    "rect_corners",
    "frame_corners",
]
