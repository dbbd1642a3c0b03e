"""Image warps on torch tensors: OpenCV's bilinear ``warpPerspective`` and ``remap`` batched, on any
device, and a frame held as yuv420p planes warped as ``stabilize/render.py``'s ``warp_yuv`` does.

Conventions (those of :mod:`mosaic_cli.geometry`):

* Pixel coordinates are OpenCV's: pixel (i, j) has its centre at x = j, y = i.
* ``H`` maps SOURCE pixels to DESTINATION pixels, ``x_dst ~ H @ [x, y, 1]`` (``cv2.warpPerspective``
  without ``WARP_INVERSE_MAP``); each output pixel is sampled at ``H^-1`` of its centre.
* Images are batch-first, ``(B, C, h, w)``; sizes are given as OpenCV gives them, ``(w, h)``.
* Borders as OpenCV's, per tap of the bilinear kernel: ``"constant"`` (a tap outside the image
  reads ``value``, so edge pixels blend with it), ``"replicate"`` (BORDER_REPLICATE, aaa|abc|ccc)
  and ``"reflect"`` (BORDER_REFLECT, cba|abc|cba, the edge pixel repeated: what mosaic's
  ``--border reflect`` is), not REFLECT_101.

Sampling is bilinear at the exact float coordinate and uint8 results are rounded half to even,
as OpenCV's warps and remap do since their SIMD rewrite (4.11; earlier ones rounded the
coordinate to 1/32 px, a difference of several levels on pixel-scale texture).
:func:`remap_nearest` is ``INTER_NEAREST``: the pixel at the coordinate rounded half to even.

Not imported by ``mosaic_cli.geometry`` (it needs torch): ``from mosaic_cli.geometry import warp``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from mosaic_cli.geometry.homography import resize_matrix

Border = Literal["constant", "replicate", "reflect"]
BORDERS: tuple[Border, ...] = ("constant", "replicate", "reflect")

# grid_sample's padding that gives OpenCV's per-tap border with align_corners=False, whose
# reflection is about the image's outer edges (-0.5 and w - 0.5): BORDER_REFLECT's.  "constant"
# samples the image less its value with zeros outside and adds the value back: the taps outside
# then weigh in as the value, as in OpenCV, with no padded copy of the image.
_PADDING = {"constant": "zeros", "replicate": "border", "reflect": "reflection"}


def _check_images(images: Tensor) -> None:
    if images.dim() != 4:
        raise ValueError(f"images must have shape (B, C, h, w), got {tuple(images.shape)}")
    if images.dtype != torch.uint8 and not images.is_floating_point():
        raise ValueError(f"images must be uint8 or floating point, got {images.dtype}")


def _check_border(border: str) -> None:
    if border not in BORDERS:
        raise ValueError(f"border must be one of {', '.join(BORDERS)}, got {border!r}")


def _check_maps(map_x: Tensor, map_y: Tensor, batch: int) -> None:
    if map_x.dim() != 3 or map_x.shape != map_y.shape:
        raise ValueError(f"map_x and map_y must have the same shape (B, H_out, W_out), got {tuple(map_x.shape)} and {tuple(map_y.shape)}")
    if map_x.shape[0] not in (1, batch):
        raise ValueError(f"the maps' batch ({map_x.shape[0]}) must be 1 or the images' ({batch})")


def border_index(index: Tensor, n: int, border: Literal["replicate", "reflect", "reflect101"]) -> Tensor:
    """OpenCV's ``borderInterpolate`` of each of ``index`` (any shape, integer) on an axis of ``n``
    >= 1 pixels: ``replicate`` (aaa|abc|ccc), ``reflect`` (BORDER_REFLECT, cba|abc|cba) or
    ``reflect101`` (BORDER_REFLECT_101, cb|abc|ba, what ``pyrDown``/``pyrUp`` pad with); any
    distance outside.  Returns indices in 0..n-1, the same shape."""
    if n == 1 or border == "replicate":
        return index.clamp(0, n - 1)
    if border == "reflect":
        period = 2 * n
        index = index.remainder(period)
        return torch.where(index >= n, period - 1 - index, index)
    if border == "reflect101":
        period = 2 * n - 2
        index = index.remainder(period)
        return torch.where(index >= n, period - index, index)
    raise ValueError(f"unknown border {border!r}")


def _values(value: float | Sequence[float] | Tensor, channels: int, dtype: torch.dtype, device: torch.device) -> Tensor | float:
    """The border value: a number, or (1, C, 1, 1) one per channel.  Numbers are filled in on the
    device, never copied from pageable host memory (a copy that would make a CUDA stream wait)."""
    if isinstance(value, Tensor):
        v = value.to(device=device, dtype=dtype).reshape(-1)
    else:
        numbers = [float(value)] if isinstance(value, int | float) else [float(x) for x in value]
        if len(numbers) == 1 or len(set(numbers)) == 1:
            return numbers[0]
        v = torch.empty(len(numbers), dtype=dtype, device=device)
        for i, x in enumerate(numbers):
            v[i] = x
    if v.numel() == 1:
        v = v.expand(channels)
    elif v.numel() != channels:
        raise ValueError(f"value must be one number or one per channel ({channels}), got {v.numel()}")
    return v.reshape(1, channels, 1, 1)


def remap(images: Tensor, map_x: Tensor, map_y: Tensor, border: Border = "constant",
          value: float | Sequence[float] | Tensor = 0.0) -> Tensor:
    """``cv2.remap(..., INTER_LINEAR)`` with float maps: output pixel (i, j) of image b is ``images``
    sampled bilinearly at (``map_x[b, i, j]``, ``map_y[b, i, j]``).

    images (B, C, h, w) uint8 or float; map_x, map_y (B, H_out, W_out) source pixel coordinates
    (a batch of 1 broadcasts over the images); ``value``: the constant border's value, one number
    or one per channel.  Returns (B, C, H_out, W_out) in ``images``' dtype (uint8 rounded half to
    even and saturated).  Non-finite coordinates read as far outside the image."""
    _check_images(images)
    _check_border(border)
    _check_maps(map_x, map_y, images.shape[0])
    B, C, h, w = images.shape
    work = images.dtype if images.dtype in (torch.float32, torch.float64) else torch.float32
    src = images.to(work)
    if border == "constant":
        fill = _values(value, C, work, images.device)
        src = src.sub_(fill) if images.dtype != work else src - fill  # in place on a converted copy only
    grid = torch.stack([_normalized(map_x, w, border), _normalized(map_y, h, border)], -1).to(work)
    if grid.shape[0] != B:
        grid = grid.expand(B, -1, -1, -1)
    out = F.grid_sample(src, grid, mode="bilinear", padding_mode=_PADDING[border], align_corners=False)
    if border == "constant":
        out.add_(fill)
    if images.dtype == torch.uint8:
        return out.round_().clamp_(0, 255).to(torch.uint8)
    return out.to(images.dtype)


def remap_nearest(images: Tensor, map_x: Tensor, map_y: Tensor, border: Border = "constant",
                  value: float | Sequence[float] | Tensor = 0.0) -> Tensor:
    """``cv2.remap(..., INTER_NEAREST)`` with float maps: output pixel (i, j) of image b is the
    pixel of ``images`` nearest (``map_x[b, i, j]``, ``map_y[b, i, j]``), the coordinate rounded
    half to even as OpenCV's ``cvRound``, in the maps' own dtype (float64 maps stay exact); a
    pixel outside the image reads the border (``value`` for ``"constant"``).

    images (B, C, h, w) of any dtype (an expanded, zero-stride tensor is read as it is: a
    constant image costs no memory); map_x, map_y (B, H_out, W_out) float (a batch of 1
    broadcasts).  Returns (B, C, H_out, W_out) in ``images``' dtype, a uint8 ``value`` rounded
    and saturated.  Non-finite coordinates read as outside the image."""
    if images.dim() != 4:
        raise ValueError(f"images must have shape (B, C, h, w), got {tuple(images.shape)}")
    _check_border(border)
    _check_maps(map_x, map_y, images.shape[0])
    B, C, h, w = images.shape
    # One pixel outside is as outside as any for the constant and replicate borders; bounding
    # the coordinate keeps it an integer.  Reflection folds any finite one.
    far = 1e6 if border == "reflect" else 1.0
    xi, yi = (torch.round(torch.nan_to_num(c, nan=-far, posinf=n - 1 + far, neginf=-far).clamp(-far, n - 1 + far)).long()
              for c, n in ((map_x, w), (map_y, h)))
    fold: Literal["replicate", "reflect"] = "reflect" if border == "reflect" else "replicate"
    batch = torch.arange(B, device=images.device).view(B, 1, 1)
    out = images[batch, :, border_index(yi, h, fold), border_index(xi, w, fold)].permute(0, 3, 1, 2)  # gathered as (B, H_out, W_out, C)
    if border != "constant":
        return out
    inside = ((xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)).unsqueeze(1)
    fill = _values(value, C, torch.float64, images.device)
    if not isinstance(fill, Tensor):
        fill = torch.full((1, 1, 1, 1), fill, dtype=torch.float64, device=images.device)  # filled on the device
    if images.dtype == torch.uint8:
        fill = fill.round().clamp(0, 255)
    return torch.where(inside, out, fill.to(images.dtype))


def _normalized(coord: Tensor, size: int, border: str) -> Tensor:
    """Pixel coordinates along an axis of ``size`` pixels as grid_sample's (align_corners=False)."""
    # A coordinate far outside reads as well as one just outside (all four taps out) for the
    # constant and replicate borders; bounding it keeps grid_sample's integer tap indices in range.
    # Reflection folds any finite coordinate.
    far = 1e6 if border == "reflect" else 2.0
    coord = torch.nan_to_num(coord.float(), nan=-far, posinf=size + far, neginf=-far).clamp(-far, size - 1 + far)
    return coord * (2.0 / size) + (1.0 / size - 1.0)


def perspective_maps(H: Tensor, dsize: tuple[int, int], dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
    """Where each output pixel samples its source: ``H^-1`` of the output pixel centres.

    H (B, 3, 3) source -> destination; dsize (W_out, H_out).  Returns map_x, map_y
    (B, H_out, W_out) in ``dtype``: float64 keeps them exact where the outputs run to tens of
    thousands of pixels (a stitch's canvas: float32 maps are off there by a few thousandths of a
    pixel).  The inverse is taken in float64 (as OpenCV does), without the error check that
    would make a GPU wait; a singular ``H`` gives non-finite maps."""
    if H.dim() != 3 or tuple(H.shape[-2:]) != (3, 3):
        raise ValueError(f"H must have shape (B, 3, 3), got {tuple(H.shape)}")
    Hi = torch.linalg.inv_ex(H.to(torch.float64)).inverse.to(dtype)
    W_out, H_out = dsize
    xs = torch.arange(W_out, dtype=dtype, device=H.device).view(1, 1, W_out)
    ys = torch.arange(H_out, dtype=dtype, device=H.device).view(1, H_out, 1)
    m = Hi.reshape(-1, 9, 1, 1)
    z = m[:, 6] * xs + m[:, 7] * ys + m[:, 8]
    return (m[:, 0] * xs + m[:, 1] * ys + m[:, 2]) / z, (m[:, 3] * xs + m[:, 4] * ys + m[:, 5]) / z


def warp_perspective(images: Tensor, H: Tensor, dsize: tuple[int, int], border: Border = "constant",
                     value: float | Sequence[float] | Tensor = 0.0) -> Tensor:
    """``cv2.warpPerspective(images[b], H[b], dsize, INTER_LINEAR, borderMode=border,
    borderValue=value)`` for each b: input pixel x lands on ``H @ x``.

    images (B, C, h, w) uint8 or float; H (B, 3, 3) source -> destination pixels; dsize
    (W_out, H_out).  Returns (B, C, H_out, W_out) in ``images``' dtype."""
    _check_images(images)
    if H.shape[0] != images.shape[0]:
        raise ValueError(f"H must hold one matrix per image ({images.shape[0]}), got {tuple(H.shape)}")
    map_x, map_y = perspective_maps(H.to(images.device), dsize)
    return remap(images, map_x, map_y, border, value)


YUV_BLACK = (16, 128, 128)  # limited-range black, as ffmpeg converts RGB (0, 0, 0)


def yuv420_planes(frames: Tensor, size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Views of yuv420p frames (B, h * 3 // 2, w) as Y (B, 1, h, w) and U, V (B, 2, h/2, w/2)."""
    w, h = size
    if w % 2 or h % 2:
        raise ValueError(f"yuv420p frames must have an even size, got {w}x{h}")
    if frames.dim() != 3 or tuple(frames.shape[1:]) != (h * 3 // 2, w):
        raise ValueError(f"frames must have shape (B, {h * 3 // 2}, {w}) for {w}x{h}, got {tuple(frames.shape)}")
    flat = frames.reshape(frames.shape[0], -1)
    return flat[:, :w * h].reshape(-1, 1, h, w), flat[:, w * h:].reshape(-1, 2, h // 2, w // 2)


def chroma_matrices(H: Tensor, size: tuple[int, int]) -> Tensor:
    """H (..., 3, 3) between full-size frames of ``size`` (w, h) as the same warp between their
    half-size chroma planes, ``S H S^-1`` with S :func:`~mosaic_cli.geometry.resize_matrix`
    (pixel centres kept: a chroma sample sits between four luma ones)."""
    w, h = size
    R = resize_matrix((w, h), (w // 2, h // 2))
    # S and its inverse filled in on H's device from numbers (no host copy, no inverse's check).
    S = torch.eye(3, dtype=torch.float64, device=H.device)
    Si = torch.eye(3, dtype=torch.float64, device=H.device)
    for i in range(2):
        S[i, i], S[i, 2] = float(R[i, i]), float(R[i, 2])
        Si[i, i], Si[i, 2] = 1.0 / float(R[i, i]), -float(R[i, 2]) / float(R[i, i])
    return (S @ H.to(torch.float64) @ Si).to(H.dtype)


def warp_yuv420(frames: Tensor, H: Tensor, size: tuple[int, int], border: Border = "constant",
                black: Sequence[float] = YUV_BLACK) -> Tensor:
    """``stabilize/render.py``'s ``warp_yuv`` batched: each yuv420p frame warped by its ``H``,
    luma at full size, chroma by the same warp at half size (:func:`chroma_matrices`).

    frames (B, h * 3 // 2, w) uint8, the Y, U and V planes one after the other; H (B, 3, 3)
    source -> destination, full-size pixels; size (w, h), even; ``black``: the constant border's
    (Y, U, V).  Returns (B, h * 3 // 2, w) uint8, a new tensor."""
    y, uv = yuv420_planes(frames, size)
    w, h = size
    H = H.to(device=frames.device, dtype=torch.float64)
    out = torch.empty_like(frames)
    out_y, out_uv = yuv420_planes(out, size)
    out_y.copy_(warp_perspective(y, H, (w, h), border, black[0]))
    out_uv.copy_(warp_perspective(uv, chroma_matrices(H, size), (w // 2, h // 2), border, list(black[1:3])))
    return out


def remap_yuv420(frames: Tensor, map_x: Tensor, map_y: Tensor, chroma_x: Tensor, chroma_y: Tensor, size: tuple[int, int],
                 border: Border = "constant", black: Sequence[float] = YUV_BLACK) -> Tensor:
    """:func:`remap` of yuv420p frames: luma by the full-size maps (B, h, w), chroma by the
    half-size ones (B, h/2, w/2), in half-size pixels.  frames (B, h * 3 // 2, w) uint8;
    returns the same shape, a new tensor."""
    y, uv = yuv420_planes(frames, size)
    out = torch.empty_like(frames)
    out_y, out_uv = yuv420_planes(out, size)
    out_y.copy_(remap(y, map_x, map_y, border, black[0]))
    out_uv.copy_(remap(uv, chroma_x, chroma_y, border, list(black[1:3])))
    return out


__all__ = [
    "BORDERS",
    "Border",
    "YUV_BLACK",
    "border_index",
    "chroma_matrices",
    "perspective_maps",
    "remap",
    "remap_nearest",
    "remap_yuv420",
    "warp_perspective",
    "warp_yuv420",
    "yuv420_planes",
]
