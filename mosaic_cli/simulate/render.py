"""Render the frames of a planned flight from a map, anti-aliased, one frame at a time.

Each frame is a ``cv2.warpPerspective`` of a map pyramid level (levels every half octave,
made with area averaging).  The level is picked per frame from the largest local
down-sampling factor over the frame (through a lens, per pixel: :func:`render_lens`), and the
two levels around it are blended (trilinear filtering), so down-sampling never aliases and
zooming in or out never pops.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator

import cv2
import numpy as np

from mosaic_cli.geometry import frame_corners, resize_matrix
from mosaic_cli.geometry.lens import Lens, distorted_grid
from mosaic_cli.geometry.rolling_shutter import row_frame_to_ref
from mosaic_cli.simulate.bursts import CODES, PIXEL_KINDS
from mosaic_cli.simulate.trajectory import FlightPlan

LEVEL_STEP = np.sqrt(2.0)  # scale factor between pyramid levels
GLARE, GUST, DARK, FLAT = (CODES[k] for k in PIXEL_KINDS)  # the burst codes of a frame's effects
BURST_NOISE = 2.0  # gray levels of sensor noise on a spoilt frame of a flight otherwise clean


class MapPyramid:
    """Half-octave levels of a map, built on demand and cached."""

    def __init__(self, map_rgb: np.ndarray):
        if map_rgb.ndim != 3 or map_rgb.shape[2] != 3 or map_rgb.dtype != np.uint8:
            raise ValueError("map must be an RGB uint8 array (H, W, 3)")
        self.base = np.ascontiguousarray(map_rgb)
        self.size = (map_rgb.shape[1], map_rgb.shape[0])
        self._levels: dict[int, tuple[np.ndarray, np.ndarray]] = {0: (self.base, np.eye(3))}

    def level(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(image, matrix map pixel -> level pixel) of level ``k`` (scale 1 / sqrt(2)^k)."""
        if k not in self._levels:
            W, H = self.size
            factor = LEVEL_STEP**k
            size = (max(1, int(round(W / factor))), max(1, int(round(H / factor))))
            # From the nearest finer level that is cached (area averaging keeps it alias-free).
            src_k = max(j for j in self._levels if j < k)
            src, _ = self._levels[src_k]
            img = cv2.resize(src, size, interpolation=cv2.INTER_AREA)
            self._levels[k] = (img, resize_matrix(self.size, size))
        return self._levels[k]


def max_scale(frame_to_map: np.ndarray, size: tuple[int, int]) -> float:
    """Largest local down-sampling factor (map pixels per frame pixel, any direction) over the
    frame's corners and centre."""
    w, h = size
    pts = np.vstack([frame_corners(w, h), [[(w - 1) / 2.0, (h - 1) / 2.0]]])
    Hm = np.asarray(frame_to_map, dtype=np.float64)
    homog = np.concatenate([pts, np.ones((len(pts), 1))], 1) @ Hm.T
    z = homog[:, 2:3]
    uv = homog[:, :2] / z
    # Jacobian of the projective map at each point: (A - uv * h3^T) / z
    J = (Hm[None, :2, :2] - uv[:, :, None] * Hm[None, 2:3, :2]) / z[:, :, None]
    return float(np.linalg.svd(J, compute_uv=False).max())


def _warp(pyramid: MapPyramid, k: int, map_to_frame: np.ndarray, size) -> np.ndarray:
    img, S = pyramid.level(k)
    H = map_to_frame @ np.linalg.inv(S)
    return cv2.warpPerspective(img, H, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT101)


def render_view(pyramid: MapPyramid, map_to_frame: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """One anti-aliased RGB frame of ``size`` (w, h) seeing the map through ``map_to_frame``."""
    size = (int(size[0]), int(size[1]))
    scale = max_scale(np.linalg.inv(map_to_frame), size)
    if scale <= 1.0:
        return _warp(pyramid, 0, map_to_frame, size)
    lod = 2.0 * np.log2(scale)  # in half octaves
    k0 = int(np.floor(lod))
    frac = lod - k0
    a = _warp(pyramid, k0, map_to_frame, size)
    if frac < 1e-3:
        return a
    b = _warp(pyramid, k0 + 1, map_to_frame, size)
    return cv2.addWeighted(a, 1.0 - frac, b, frac, 0.0)


def render_rolling(pyramid: MapPyramid, band_map_to_frame: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """One anti-aliased RGB frame of a rolling-shutter camera: each row sees the map through its
    own homography (the bands' (K, 3, 3), blended by :func:`row_frame_to_ref`), by one
    ``cv2.remap`` per pyramid level.  The level is the mid band's, for the whole frame."""
    w, h = int(size[0]), int(size[1])
    rows = np.arange(h, dtype=np.float64)
    F = row_frame_to_ref(np.linalg.inv(band_map_to_frame), rows, h)  # (h, 3, 3) frame -> map per row
    x = np.arange(w, dtype=np.float64)[None, :]
    mid = band_map_to_frame[len(band_map_to_frame) // 2]
    scale = max_scale(np.linalg.inv(mid), size)
    lod = 2.0 * np.log2(scale) if scale > 1.0 else 0.0
    k0 = int(np.floor(lod))
    frac = lod - k0

    def remap(k: int) -> np.ndarray:
        img, S = pyramid.level(k)
        G = S @ F  # frame -> level pixels, per row
        z = G[:, 2, 0, None] * x + (G[:, 2, 1] * rows + G[:, 2, 2])[:, None]
        u = (G[:, 0, 0, None] * x + (G[:, 0, 1] * rows + G[:, 0, 2])[:, None]) / z
        v = (G[:, 1, 0, None] * x + (G[:, 1, 1] * rows + G[:, 1, 2])[:, None]) / z
        return cv2.remap(img, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT101)

    a = remap(k0)
    if frac < 1e-3:
        return a
    return cv2.addWeighted(a, 1.0 - frac, remap(k0 + 1), frac, 0.0)


class LensGrid:
    """A lens's view of the pinhole frame, for :func:`render_lens`: for each pixel of the
    distorted frame, the pinhole pixel (camera ``lens.K``) it shows (``x``, ``y``: (h, w)), and
    the lens's local stretch there (``stretch``, (h, w): pinhole pixels per frame pixel, the
    longer of the steps one frame pixel across and one down makes), from which each pixel's
    pyramid level is chosen so that the squeezed edges of a wide lens do not alias while its
    centre keeps the pinhole's sharpness."""

    def __init__(self, lens: Lens):
        self.x, self.y = distorted_grid(lens)
        steps = [np.hypot(np.gradient(self.x, axis=axis), np.gradient(self.y, axis=axis)) for axis in (0, 1)]
        self.stretch = np.maximum(*steps).astype(np.float32)


def render_lens(pyramid: MapPyramid, map_to_frame: np.ndarray, grid: LensGrid) -> np.ndarray:
    """One anti-aliased RGB frame seen through a lens: each pixel shows the map where the
    pinhole frame of ``map_to_frame`` has the pixel ``grid`` gives it, by one ``cv2.remap`` per
    pyramid level the frame needs (one resampling of the map, as :func:`render_view`).

    The level is chosen per pixel (trilinear filtering, as a GPU's mip-mapping): a fisheye
    squeezes the pinhole frame 3-4x at its corners and not at all at its centre, and one level
    for the whole frame, the corners', would blur the centre as no real lens does."""
    h, w = grid.x.shape
    F = np.linalg.inv(map_to_frame)  # pinhole frame -> map
    scale = max_scale(F, (w, h)) * np.maximum(grid.stretch, 1.0)
    lod = np.where(scale > 1.0, 2.0 * np.log2(np.maximum(scale, 1.0)), 0.0).astype(np.float32)  # half octaves, per pixel
    first, last = int(np.floor(lod.min())), int(np.floor(lod.max())) + 1

    def remap(k: int) -> np.ndarray:
        img, S = pyramid.level(k)
        G = S @ F
        z = G[2, 0] * grid.x + G[2, 1] * grid.y + G[2, 2]
        u = (G[0, 0] * grid.x + G[0, 1] * grid.y + G[0, 2]) / z
        v = (G[1, 0] * grid.x + G[1, 1] * grid.y + G[1, 2]) / z
        return cv2.remap(img, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT101)

    if last - first == 1 and float(lod.max() - first) < 1e-3:  # one level serves every pixel
        return remap(first)
    out = np.zeros((h, w, 3), np.float32)
    for k in range(first, last + 1):
        weight = np.clip(1.0 - np.abs(lod - k), 0.0, 1.0)  # the two levels around each pixel's, linearly
        if weight.max() > 0:
            out += remap(k).astype(np.float32) * weight[..., None]
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def apply_effects(frame: np.ndarray, effects: dict[str, np.ndarray], t: int, seed: int) -> np.ndarray:
    """Motion blur, contrast, vignetting, exposure gain and sensor noise of frame ``t`` (degraded profiles),
    and the burst that spoils it, if any (:mod:`mosaic_cli.simulate.bursts`)."""
    out = frame
    burst = int(effects["burst"][t]) if "burst" in effects else 0  # simulate.bursts.CODES
    level = float(effects["burst_level"][t]) if burst else 0.0
    if "blur" in effects or burst == GUST:
        bx, by = (float(v) for v in effects["blur"][t]) if "blur" in effects else (0.0, 0.0)
        if burst == GUST:  # a gust: the camera swings far during the exposure
            angle, length = float(effects["burst_angle"][t]), level * frame.shape[1] / 1280.0
            bx, by = bx + length * np.cos(angle), by + length * np.sin(angle)
        length = float(np.hypot(bx, by))
        if length >= 1.0:
            ksize = int(np.ceil(length)) | 1
            ksize = max(3, ksize)
            kernel = np.zeros((ksize, ksize), np.float32)
            c = ksize // 2
            steps = max(2, int(np.ceil(length * 2)))
            for s in np.linspace(-0.5, 0.5, steps):
                x, y = c + s * bx, c + s * by
                x0, y0 = int(np.floor(x)), int(np.floor(y))
                fx, fy = x - x0, y - y0
                for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
                    if 0 <= x0 + dx < ksize and 0 <= y0 + dy < ksize:
                        kernel[y0 + dy, x0 + dx] += wgt
            kernel /= kernel.sum()
            out = cv2.filter2D(out, -1, kernel, borderType=cv2.BORDER_REFLECT101)
    gain = float(effects["gain"][t]) if "gain" in effects else 1.0
    sigma = float(effects["noise_sigma"][t]) if "noise_sigma" in effects else 0.0
    contrast = float(effects["contrast"][t]) if "contrast" in effects else 1.0
    vignette = float(effects["vignette"][t]) if "vignette" in effects else 0.0
    if burst:
        sigma = max(sigma, BURST_NOISE)  # a spoilt frame is never clean: the sensor's floor shows
        if burst == FLAT:
            contrast *= level
        elif burst == DARK:
            gain *= level
    if gain != 1.0 or sigma > 0 or contrast != 1.0 or vignette > 0 or burst == GLARE:
        h, w = out.shape[:2]
        f = out.astype(np.float32)
        if burst == GLARE:  # washed out toward white, a faint residue of the ground left
            f = 255.0 - (255.0 - f) * level
        if contrast != 1.0:  # haze, flat ground: detail fades toward the scene's mean
            mean = cv2.mean(f)[:3]
            f = cv2.addWeighted(f, contrast, np.full_like(f, mean), 1.0 - contrast, 0.0)
        if vignette > 0:
            f *= vignette_map((w, h), round(vignette, 4))[..., None]
        if sigma > 0:
            # Luma noise at full resolution plus a little blotchy chroma noise, like a small
            # sensor; OpenCV's generator, seeded per frame, is several times faster than numpy's.
            cv2.setRNGSeed(int((int(seed) * 1_000_003 + int(t) * 7919 + 104729) % 2_147_483_647))
            luma = np.empty((h, w), np.float32)
            cv2.randn(luma, 0.0, sigma)
            chroma = np.empty(((h + 1) // 2, (w + 1) // 2, 3), np.float32)
            cv2.randn(chroma, (0.0, 0.0, 0.0), (0.35 * sigma,) * 3)
            noise = cv2.resize(chroma, (w, h), interpolation=cv2.INTER_NEAREST)
            noise += luma[..., None]
            f = cv2.scaleAdd(f, gain, noise)
        else:
            f *= gain
        out = np.clip(f, 0, 255, out=f).astype(np.uint8)
    return out


@functools.lru_cache(maxsize=8)
def vignette_map(size: tuple[int, int], strength: float) -> np.ndarray:
    """(h, w) float32 brightness factor of a lens's smooth radial falloff: 1 at the centre,
    ``1 - strength`` at the corners."""
    w, h = int(size[0]), int(size[1])
    x = (np.arange(w, dtype=np.float32) - (w - 1) / 2) / max((w - 1) / 2, 1)
    y = (np.arange(h, dtype=np.float32) - (h - 1) / 2) / max((h - 1) / 2, 1)
    r2 = (x[None, :] ** 2 * w * w + y[:, None] ** 2 * h * h) / float(w * w + h * h)  # 1 at the corners
    return (1.0 - strength * r2 * r2 * (3 - 2 * r2)).astype(np.float32)


def render_frames(map_rgb: np.ndarray, plan: FlightPlan, lens: Lens | None = None) -> Iterator[np.ndarray]:
    """Stream the RGB uint8 frames (h, w, 3) of ``plan`` over ``map_rgb``; ``lens``: seen
    through it (the plan's homographies are then its pinhole frames', camera ``lens.K``)."""
    if (map_rgb.shape[1], map_rgb.shape[0]) != tuple(plan.map_size) and tuple(plan.map_size) != (0, 0):
        raise ValueError(f"plan made for a {plan.map_size} map, got {map_rgb.shape[1]}x{map_rgb.shape[0]}")
    pyramid = MapPyramid(map_rgb)
    grid = None if lens is None else LensGrid(lens.at(plan.size))
    for t in range(plan.frames):
        if grid is not None:
            frame = render_lens(pyramid, plan.map_to_frame[t], grid)
        elif plan.row_bands is not None and plan.rolling is not None and plan.rolling.readout > 0:
            frame = render_rolling(pyramid, plan.row_bands[t], plan.size)
        else:
            frame = render_view(pyramid, plan.map_to_frame[t], plan.size)
        if plan.effects:
            frame = apply_effects(frame, plan.effects, t, plan.seed)
        yield frame
