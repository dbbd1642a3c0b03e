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


def four_point_to_homography(corners: Tensor, offsets: Tensor) -> Tensor:
    """4-point DLT: the homography (..., 3, 3) mapping ``corners`` (..., 4, 2) onto
    ``corners + offsets`` (..., 4, 2), normalised to H[2, 2] = 1; the leading dimensions broadcast.

    Solved by kornia's ``get_perspective_transform`` in float64 (pixel coordinates of a few
    hundred make float32 lose ~1e-3 px at the frame corners) and returned in ``offsets``' dtype
    (float32 for half-precision offsets, which cannot even hold the corners exactly); autocast
    never lowers its precision.
    """
    _check_points(corners, 4, "corners")
    _check_points(offsets, 4, "offsets")
    dtype = torch.float32 if offsets.dtype in (torch.float16, torch.bfloat16) else offsets.dtype
    src, offsets = torch.broadcast_tensors(corners.to(dtype), offsets.to(dtype))
    batch = src.shape[:-2]
    src64 = src.reshape(-1, 4, 2).double()
    # kornia is imported with the first pair, not at start-up (a quarter of a second).
    from kornia.geometry.transform import get_perspective_transform

    H = get_perspective_transform(src64, src64 + offsets.reshape(-1, 4, 2).double())
    return normalize(H).to(dtype).reshape(*batch, 3, 3)


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
    "four_point_to_homography",
    "homography_to_four_point",
    "cumulative",
    "rect_corners",
    "frame_corners",
]
