"""The network's patches: where they sit, their corner offsets as homographies, and cutting and
sampling them from frames.  Batched over leading dimensions, differentiable, any device; the
homography algebra itself (DLT, projection, chaining) is :mod:`mosaic_cli.geometry.tensor`.

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
from torch import Tensor

from mosaic_cli.geometry.tensor import four_point_to_homography, homography_to_four_point, project, rect_corners


def patch_corners(positions: Tensor, patch: int) -> Tensor:
    """Outer corners (..., 4, 2), TL, TR, BR, BL, of the ``patch`` x ``patch`` squares whose
    top-left *pixel* is at ``positions`` (..., 2) = (x, y).  With pixel centres on integers the
    square spans [x - 0.5, x + patch - 0.5], like :func:`mosaic_cli.geometry.rect_corners`."""
    origin = positions.to(torch.float32 if not positions.is_floating_point() else positions.dtype) - 0.5
    return rect_corners(origin, patch, patch)


def offsets_to_homography(offsets: Tensor, positions: Tensor, patch: int) -> Tensor:
    """The network's output as a homography of the whole working frame, frame t -> frame t+1.

    ``offsets`` (..., 4, 2): displacement of the patch corners (TL, TR, BR, BL) from frame t to t+1;
    ``positions`` (..., 2): top-left pixel (x, y) of the patch in frame t (broadcast against offsets).
    """
    if offsets.dtype in (torch.float16, torch.bfloat16):
        offsets = offsets.float()  # half precision cannot even hold the corners (223.5) exactly
    return four_point_to_homography(patch_corners(positions, patch).to(offsets.dtype), offsets)


def homography_to_offsets(H: Tensor, positions: Tensor, patch: int) -> Tensor:
    """Inverse of :func:`offsets_to_homography`: where ``H`` (..., 3, 3) moves the patch corners."""
    return homography_to_four_point(H, patch_corners(positions, patch).to(H.dtype))


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
    points = project(H, grid.reshape(N, M, size * size, 2)).reshape(N, M, size, size, 2)
    values, mask = sample(images, points)  # (N, C, M, S, S)
    return values.transpose(1, 2), mask.transpose(1, 2)


def warp_perspective(images: Tensor, H: Tensor, dsize: tuple[int, int]) -> Tensor:
    """Warp ``images`` (N, C, h, w) by ``H`` (N, 3, 3), source -> destination pixels, into an image
    of ``dsize`` = (w, h): out(H @ x) = image(x), as ``cv2.warpPerspective(image, H, dsize)``
    (kornia's warp_perspective, zero padding)."""
    from kornia.geometry.transform import warp_perspective  # (with the first use: start-up)

    w, h = dsize
    return warp_perspective(images, H.to(images.dtype), (h, w), mode="bilinear", align_corners=True)


__all__ = [
    "patch_corners",
    "offsets_to_homography",
    "homography_to_offsets",
    "pixel_grid",
    "crop",
    "sample",
    "sample_patches",
    "warp_perspective",
]
