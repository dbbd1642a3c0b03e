"""The paper's loss terms, each a small function of tensors (see :mod:`.objective` for how they
are put together).

Every homography here maps frame t -> frame t+1 of the working frame (320x180 px).

How homographies are compared.  The paper takes the L1 norm of the difference of raw 3x3 matrices,
where translations (pixels) are ~1e4 times the projective entries (~1e-4/px), so the latter barely
count.  Here two homographies are compared by where they send a fixed set of reference points,
the four outer corners of the working frame, in pixels:

    d(H_a, H_b) = sum_k || H_a(p_k) - H_b(p_k) ||_1        (k over the 4 frame corners)

a sum of 8 absolute coordinate differences, like the paper's sum over 9 matrix entries.  Every
parameter (translation, rotation, zoom, tilt) counts by how far it moves the image content, which
is also what the MACE metric measures.  The regularisers return the *mean* of d over their N
compared pairs, so the paper's lambda = 1/(9 N) is the weight 1/9 on these means.
"""

from __future__ import annotations

import itertools
import math

import cv2
import numpy as np
import torch
from kornia.filters import gaussian_blur2d
from torch import Tensor

from mosaic_cli.geometry.tensor import cumulative, project
from mosaic_cli.model.patches import crop, sample_patches

PHOTOMETRIC_NORMS = ("l2", "l1")
PHOTOMETRIC_SPACES = ("gray", "band")
BAND_SIGMAS = (1.5, 6.0)  # working px: the band the polish aligns (estimators.refine.band_pass)


def band_pass(frames: Tensor, fine: float = BAND_SIGMAS[0], coarse: float = BAND_SIGMAS[1]) -> Tensor:
    """Difference of Gaussians of ``frames`` (..., C, h, w), each image scaled to unit RMS.

    What the photometric loss compares in the "band" space: the ground's detail without the
    brightness and contrast that exposure drift, haze and vignetting change between frames (a
    gain and offset of an image leave it unchanged but for the blur's edge effects), so that
    these no longer outweigh a misalignment in the loss."""
    flat = frames.reshape(-1, 1, *frames.shape[-2:])
    dog = _blur(flat, fine) - _blur(flat, coarse)
    rms = dog.square().mean(dim=(-1, -2), keepdim=True).sqrt()
    return (dog / (rms + 1e-4)).reshape(frames.shape)


def _blur(images: Tensor, sigma: float) -> Tensor:
    """Gaussian blur of (N, 1, h, w), reflect-101 borders, 3-sigma kernel.  On the CPU, outside
    autograd, OpenCV's: some 30x faster than a torch convolution of one channel there."""
    taps = 2 * int(math.ceil(3 * sigma)) + 1
    if images.device.type != "cpu" or images.requires_grad:
        return gaussian_blur2d(images, (taps, taps), (sigma, sigma), border_type="reflect")
    planes = images[:, 0].detach().float().contiguous().numpy()
    blurred = [cv2.GaussianBlur(plane, (taps, taps), sigma, borderType=cv2.BORDER_REFLECT_101) for plane in planes]
    return torch.from_numpy(np.stack(blurred)).to(images.dtype)[:, None]


def photometric(target: Tensor, warped: Tensor, mask: Tensor, norm: str = "l2") -> Tensor:
    """Photometric loss L between patches of frame t and frame t+1 sampled through H.

    ``target``, ``warped`` (..., C, P, P), ``mask`` (..., 1, P, P) with 1 where H x fell inside
    frame t+1.  Masked-out pixels are left out and the rest rescaled to the full patch, so that a
    warp gains nothing by pushing pixels out of the frame.  With n = P*P pixels, V the valid ones:

        "l2" (the authors' code):  L = mean_i sqrt( n/|V_i| * sum_{x in V_i} (I_i(x) - J_i(H_i x))^2 + 1e-6 )
        "l1" (the paper's text):   L = mean_i (1/|V_i|) * sum_{x in V_i} |I_i(x) - J_i(H_i x)|
    """
    if norm not in PHOTOMETRIC_NORMS:
        raise ValueError(f"unknown photometric norm {norm!r}: choose one of {', '.join(PHOTOMETRIC_NORMS)}")
    diff = (target - warped) * mask
    pixels = mask[..., 0, :, :].flatten(-2)
    n = pixels.shape[-1]
    valid = pixels.sum(-1).clamp(min=1.0)
    if norm == "l2":
        per_sample = torch.sqrt(diff.square().flatten(-3).sum(-1) * (n / valid) + 1e-6)
    else:
        per_sample = diff.abs().flatten(-3).sum(-1) / valid
    return per_sample.mean()


def corner_distance(H_a: Tensor, H_b: Tensor, points: Tensor) -> Tensor:
    """d(H_a, H_b) = sum_k || H_a(p_k) - H_b(p_k) ||_1 over reference ``points`` (K, 2) (the frame
    corners); broadcast over leading dimensions of H_a, H_b (..., 3, 3) -> (...)."""
    pts = points.to(H_a.dtype)
    return (project(H_a, pts) - project(H_b, pts)).abs().sum((-1, -2))


def spatial_consistency(H: Tensor, points: Tensor) -> Tensor:
    """R_p: patches at different places of the same frame pair must give the same homography.

    ``H`` (B, M, T, 3, 3), M patch positions per frame pair:

        R_p = mean over b, t and pairs a < b' of d(H[b, a, t], H[b, b', t])

    (the paper sums over ordered pairs a != b; d is symmetric so that only doubles the sum).
    Zero when M < 2."""
    M = H.shape[1]
    if M < 2:
        return H.new_zeros(())
    a, b = zip(*itertools.combinations(range(M), 2))
    return corner_distance(H[:, list(a)], H[:, list(b)], points).mean()


def scale_consistency(H_parent: Tensor, H_children: Tensor, points: Tensor) -> Tensor:
    """R_s: a 128 patch and each of its four 64x64 quadrants (resized to 128, offsets halved)
    must give the same homography.

    ``H_parent`` (..., 3, 3), ``H_children`` (..., 4, 3, 3):

        R_s = mean over samples and children c of d(H_parent, H_child_c)"""
    return corner_distance(H_parent.unsqueeze(-3), H_children, points).mean()


def temporal_smoothness(H: Tensor, points: Tensor) -> Tensor:
    """R_t1: consecutive frame pairs move alike (the camera's motion is smooth).

    ``H`` (..., T, 3, 3) consecutive pairwise homographies (H[t]: frame t -> t+1):

        R_t1 = mean over samples and t < T-1 of d(H[t], H[t+1])

    Zero when T < 2."""
    if H.shape[-3] < 2:
        return H.new_zeros(())
    return corner_distance(H[..., :-1, :, :], H[..., 1:, :, :], points).mean()


def chain_consistency(frames: Tensor, H: Tensor, positions: Tensor, patch: int, norm: str = "l2") -> Tensor:
    """R_t2: the chained homography must register frames further apart too.

    ``frames`` (B, K, C, h, w), ``H`` (B, M, K-1, 3, 3) pairwise (frame t -> t+1) for the patches
    at ``positions`` (B, M, 2) of frame 0.  With H_[0,s] = H_{s-1} ... H_0 and I_0 the patch of
    frame 0:

        R_t2 = mean over samples and s = 2..K-1 of L(I_0(x), I_s(H_[0,s] x))

    with L the masked :func:`photometric` loss of one patch pair.  Zero when K < 3."""
    B, K = frames.shape[:2]
    if K < 3:
        return frames.new_zeros(())
    M = positions.shape[1]
    chained = cumulative(H)[:, :, 2:]  # (B, M, K-2, 3, 3): H_[0,s] for s = 2..K-1
    later = frames[:, 2:].flatten(0, 1)  # (B*(K-2), C, h, w)
    H_flat = chained.transpose(1, 2).flatten(0, 1)  # (B*(K-2), M, 3, 3)
    pos = positions[:, None].expand(B, K - 2, M, 2).flatten(0, 1)
    warped, mask = sample_patches(later, H_flat, pos, patch)
    first = crop(frames[:, 0], positions, patch)  # (B, M, C, P, P)
    target = first[:, None].expand(B, K - 2, *first.shape[1:]).flatten(0, 1)
    return photometric(target, warped, mask, norm)


__all__ = [
    "PHOTOMETRIC_NORMS",
    "PHOTOMETRIC_SPACES",
    "band_pass",
    "photometric",
    "corner_distance",
    "spatial_consistency",
    "scale_consistency",
    "temporal_smoothness",
    "chain_consistency",
]
