"""The mosaic laid on the ground by one adjustment of GPS, camera attitude and the images.

The registered mosaic is the ground seen through one homography ``G`` (mosaic pixels ->
ground metres): the images fix its shape up to ``G``.  Four of ``G``'s eight degrees of
freedom are a similarity (position, scale, heading): the GPS fixes them.  The other four
(tilt and shear) are what chained registrations get slightly wrong, and GPS errors of metres
over a narrow survey strip barely see them; fitted from GPS alone they tilt every frame of
the map by a degree.  The camera's attitude sees them: keyframe ``k``, undone of its own
gimbal pitch and roll (``U_k``), looks straight down, so ``G P_k U_k^-1`` must be a
similarity on the ground.  A wrong tilt in ``G`` shows in every keyframe, more the farther
it lies from the mosaic's centre, so many keyframes pin it down and one keyframe's bad
reading bends nothing.  ``G`` minimises

    sum_k  w_k |G(n_k) - g_k|^2 / s_gps^2           GPS fix g_k of keyframe k's nadir point n_k
  + sum_k  v_k |nonsimilar(G P_k U_k^-1)|^2 / s_att^2   attitude, in the keyframe's own pixels
  + (mean_k log(s_k / (h_k / f)))^2 / s_scale^2      scale: keyframe k's untilted view seen at s_k metres
                                                      per pixel on the ground, h_k / f by its height
  + (heading of the reference view - compass)^2 / s_heading^2

with robust weights: Huber on both (``w_k``, ``v_k``), fixes beyond 3.5 robust sigmas out, and
each fix weighed by its worth under GPS errors correlated over seconds (``fit.fix_weights``: ten
fixes in two seconds are worth about one, two fixes a correlation time apart about one and a half).  The scale term is one equation for the
whole mosaic: the heights' error is mostly one offset for the flight, which averaging over the
keyframes does not remove, so ``s_scale`` is that offset's and the field of view's (georef.py).  ``level_mosaic`` is the attitude
term alone: it levels the mosaic before the robust similarity fit that starts the adjustment,
and says when the gimbal's angles and the images tell no one story.  Pure geometry: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mosaic_cli.geo.fit import OUTLIER, SimilarityPrior, axis_sigma, fix_weights, huber_weights, normaliser, robust_scatter, robust_weights
from mosaic_cli.geometry import normalize, project


@dataclass
class AttitudeViews:
    """Keyframes whose attitude is known: ``views[m]`` maps the m-th one's pixels undone of its
    tilt (a nadir view) into the mosaic; ``corners[m]`` are its frame corners in that view."""

    views: np.ndarray  # (M, 3, 3) untilted keyframe pixels -> mosaic pixels (P_k U_k^-1)
    corners: np.ndarray  # (M, 4, 2) untilted keyframe pixels
    sigma: float  # pixels: the non-similarity of one keyframe from an attitude error of the gimbal's accuracy

    def __len__(self) -> int:
        return len(self.views)


@dataclass
class GroundFit:
    matrix: np.ndarray  # 3x3, mosaic pixels -> ground (x, y) metres
    residuals: np.ndarray  # (F,) metres, per fix
    inliers: np.ndarray  # (F,) bool
    sigma: float  # robust scatter of the fixes about the fit (1.4826 x median distance)
    scale: float  # metres per untilted pixel of the prior's view (the reference keyframe)
    rotation: float  # radians, of that view
    attitude_residual: float  # median non-similarity of the keyframes, pixels (as attitude_sigma)


def attitude_sigma(size: tuple[int, int], focal: float, degrees: float) -> float:
    """The non-similarity (pixels, the length of the four corners' residuals) that a pitch or
    roll error of ``degrees`` gives one frame of ``size`` and focal length ``focal``: the unit
    of the attitude terms, so that a keyframe off by that much costs as much as one GPS sigma."""
    from mosaic_cli.geo.camera import untilt
    from mosaic_cli.geometry import frame_corners

    corners = frame_corners(*size)
    errors = [_nonsimilar(project(untilt(size, focal, -90.0 + pitch, roll), corners)[None], corners[None])
              for pitch, roll in ((degrees, 0.0), (0.0, degrees))]
    return float(np.mean([np.linalg.norm(e) for e in errors]))


def similarity_ratios(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(M,) complex ratios r of the least-squares similarities dst ~ r src + t, for (M, P, 2) point sets."""
    zs = src[..., 0] + 1j * src[..., 1]
    zd = dst[..., 0] + 1j * dst[..., 1]
    zs = zs - zs.mean(1, keepdims=True)
    zd = zd - zd.mean(1, keepdims=True)
    return (np.conj(zs) * zd).sum(1) / (np.abs(zs) ** 2).sum(1)


def _nonsimilar(dst: np.ndarray, src: np.ndarray) -> np.ndarray:
    """(M, 2P) what of dst (M, P, 2) no similarity from src explains, in src's units."""
    r = similarity_ratios(src, dst)
    zs = src[..., 0] + 1j * src[..., 1]
    zd = dst[..., 0] + 1j * dst[..., 1]
    left = (zd - zd.mean(1, keepdims=True)) - r[:, None] * (zs - zs.mean(1, keepdims=True))
    left = left / np.abs(r)[:, None]
    return np.concatenate([left.real, left.imag], axis=1)


@dataclass
class Levelling:
    matrix: np.ndarray  # 3x3, mosaic pixels -> levelled mosaic pixels
    residual: float  # median non-similarity of the keyframes after it, in attitude sigmas
    spread: float  # min / max of its projective denominator over the keyframes: 1 for an affine levelling

    def agrees(self, max_residual: float = 3.0, min_spread: float = 0.25) -> bool:
        """Whether the gimbal and the images tell one story: the keyframes levelled to within
        a few times the gimbal's accuracy, without a projective stretch no chain of
        registrations drifts by (a quarter of the scale at one end of the mosaic)."""
        return self.residual <= max_residual and self.spread >= min_spread


def level_mosaic(attitude: AttitudeViews, rounds: int = 10) -> Levelling:
    """The homography (mosaic pixels -> levelled mosaic pixels) that makes every keyframe of
    known attitude, undone of its tilt, a similarity in the mosaic again: the mosaic made the
    ground's up to a similarity by all keyframes' gimbals at once (robustly: Huber per
    keyframe), not by one keyframe's.  Only the tilt and shear are chosen (4 parameters); the
    similarity left is the GPS's to fix."""
    from scipy.optimize import least_squares
    corners = project(attitude.views, attitude.corners)  # (M, 4, 2)
    to_unit = normaliser(corners.reshape(-1, 2))
    unit = project(to_unit, corners.reshape(-1, 2))

    def matrix(p: np.ndarray) -> np.ndarray:
        shear = np.array([[math.exp(p[0]), p[1], 0.0], [0.0, math.exp(-p[0]), 0.0], [0.0, 0.0, 1.0]])
        return shear @ np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [p[2], p[3], 1.0]])

    def nonsimilar(p: np.ndarray) -> np.ndarray:
        return _nonsimilar(project(matrix(p), unit).reshape(corners.shape), attitude.corners) / attitude.sigma

    def residuals(p: np.ndarray, weights: np.ndarray) -> np.ndarray:
        return (nonsimilar(p) * np.sqrt(weights)[:, None]).ravel()

    p = np.zeros(4)
    for _ in range(rounds):
        weights = huber_weights(np.linalg.norm(nonsimilar(p), axis=1))
        new = least_squares(residuals, p, args=(weights,), method="trf", xtol=1e-12, ftol=1e-12).x
        done = np.allclose(new, p, rtol=0, atol=1e-9)
        p = new
        if done:
            break
    denominator = unit @ np.array([p[2], p[3]]) + 1.0
    spread = float(denominator.min() / denominator.max()) if denominator.max() > 0 else -1.0
    return Levelling(normalize(np.linalg.inv(to_unit) @ matrix(p) @ to_unit),
                     float(np.median(np.linalg.norm(nonsimilar(p), axis=1))), spread)


def adjust_to_ground(
    nadirs: np.ndarray,  # (F, 2) mosaic pixels of the keyframes with a fix: the points below the camera
    fixes: np.ndarray,  # (F, 2) their GPS positions, ground metres
    times: np.ndarray,  # (F,) seconds
    start: np.ndarray,  # 3x3 mosaic -> ground to start from (a robust similarity fit)
    attitude: AttitudeViews,
    prior: SimilarityPrior | None = None,
    prior_view: int | None = None,  # the attitude view the prior's scale and heading are of
    view_scales: np.ndarray | None = None,  # (M,) metres per untilted pixel of each view by its height (NaN: none)
    correlation: float = 2.0,  # seconds over which GPS errors are taken as one
    min_sigma: float = 1.0,
    rounds: int = 10,
) -> GroundFit:
    """The homography mosaic -> ground that the fixes, the attitudes and the prior agree on best (module doc)."""
    from scipy.optimize import least_squares
    nadirs = np.asarray(nadirs, np.float64)
    fixes = np.asarray(fixes, np.float64)
    times = np.asarray(times, np.float64)
    if len(attitude) == 0:
        raise ValueError("the adjustment needs at least one keyframe of known attitude")
    # Normalised coordinates on both sides: the parameters are of order one.
    to_unit = normaliser(nadirs)
    from_unit = np.linalg.inv(normaliser(fixes)) if len(fixes) else np.eye(3)
    unit_start = normalize(np.linalg.inv(from_unit) @ start @ np.linalg.inv(to_unit))
    mosaic_corners = project(attitude.views, attitude.corners)  # (M, 4, 2)
    unit_corners = project(to_unit, mosaic_corners.reshape(-1, 2)).reshape(mosaic_corners.shape)
    unit_nadirs = project(to_unit, nadirs)
    # the prior: the scale by every view of known height (else by the prior view's), the heading by the prior view's
    scaled = np.zeros(len(attitude), bool)
    expected = np.full(len(attitude), np.nan)
    scale_sigma = heading = heading_sigma = None
    if prior is not None and prior.sigma is not None:
        if view_scales is not None:
            expected = np.asarray(view_scales, np.float64)
        elif prior_view is not None:
            expected[prior_view] = prior.scale
        scaled = np.isfinite(expected) & (expected > 0)
        scale_sigma = max(prior.sigma, 1e-12)
    if prior is not None and prior.rotation is not None and prior.heading_sigma is not None and prior_view is not None:
        heading, heading_sigma = prior.rotation, max(prior.heading_sigma, 1e-12)

    def matrix(p: np.ndarray) -> np.ndarray:
        return from_unit @ np.append(p, 1.0).reshape(3, 3)

    def attitude_residuals(G: np.ndarray) -> np.ndarray:
        on_ground = project(G, unit_corners.reshape(-1, 2)).reshape(unit_corners.shape)
        return _nonsimilar(on_ground, attitude.corners) / attitude.sigma  # (M, 8)

    def prior_residual(G: np.ndarray) -> np.ndarray:
        parts = []
        if scale_sigma is not None and scaled.any():
            on_ground = project(G, unit_corners[scaled].reshape(-1, 2)).reshape(-1, 4, 2)
            r = similarity_ratios(attitude.corners[scaled], on_ground)
            parts.append(float(np.mean(np.log(np.abs(r) / expected[scaled]))) / scale_sigma)
        if heading is not None and heading_sigma is not None and prior_view is not None:
            r = similarity_ratios(attitude.corners[prior_view][None], project(G, unit_corners[prior_view])[None])[0]
            parts.append(math.remainder(float(np.angle(r)) - heading, 2 * math.pi) / heading_sigma)
        return np.array(parts)

    def residuals(p: np.ndarray, gps_w: np.ndarray, att_w: np.ndarray, gps_sigma: float) -> np.ndarray:
        G = matrix(p)
        parts = [((project(G, unit_nadirs) - fixes) * np.sqrt(gps_w)[:, None] / gps_sigma).ravel(),
                 (attitude_residuals(G) * np.sqrt(att_w)[:, None]).ravel()]
        if (scale_sigma is not None and scaled.any()) or heading is not None:
            parts.append(prior_residual(G))
        return np.concatenate(parts)

    p = unit_start.ravel()[:8]
    for _ in range(rounds):
        G = matrix(p)
        r = np.linalg.norm(project(G, unit_nadirs) - fixes, axis=1)
        sigma = robust_scatter(r, min_sigma)
        gps_w = robust_weights(r, sigma)
        gps_w *= fix_weights(times, gps_w > 0, correlation)
        att_w = huber_weights(np.linalg.norm(attitude_residuals(G), axis=1))  # per keyframe, in attitude sigmas
        # sigma is the scatter of distances; the per-axis sigma of 2-D Gaussian errors is smaller
        new = least_squares(residuals, p, args=(gps_w, att_w, axis_sigma(sigma)), method="lm", xtol=1e-12, ftol=1e-12).x
        done = np.allclose(new, p, rtol=0, atol=1e-9)
        p = new
        if done:
            break
    G = matrix(p)
    r = np.linalg.norm(project(G, unit_nadirs) - fixes, axis=1)
    sigma = robust_scatter(r, min_sigma)
    view = prior_view if prior_view is not None else 0
    ratio = similarity_ratios(attitude.corners[view][None], project(G, unit_corners[view])[None])[0]
    att = np.linalg.norm(attitude_residuals(G), axis=1) * attitude.sigma
    return GroundFit(normalize(G @ to_unit), r, r <= OUTLIER * sigma, sigma, float(abs(ratio)), float(np.angle(ratio)),
                     float(np.median(att)))
