"""The canvas warps and the multi-band blend of stitch's compose (:mod:`mosaic_cli.stitch.compose`)
in torch, on any device: the GPU under ``stitch --device cuda``, torch's CPU in tests.

:class:`MultiBandBlender` is ``cv2.detail.MultiBandBlender`` (float weights, OpenCV's CPU code
path) step by step: the same padded canvas and source rectangles, the same borders (the image
mirrored with ``BORDER_REFLECT``, the weights bordered with zeros, ``pyrDown``/``pyrUp`` with
``BORDER_REFLECT_101``), the same integer rounding of the int16 pyramids and the same truncations
where OpenCV casts to ``short``.  The int16 pyramids are held as integer-valued float32: every
sum the 5-tap kernels make stays below 2^24, so float32 holds it exactly and the pyramids agree
with OpenCV's to the bit; only the float weights' sums may differ in their last bits.

:class:`FeatherBlender` and :class:`PlainBlender` are ``cv2.detail.FeatherBlender`` and
``cv2.detail.Blender`` (``--blend feather`` and ``none``) likewise, to the bit.

:class:`DeviceSource` warps a keyframe into a canvas strip with :mod:`mosaic_cli.geometry.warp`,
as compose's ``warp_into`` does with OpenCV: ``INTER_LINEAR`` and ``BORDER_REPLICATE`` (the
image), ``INTER_NEAREST`` with a zero border (its coverage mask).

Not imported by ``mosaic_cli.stitch``: compose imports it when a torch device is asked for
(``ComposeOptions.torch_device``), so that the OpenCV path never loads torch for it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from mosaic_cli.geometry.homography import resize_matrix
from mosaic_cli.geometry.warp import border_index, perspective_maps, remap, remap_nearest, warp_perspective

WEIGHT_EPS = 1e-5  # OpenCV's blenders.cpp: a pixel no weight reached stays uncovered
# OpenCV's float constants, as float32 rounds them (a Python float scalar is applied to a float32
# tensor in float32): the mask's 1/255 and the weight's epsilon.
_INV_255 = float(np.float32(1.0 / 255.0))
_WEIGHT_EPS32 = float(np.float32(WEIGHT_EPS))


# --- borders and pyramids ---------------------------------------------------------------------


def _pad(x: Tensor, top: int, bottom: int, left: int, right: int,
         mode: Literal["constant", "replicate", "reflect", "reflect101"]) -> Tensor:
    """``x`` (..., H, W) padded as ``cv2.copyMakeBorder`` with ``mode`` (see
    :func:`~mosaic_cli.geometry.warp.border_index`), or with zeros (``constant``)."""
    if mode == "constant":
        return torch.nn.functional.pad(x, (left, right, top, bottom))
    h, w = x.shape[-2:]
    rows = border_index(torch.arange(-top, h + bottom, device=x.device), h, mode)
    cols = border_index(torch.arange(-left, w + right, device=x.device), w, mode)
    return x.index_select(-2, rows).index_select(-1, cols)


def pyr_down(x: Tensor, integer: bool = True) -> Tensor:
    """``cv2.pyrDown``: ``x`` (..., H, W) float -> (..., (H + 1) // 2, (W + 1) // 2), the 5-tap
    binomial with BORDER_REFLECT_101, rows first.  ``integer``: ``x`` holds integers (an int16
    image) and the result is rounded as OpenCV's fixed point does, floor((s + 128) / 256);
    else (float weights) s / 256."""
    h, w = x.shape[-2:]
    oh, ow = (h + 1) // 2, (w + 1) // 2
    # Output k takes the inputs 2k - 2 .. 2k + 2: two samples of border before, enough after.
    p = _pad(x, 2, 2 * oh + 2 - h, 2, 2 * ow + 2 - w, "reflect101")
    c = [p[..., k:k + 2 * ow - 1:2] for k in range(5)]
    p = c[0] + c[4] + (c[1] + c[3]) * 4 + c[2] * 6
    r = [p[..., k:k + 2 * oh - 1:2, :] for k in range(5)]
    s = r[0] + r[4] + (r[1] + r[3]) * 4 + r[2] * 6
    return torch.floor((s + 128) / 256) if integer else s * (1.0 / 256)


def pyr_up(x: Tensor, integer: bool = True) -> Tensor:
    """``cv2.pyrUp`` to twice the size: ``x`` (..., H, W) float -> (..., 2H, 2W).  OpenCV pads
    the zero-interleaved image with BORDER_REFLECT_101, which makes the first output of an axis
    s[1] + 6 s[0] + s[1] and its last two s[n-2] + 7 s[n-1] and 8 s[n-1].  ``integer``: rounded
    as OpenCV's fixed point does, floor((s + 32) / 64); else s / 64."""
    h, w = x.shape[-2:]
    # Along x: one sample before the axis (reflected: s[1]) and one after (replicated: s[n-1]).
    p = torch.cat([x[..., min(1, w - 1):min(1, w - 1) + 1], x, x[..., w - 1:]], dim=-1)
    even, odd = p[..., :w] + p[..., 1:w + 1] * 6 + p[..., 2:], (p[..., 1:w + 1] + p[..., 2:]) * 4
    x = torch.stack([even, odd], dim=-1).reshape(*x.shape[:-1], 2 * w)
    p = torch.cat([x[..., min(1, h - 1):min(1, h - 1) + 1, :], x, x[..., h - 1:, :]], dim=-2)
    even, odd = p[..., :h, :] + p[..., 1:h + 1, :] * 6 + p[..., 2:, :], (p[..., 1:h + 1, :] + p[..., 2:, :]) * 4
    s = torch.stack([even, odd], dim=-2).reshape(*x.shape[:-2], 2 * h, 2 * w)
    return torch.floor((s + 32) / 64) if integer else s * (1.0 / 64)


def laplacian_pyramid(image: Tensor, levels: int) -> list[Tensor]:
    """OpenCV's ``createLaplacePyr`` of an int16 image held as integer-valued float: ``image``
    (..., H, W), H and W divisible by 2**levels -> ``levels`` + 1 tensors, each level minus the
    next one brought up (:func:`pyr_up`), the last the coarsest Gaussian level."""
    gauss = [image]
    for _ in range(levels):
        gauss.append(pyr_down(gauss[-1]))
    return [g - pyr_up(n) for g, n in zip(gauss[:-1], gauss[1:])] + [gauss[-1]]


def collapse(pyramid: list[Tensor]) -> Tensor:
    """OpenCV's ``restoreImageFromLaplacePyr``: the finest level of ``pyramid`` (integer-valued,
    each level (..., 2H, 2W) of the next) with every coarser level brought up and added, as
    int16 saturates."""
    out = pyramid[-1]
    for level in reversed(pyramid[:-1]):
        out = (pyr_up(out) + level).clamp(-32768, 32767)
    return out


@dataclass
class _Feed:
    """Where one fed image lands: its padded source rectangle in the blender's canvas (x0, y0,
    x1, y1, level-0 px, on the pyramid's grid) and the border it gets (top, bottom, left, right)."""

    box: tuple[int, int, int, int]
    border: tuple[int, int, int, int]


class MultiBandBlender:
    """``cv2.detail.MultiBandBlender(0, num_bands)`` (float weights) in torch on ``device``:
    :meth:`prepare` a canvas rectangle, :meth:`feed` images with their masks, :meth:`blend`.

    ``feed`` takes what ``cv2.detail`` takes (an int16 (h, w, 3) array and a uint8 (h, w) mask)
    or tensors already on the device: an integer-valued float (3, h, w) image and a (h, w) mask
    (0..255), so that the warps need not come back to the host.  ``blend`` returns numpy arrays
    as OpenCV does: the (H, W, 3) int16 image (zero where uncovered) and the (H, W) uint8 mask.
    """

    def __init__(self, num_bands: int, device: torch.device | str = "cpu"):
        self.requested_bands = num_bands
        self.device = torch.device(device)

    def prepare(self, roi: tuple[int, int, int, int]) -> None:
        x, y, w, h = (int(v) for v in roi)
        self.final = (w, h)
        # As OpenCV: no more bands than the canvas' longest side allows, and the canvas grown to
        # a multiple of 2**bands so that every level is exactly half the one below.
        self.bands = min(self.requested_bands, int(np.ceil(np.log(max(w, h)) / np.log(2.0))))
        unit = 1 << self.bands
        w, h = w + (unit - w % unit) % unit, h + (unit - h % unit) % unit
        self.roi = (x, y, w, h)
        self.images: list[Tensor] = []
        self.weights: list[Tensor] = []
        for _ in range(self.bands + 1):
            self.images.append(torch.zeros(3, h, w, device=self.device))
            self.weights.append(torch.zeros(h, w, device=self.device))
            h, w = (h + 1) // 2, (w + 1) // 2

    def _place(self, tl: tuple[int, int], size: tuple[int, int]) -> _Feed:
        """OpenCV's feed(): the source rectangle grown by 3 * 2**bands on each side, clipped to
        the canvas, its corner moved down onto the grid and its size up to the grid."""
        X, Y, W, H = self.roi
        unit = 1 << self.bands
        gap = 3 * unit
        x0, y0 = max(X, tl[0] - gap), max(Y, tl[1] - gap)
        x1, y1 = min(X + W, tl[0] + size[0] + gap), min(Y + H, tl[1] + size[1] + gap)
        x0, y0 = X + ((x0 - X) >> self.bands << self.bands), Y + ((y0 - Y) >> self.bands << self.bands)
        width, height = x1 - x0, y1 - y0
        x1 = x0 + width + (unit - width % unit) % unit
        y1 = y0 + height + (unit - height % unit) % unit
        dx, dy = max(x1 - (X + W), 0), max(y1 - (Y + H), 0)
        x0, x1, y0, y1 = x0 - dx, x1 - dx, y0 - dy, y1 - dy
        border = (tl[1] - y0, y1 - tl[1] - size[1], tl[0] - x0, x1 - tl[0] - size[0])
        return _Feed((x0 - X, y0 - Y, x1 - X, y1 - Y), border)

    def feed(self, image: np.ndarray | Tensor, mask: np.ndarray | Tensor, tl: tuple[int, int]) -> None:
        """Add ``image`` ((h, w, 3) int16 array, or (3, h, w) integer-valued float tensor) and its
        blend ``mask`` ((h, w), 0..255) with its top-left corner at canvas pixel ``tl``."""
        img = _as_image(image, self.device)
        weight = _as_mask(mask, self.device) * _INV_255
        place = self._place((int(tl[0]), int(tl[1])), (img.shape[-1], img.shape[-2]))
        top, bottom, left, right = place.border
        bands = laplacian_pyramid(_pad(img, top, bottom, left, right, "reflect"), self.bands)
        weight = _pad(weight, top, bottom, left, right, "constant")
        x0, y0, x1, y1 = place.box
        for level, band in enumerate(bands):
            # OpenCV adds static_cast<short>(value * weight): truncated toward zero.
            self.images[level][:, y0:y1, x0:x1] += torch.trunc(band * weight)
            self.weights[level][y0:y1, x0:x1] += weight
            if level < self.bands:
                weight = pyr_down(weight, integer=False)
            x0, y0, x1, y1 = x0 // 2, y0 // 2, x1 // 2, y1 // 2

    def blend(self, dst: object = None, dst_mask: object = None) -> tuple[np.ndarray, np.ndarray]:
        """The blended canvas: (H, W, 3) int16 (zero where uncovered) and its (H, W) uint8 mask
        (255 where any weight reached).  ``dst``/``dst_mask``: ignored (cv2's signature)."""
        return _to_host(*self.blend_tensors())

    def blend_tensors(self) -> tuple[Tensor, Tensor]:
        """:meth:`blend` on the device: the (3, H, W) integer-valued float image and the (H, W)
        bool coverage.  The blender is spent afterwards."""
        levels = [torch.trunc(image / (weight + _WEIGHT_EPS32)) for image, weight in zip(self.images, self.weights)]
        w, h = self.final
        image = collapse(levels)[:, :h, :w]
        covered = self.weights[0][:h, :w] > WEIGHT_EPS
        self.images, self.weights = [], []
        return image * covered, covered


def distance_l1(mask: Tensor) -> Tensor:
    """``cv2.distanceTransform(mask, DIST_L1, 3)``: each pixel's city-block distance (float32) to
    the nearest zero of ``mask`` (..., H, W), inf where it has none (OpenCV: FLT_MAX); the
    outside of the image is not zero.  Exact: the L1 distance is separable, and along one axis
    min_j(|i - j| + g_j) is the smaller of two running minima, of g_j - j and of g_j + j."""
    g = torch.where(mask == 0, 0.0, torch.inf).to(torch.float32)

    def along(g: Tensor, dim: int) -> Tensor:
        n = g.shape[dim]
        shape = [1] * g.dim()
        shape[dim] = n
        i = torch.arange(n, dtype=g.dtype, device=g.device).reshape(shape)
        before = torch.cummin(g - i, dim=dim).values + i
        after = torch.cummin((g + i).flip(dim), dim=dim).values.flip(dim) - i
        return torch.minimum(before, after)

    return along(along(g, -1), -2)


class FeatherBlender:
    """``cv2.detail.FeatherBlender(sharpness)`` in torch on ``device``: each image weighted by its
    mask's L1 distance to the mask's edge times ``sharpness``, at most 1; the same API as
    :class:`MultiBandBlender`."""

    def __init__(self, sharpness: float, device: torch.device | str = "cpu"):
        self.sharpness = float(np.float32(sharpness))
        self.device = torch.device(device)

    def prepare(self, roi: tuple[int, int, int, int]) -> None:
        x, y, w, h = (int(v) for v in roi)
        self.roi = (x, y, w, h)
        self.image = torch.zeros(3, h, w, device=self.device)
        self.weight = torch.zeros(h, w, device=self.device)

    def feed(self, image: np.ndarray | Tensor, mask: np.ndarray | Tensor, tl: tuple[int, int]) -> None:
        """As :meth:`MultiBandBlender.feed`."""
        img = _as_image(image, self.device)
        weight = (distance_l1(_as_mask(mask, self.device)) * self.sharpness).clamp_(max=1.0)
        x0, y0 = int(tl[0]) - self.roi[0], int(tl[1]) - self.roi[1]
        h, w = weight.shape
        self.image[:, y0:y0 + h, x0:x0 + w] += torch.trunc(img * weight)  # static_cast<short>, as OpenCV
        self.weight[y0:y0 + h, x0:x0 + w] += weight

    def blend(self, dst: object = None, dst_mask: object = None) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`MultiBandBlender.blend`."""
        covered = self.weight > WEIGHT_EPS
        image = torch.trunc(self.image / (self.weight + _WEIGHT_EPS32)) * covered
        return _to_host(image, covered)


class PlainBlender:
    """``cv2.detail.Blender`` (``--blend none``) in torch: each pixel takes the last image fed
    there with a non-zero mask, and its mask is every mask's there OR-ed bit by bit (soft masks
    give soft alphas, as OpenCV's); the same API as :class:`MultiBandBlender`."""

    def __init__(self, device: torch.device | str = "cpu"):
        self.device = torch.device(device)

    def prepare(self, roi: tuple[int, int, int, int]) -> None:
        x, y, w, h = (int(v) for v in roi)
        self.roi = (x, y, w, h)
        self.image = torch.zeros(3, h, w, device=self.device)
        self.mask = torch.zeros(h, w, dtype=torch.uint8, device=self.device)

    def feed(self, image: np.ndarray | Tensor, mask: np.ndarray | Tensor, tl: tuple[int, int]) -> None:
        """As :meth:`MultiBandBlender.feed`."""
        img, bits = _as_image(image, self.device), _as_mask(mask, self.device).to(torch.uint8)
        x0, y0 = int(tl[0]) - self.roi[0], int(tl[1]) - self.roi[1]
        h, w = bits.shape
        region = self.image[:, y0:y0 + h, x0:x0 + w]
        region.copy_(torch.where(bits > 0, img, region))
        self.mask[y0:y0 + h, x0:x0 + w] |= bits

    def blend(self, dst: object = None, dst_mask: object = None) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`MultiBandBlender.blend`."""
        return self.image.mul(self.mask > 0).permute(1, 2, 0).to(torch.int16).cpu().numpy(), self.mask.cpu().numpy()


def _to_host(image: Tensor, covered: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """A blender's result as OpenCV returns it: (H, W, 3) int16 and (H, W) uint8 0/255."""
    return image.permute(1, 2, 0).to(torch.int16).cpu().numpy(), covered.to(torch.uint8).mul_(255).cpu().numpy()


def _as_image(image: np.ndarray | Tensor, device: torch.device) -> Tensor:
    if isinstance(image, Tensor):
        return image.to(device=device, dtype=torch.float32)
    return torch.from_numpy(np.ascontiguousarray(image)).to(device).permute(2, 0, 1).float()


def _as_mask(mask: np.ndarray | Tensor, device: torch.device) -> Tensor:
    if isinstance(mask, Tensor):
        return mask.to(device=device, dtype=torch.float32)
    return torch.from_numpy(np.ascontiguousarray(mask)).to(device).float()


# --- the canvas warps -------------------------------------------------------------------------


class DeviceSource:
    """One keyframe held on the device for compose's strips: its pixels as compose samples them
    (``image`` (h, w, 3) uint8, already shrunk where the warp shrinks it), their ``coverage``
    ((h, w) uint8, 255 = use; None: all), its ``seam`` mask at its canvas box's full size
    ((H, W) uint8) and its exposure ``gain`` (None, a scalar or a block map over the box).
    Uploaded once, however many strips it spans."""

    def __init__(self, image: np.ndarray, coverage: np.ndarray | None, seam: np.ndarray, gain: np.ndarray | None,
                 device: torch.device | str):
        self.device = torch.device(device)
        # held as uint8 (a quarter of float's memory: a strip may reach many keyframes)
        self.image = torch.from_numpy(np.ascontiguousarray(image)).to(self.device).permute(2, 0, 1).contiguous()
        # (1, 1, h, w) for remap_nearest; all covered: 255 expanded, a view that takes no memory
        self.coverage = (torch.full((1, 1, 1, 1), 255, dtype=torch.uint8, device=self.device).expand(1, 1, *image.shape[:2])
                         if coverage is None else torch.from_numpy(np.ascontiguousarray(coverage)).to(self.device)[None, None])
        self.seam = torch.from_numpy(np.ascontiguousarray(seam)).to(self.device)
        self.gain: float | Tensor | None = None
        if gain is not None and gain.size == 1:
            self.gain = float(gain.ravel()[0])
        elif gain is not None:
            self.gain = torch.as_tensor(np.asarray(gain, np.float32), device=self.device)

    @property
    def nbytes(self) -> int:
        """Device memory held (compose's cache counts it)."""
        held = [self.image, self.seam] + [t for t in (self.gain,) if isinstance(t, Tensor)]
        return sum(t.numel() * t.element_size() for t in held)

    def part(self, box: tuple[int, int, int, int], T: np.ndarray | None = None,
             maps: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[Tensor, Tensor]:
        """The part ``box`` = (c0, r0, c1, r1) of its canvas box, as compose's ``_tile_part``
        makes it: the (3, r1 - r0, c1 - c0) image (integer-valued float, 0..255), warped,
        rounded as a uint8 warp is, times the exposure gain and rounded again, and its blend
        mask (uint8: the seam mask where the warp covers).  The warp is ``T`` (3, 3: pixels ->
        the part's pixels) or, for a rolling shutter, the sampling maps (two arrays of the
        part's shape of pixel coordinates, as ``cv2.remap`` takes)."""
        c0, r0, c1, r1 = box
        if maps is not None:
            x, y = (torch.from_numpy(np.ascontiguousarray(m)).to(self.device)[None] for m in maps)
        elif T is not None:
            # float64 maps: a canvas is tens of thousands of pixels wide, where float32 maps
            # would move the mask's nearest samples (OpenCV's differ from both on a few pixels)
            x, y = perspective_maps(self._matrix(T), (c1 - c0, r1 - r0), torch.float64)
        else:
            raise ValueError("part() needs a homography or sampling maps")
        warped = remap(self.image[None], x, y, "replicate")[0].float()  # a uint8 warp, as OpenCV's
        covered = remap_nearest(self.coverage, x, y)[0, 0]
        if isinstance(self.gain, float):
            warped = torch.round(warped * float(np.float32(self.gain))).clamp_(0, 255)
        elif self.gain is not None:
            # the part of cv2.resize(gain, (W, H), INTER_LINEAR): bilinear at the resized pixel
            # centres, the edges replicated
            whole = (self.seam.shape[1], self.seam.shape[0])
            to_part = np.array([[1.0, 0.0, -c0], [0.0, 1.0, -r0], [0.0, 0.0, 1.0]]) @ resize_matrix((self.gain.shape[1], self.gain.shape[0]), whole)
            full = warp_perspective(self.gain[None, None], self._matrix(to_part), (c1 - c0, r1 - r0), "replicate")[0]
            warped = torch.round(warped * full).clamp_(0, 255)
        return warped, torch.bitwise_and(self.seam[r0:r1, c0:c1], covered)

    def _matrix(self, M: np.ndarray) -> Tensor:
        """A (3, 3) matrix as warp.py takes it: (1, 3, 3) float64 on the device."""
        return torch.as_tensor(np.asarray(M, np.float64), device=self.device)[None]
