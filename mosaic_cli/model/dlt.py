"""Tensor DLT and perspective sampling: batched over leading dimensions, differentiable, any device.

Conventions (the same as :mod:`mosaic_cli.geometry`):

* Pixel coordinates are OpenCV's: pixel (i, j) has its centre at x = j, y = i.
* A homography ``H`` maps column vectors ``x_dst ~ H @ [x, y, 1]``; every function says which
  frame is the source and which the destination.
* The network's homography maps frame t -> frame t+1 (the paper's kornia code learns the
  opposite, t+1 -> t; mosaic uses t -> t+1 everywhere, so no conversion is ever needed).
* To compare frame t with frame t+1 we *sample* frame t+1 at ``H @ x`` for every pixel x of a
  patch of frame t (:func:`sample`): the warped patch lines up with the patch of frame t.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.geometry.transform import get_perspective_transform
from kornia.geometry.transform import warp_perspective as _kornia_warp_perspective
from torch import Tensor

_EPS = 1e-6


def patch_corners(positions: Tensor, patch: int) -> Tensor:
    """Outer corners (..., 4, 2), TL, TR, BR, BL, of the ``patch`` x ``patch`` squares whose
    top-left *pixel* is at ``positions`` (..., 2) = (x, y).  With pixel centres on integers the
    square spans [x - 0.5, x + patch - 0.5], like :func:`mosaic_cli.geometry.rect_corners`."""
    origin = positions.to(torch.float32 if not positions.is_floating_point() else positions.dtype) - 0.5
    unit = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], dtype=origin.dtype, device=origin.device)
    return origin.unsqueeze(-2) + patch * unit


def dlt(src: Tensor, dst: Tensor) -> Tensor:
    """4-point DLT: the homography (..., 3, 3) mapping ``src`` (..., 4, 2) onto ``dst`` (..., 4, 2),
    normalised to H[2, 2] = 1.

    Solved by kornia's ``get_perspective_transform`` in float64 (pixel coordinates of a few
    hundred make float32 lose ~1e-3 px at the frame corners) and returned in ``dst``'s dtype;
    autocast never lowers its precision.
    """
    batch = dst.shape[:-2]
    src, dst = torch.broadcast_tensors(src.to(dst.dtype), dst)
    H = get_perspective_transform(src.reshape(-1, 4, 2).double(), dst.reshape(-1, 4, 2).double())
    H = H / H[:, 2:3, 2:3]
    return H.to(dst.dtype).reshape(*batch, 3, 3)


def offsets_to_homography(offsets: Tensor, positions: Tensor, patch: int) -> Tensor:
    """The network's output as a homography of the whole working frame, frame t -> frame t+1.

    ``offsets`` (..., 4, 2): displacement of the patch corners (TL, TR, BR, BL) from frame t to t+1;
    ``positions`` (..., 2): top-left pixel (x, y) of the patch in frame t (broadcast against offsets).
    """
    if offsets.dtype in (torch.float16, torch.bfloat16):
        offsets = offsets.float()  # half precision cannot even hold the corners (223.5) exactly
    corners = patch_corners(positions, patch).to(offsets.dtype)
    return dlt(corners, corners + offsets)


def homography_to_offsets(H: Tensor, positions: Tensor, patch: int) -> Tensor:
    """Inverse of :func:`offsets_to_homography`: where ``H`` (..., 3, 3) moves the patch corners."""
    corners = patch_corners(positions, patch).to(H.dtype)
    return transform_points(H, corners) - corners


def transform_points(H: Tensor, points: Tensor) -> Tensor:
    """Map ``points`` (..., N, 2) through ``H`` (..., 3, 3).  The projective divisor is kept away
    from zero (|w| >= 1e-6, sign kept) so that a wild early-training estimate gives large but
    finite points and gradients, never inf/NaN."""
    mapped = points @ H[..., :2, :2].transpose(-1, -2) + H[..., None, :2, 2]
    w = points @ H[..., 2:3, :2].transpose(-1, -2) + H[..., None, 2:3, 2]
    w = torch.where(w.abs() < _EPS, torch.where(w < 0, -_EPS, _EPS), w)
    return mapped / w


def chain(pairwise: Tensor) -> Tensor:
    """Cumulative homographies over a window: ``pairwise`` (..., T, 3, 3) with ``pairwise[k]``
    frame k -> k+1 gives (..., T, 3, 3) whose k-th entry is H_[0,k+1] = H_k @ ... @ H_0 (frame 0 ->
    frame k+1), each normalised to H[2, 2] = 1."""
    out = []
    acc = None
    for k in range(pairwise.shape[-3]):
        acc = pairwise[..., k, :, :] if acc is None else pairwise[..., k, :, :] @ acc
        acc = acc / acc[..., 2:3, 2:3]
        out.append(acc)
    return torch.stack(out, dim=-3)


def pixel_grid(positions: Tensor, size: int) -> Tensor:
    """Pixel centres (..., size, size, 2) = (x, y) of the ``size``-square patches whose top-left
    pixel is at ``positions`` (..., 2)."""
    r = torch.arange(size, device=positions.device, dtype=torch.float32)
    yy, xx = torch.meshgrid(r, r, indexing="ij")
    grid = torch.stack([xx, yy], dim=-1)
    return positions.to(torch.float32)[..., None, None, :] + grid


def crop(images: Tensor, positions: Tensor, size: int) -> Tensor:
    """Integer crops: ``images`` (N, C, h, w), ``positions`` (N, M, 2) top-left (x, y), fully
    inside -> (N, M, C, size, size)."""
    N, M = positions.shape[:2]
    r = torch.arange(size, device=images.device)
    xs = positions[..., 0:1].long() + r  # (N, M, S)
    ys = positions[..., 1:2].long() + r
    n = torch.arange(N, device=images.device)[:, None, None, None]
    out = images[n, :, ys[:, :, :, None], xs[:, :, None, :]]  # (N, M, S, S, C)
    return out.permute(0, 1, 4, 2, 3)


def sample(images: Tensor, points: Tensor) -> tuple[Tensor, Tensor]:
    """Bilinear samples of ``images`` (N, C, h, w) at pixel coordinates ``points`` (N, ..., 2).

    Returns values (N, C, ...) and a float mask (N, 1, ...) that is 1 where the point lies inside
    the image (0 <= x <= w-1, 0 <= y <= h-1: every bilinear tap is a real pixel) and 0 where the
    warp takes it outside; masked values are 0 and carry no gradient.
    """
    N, C, h, w = images.shape
    extra = points.shape[1:-1]
    pts = points.reshape(N, -1, 1, 2).to(images.dtype)
    scale = torch.tensor([2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)], dtype=pts.dtype, device=pts.device)
    grid = pts * scale - 1.0  # align_corners=True: -1 and +1 are the centres of the edge pixels
    values = F.grid_sample(images, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    inside = (pts[..., 0] >= 0) & (pts[..., 0] <= w - 1) & (pts[..., 1] >= 0) & (pts[..., 1] <= h - 1)
    mask = inside.to(images.dtype).unsqueeze(1)
    values = values * mask
    return values.reshape(N, C, *extra), mask.reshape(N, 1, *extra)


def sample_patches(images: Tensor, H: Tensor, positions: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """The patches of ``images`` seen through ``H``: for every pixel x of the ``size``-square
    patch at ``positions`` of a *reference* frame, the value of ``images`` at ``H @ x``.

    ``images`` (N, C, h, w); ``H`` (N, M, 3, 3) maps reference-frame pixels to ``images``' pixels;
    ``positions`` (N, M, 2).  Returns patches (N, M, C, size, size) and mask (N, M, 1, size, size).
    """
    N, M = positions.shape[:2]
    grid = pixel_grid(positions, size).to(H.dtype)  # (N, M, S, S, 2)
    points = transform_points(H, grid.reshape(N, M, size * size, 2)).reshape(N, M, size, size, 2)
    values, mask = sample(images, points)  # (N, C, M, S, S)
    return values.transpose(1, 2), mask.transpose(1, 2)


def warp_perspective(images: Tensor, H: Tensor, dsize: tuple[int, int]) -> Tensor:
    """Warp ``images`` (N, C, h, w) by ``H`` (N, 3, 3), source -> destination pixels, into an image
    of ``dsize`` = (w, h): out(H @ x) = image(x), as ``cv2.warpPerspective(image, H, dsize)``
    (kornia's warp_perspective, zero padding)."""
    w, h = dsize
    return _kornia_warp_perspective(images, H.to(images.dtype), (h, w), mode="bilinear", align_corners=True)


__all__ = [
    "patch_corners",
    "dlt",
    "offsets_to_homography",
    "homography_to_offsets",
    "transform_points",
    "chain",
    "pixel_grid",
    "crop",
    "sample",
    "sample_patches",
    "warp_perspective",
]
