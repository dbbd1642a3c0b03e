"""What the height and the field of view say of the mosaic's scale, and how sure they are.

A camera ``h`` metres above flat ground, looking straight down with a focal length of ``f``
pixels, sees ``h / f`` metres per pixel, whatever the GPS says.  Every keyframe of known height
gives that figure for its own view (undone of its tilt); how many mosaic pixels one of its
pixels covers the images say, so each keyframe gives an estimate of the mosaic's scale on the
ground.  Their errors are not independent:

- the height is barometric, zeroed at take-off: its error is mostly one offset for the whole
  flight (weather, temperature, airspeed; and the ground under the flight not level with the
  take-off point), ``height_accuracy`` metres, which no averaging over keyframes removes;
- the field of view a log gives is nominal (a focal length from the lens's name, a video
  mode's crop): ``fov_accuracy``, relative, of ``f``, again one error for the flight;
- the per-sample noise of the height and the images' own scale along the flight do average
  out: their scatter over the keyframes / sqrt(count).

So the prior is one figure with one relative sigma,

    sigma^2 = (height_accuracy / median height)^2 + fov_accuracy^2 + var(log estimates) / n,

and the adjustment weighs it against the GPS by that and by the GPS's own scale error (the
fixes' scatter over the track's extent, ``fit.scale_sigma``).  Pure arithmetic: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mosaic_cli.geo.fit import SCATTER

SCREEN = 5.0  # robust sigmas: a keyframe's estimate this far from the median is a misread height
SCREEN_FLOOR = 0.005  # relative: the screen never closer than this (an exact log has no scatter)


@dataclass
class HeightScale:
    per_keyframe: np.ndarray  # (N,) metres per untilted pixel expected from each keyframe's height (NaN: none, or screened out)
    mosaic_scale: float  # metres per mosaic pixel: the keyframes' estimates' mean (of logs)
    sigma: float  # relative uncertainty of ``mosaic_scale`` (module doc)
    used: int  # keyframes that entered


def height_scale(heights: np.ndarray, focal: float, mosaic_per_pixel: np.ndarray, height_accuracy: float,
                 fov_accuracy: float) -> HeightScale | None:
    """The mosaic's scale (metres per mosaic pixel) by the keyframes' ``heights`` (metres above
    the ground, NaN: unknown) and ``focal`` (pixels); ``mosaic_per_pixel[k]``: mosaic pixels per
    pixel of keyframe k's untilted view.  None when no keyframe has a height."""
    heights = np.asarray(heights, np.float64)
    per_pixel = np.asarray(mosaic_per_pixel, np.float64)
    known = np.isfinite(heights) & (heights > 0) & np.isfinite(per_pixel) & (per_pixel > 0)
    if not known.any() or not focal > 0:
        return None
    estimates = np.full(len(heights), np.nan)
    estimates[known] = np.log(heights[known] / focal / per_pixel[known])
    centre = float(np.median(estimates[known]))
    spread = SCATTER * float(np.median(np.abs(estimates[known] - centre)))
    kept = known & (np.abs(estimates - centre) <= max(SCREEN * spread, SCREEN_FLOOR))
    n = int(kept.sum())
    scatter = float(np.var(estimates[kept])) / n if n > 1 else 0.0
    sigma = math.sqrt((height_accuracy / float(np.median(heights[kept]))) ** 2 + fov_accuracy**2 + scatter)
    per_keyframe = np.where(kept, heights / focal, np.nan)
    return HeightScale(per_keyframe, float(math.exp(np.mean(estimates[kept]))), max(sigma, 1e-6), n)


def sigmas_apart(scale_a: float, sigma_a: float, scale_b: float, sigma_b: float) -> float:
    """How many combined sigmas two scale estimates (each with its relative sigma) lie apart."""
    return abs(math.log(scale_a / scale_b)) / max(math.hypot(sigma_a, sigma_b), 1e-12)
