"""Georeferencing a stitched flight: the images fix the mosaic's shape, the telemetry its
position, scale and heading.

1. align     the track to the keyframes' times (interpolated; outliers, gaps reported)
2. untilt    the reference view by the gimbal's pitch and roll (with a field of view), so the
             mosaic's plane is the ground's up to a similarity; with the pitch of every
             keyframe, the mosaic levelled by all of them (adjust.level_mosaic)
3. fit       the keyframes' nadir points in the mosaic onto their GPS positions in the site's
             UTM zone: a robust similarity (see fit.py), with the height x field of view scale
             (prior.py) and the compass heading as a prior, each weighed by its stated error;
             a height x field of view scale far from the GPS's own is said and not used
4. check     the fit against the images: too few agreeing fixes, or GPS scatter no drone has,
             mean the telemetry belongs to another flight or clock
5. adjust    with the gimbal's pitch of the keyframes, one adjustment (adjust.py): the tilt and
             shear the chained registrations left in the mosaic from every keyframe's attitude,
             position, scale and heading from the GPS and the prior; without it a homography
             from the GPS alone where it explains the fixes clearly better
6. drift     per keyframe, for what bending is left: shifts toward the GPS and, over level
             ground (``level_ground``), scales toward the heights' (the chained registrations'
             scale drift), held stiff by the images (drift.py)

Everything here is pure geometry: no file is read or written.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.geo.adjust import AttitudeViews, adjust_to_ground, attitude_sigma, level_mosaic, similarity_ratios
from mosaic_cli.geo.camera import focal_pixels, nadir_pixel, untilt
from mosaic_cli.geo.crs import Projection
from mosaic_cli.geo.drift import DriftCorrection, DriftOptions, drift_correction
from mosaic_cli.geo.fit import SimilarityFit, SimilarityPrior, axis_sigma, fit_similarity, fix_weights, refine_homography, scale_sigma
from mosaic_cli.geo.prior import height_scale, sigmas_apart
from mosaic_cli.geometry import frame_corners, normalize, project
from mosaic_cli.telemetry.align import AlignedTelemetry, AlignOptions, align_to_frames
from mosaic_cli.telemetry.flight_log import FlightLog

FLIP = np.diag([1.0, -1.0, 1.0])  # (east, -north) <-> (east, north)
# The fixes' robust scatter (metres) is never taken as less than GPS_FLOOR: no GPS is better than
# about a metre, and a short, exact track must not call every fix but the best few an outlier.
# Where the fixes are too few to tell their own scatter, a consumer receiver's (GPS_TYPICAL:
# about 2 m per axis) is weighed in as GPS_TYPICAL_DOF degrees of freedom against theirs.
GPS_FLOOR = 1.0
GPS_TYPICAL = 3.5
GPS_TYPICAL_DOF = 4.0


@dataclass
class GeorefOptions:
    telemetry: Path | None = None  # a file; None: look inside the video
    hfov: float | None = None  # degrees; overrides the telemetry's
    offset: float = 0.0  # seconds added to the telemetry's times
    footprints: Path | None = None
    html: Path | None = None  # --html: the quick-look page (geo/quicklook.py)
    align: AlignOptions = field(default_factory=AlignOptions)
    min_coverage: float = 0.5  # at least this fraction of keyframes must have a fix
    max_scatter: float = 30.0  # metres: robust GPS scatter about the fit beyond this is no GPS error
    # ... and beyond this the map is made but said to be placed no better: the images' one plane
    # and the GPS disagree by more than a receiver errs (relief, trees, an oblique camera)
    loose_scatter: float = 3 * GPS_TYPICAL
    min_agreeing: float = 0.6  # fraction of fixes that must agree with the images
    # A long flight's mosaic bends a little (perspective drift): a homography replaces the
    # similarity when it explains the fixes this much better (robust scatter ratio) ...
    perspective_gain: float = 0.8
    min_fixes_for_perspective: int = 12
    # With the gimbal's pitch and roll the tilt comes from them instead (adjust.py): how far
    # the gimbal's reported attitude may be off, degrees (None: not used, the tilt from the GPS)
    attitude_accuracy: float | None = 1.0
    # What the height x field of view scale and the compass heading are worth against the GPS
    # (prior.py): the height's offset over a flight, metres (a barometer zeroed at take-off);
    # the field of view's relative error (a log's focal length is nominal); the compass, degrees
    height_accuracy: float = 0.5
    fov_accuracy: float = 0.01
    compass_accuracy: float = 3.0
    # a height x field of view scale this many combined sigmas from the GPS's own (as unlikely, in
    # Student's t, on a short track's few fixes: disagreement_limit) is not used (said)
    max_scale_disagreement: float = 3.5
    drift: DriftOptions = field(default_factory=DriftOptions)  # ... and GPS shifts what is left (drift.py)
    # Each keyframe bent toward its own fix (drift.py, and the GPS-straightened start of drift
    # control): a video's chained registrations drift.  A photo folder's photos are registered
    # to all their neighbours directly, and each photo's fix carries its own noise: bending them
    # toward it would move the photos apart by the GPS's error (measured: 7 px at 10 cm a pixel).
    bend_to_gps: bool = True
    # The ground under the whole flight is level with the take-off point (to about the height's
    # noise): each keyframe's height then also says its own scale, which corrects the scale the
    # chained registrations drift in (drift.py).  Off by default: over relief the heights above
    # take-off are not heights above the ground, and would scale keyframes wrongly.
    level_ground: bool = False

    def __post_init__(self) -> None:
        self.validate()

    def without_telemetry(self) -> list[str]:
        """The flags given that mean nothing without a GPS track (said when there is none)."""
        return [flag for flag, given in (("--footprints", self.footprints is not None), ("--html", self.html is not None),
                                         ("--level-ground", self.level_ground)) if given]

    def validate(self) -> None:
        if self.attitude_accuracy is not None and not 0 < self.attitude_accuracy <= 90:
            raise BadInput(f"the gimbal's attitude accuracy must be between 0 and 90 degrees, got {self.attitude_accuracy}")
        if not (0 <= self.height_accuracy <= 1000 and 0 <= self.fov_accuracy <= 1 and 0 < self.compass_accuracy <= 180
                and self.max_scale_disagreement > 0):
            raise BadInput(f"the telemetry's accuracies must be a height of 0-1000 m, a field of view of 0-100%, a compass of "
                           f"0-180 degrees and a disagreement above 0 sigmas, got {self.height_accuracy}, {self.fov_accuracy}, "
                           f"{self.compass_accuracy}, {self.max_scale_disagreement}")
        if self.hfov is not None and not 1.0 <= self.hfov <= 170.0:
            raise BadInput(f"--hfov must be between 1 and 170 degrees, got {self.hfov}")
        if not math.isfinite(self.offset):
            raise BadInput("--telemetry-offset must be a number of seconds")
        if self.footprints is not None and Path(self.footprints).suffix.lower() not in (".geojson", ".json"):
            raise BadInput(f"--footprints {self.footprints} must end in .geojson or .json")
        if self.html is not None and Path(self.html).suffix.lower() not in (".html", ".htm"):
            raise BadInput(f"--html {self.html} must end in .html or .htm")


@dataclass
class Georeference:
    projection: Projection
    mosaic_to_ground: np.ndarray  # reference-frame pixels -> (east, north) metres
    ground_to_pixels: np.ndarray  # (east, north) -> north-up output pixels of ``gsd`` metres
    gsd: float
    fit: SimilarityFit
    telemetry: AlignedTelemetry
    frame_indices: list[int]
    used: np.ndarray  # keyframes whose fix entered the fit
    shifts: np.ndarray  # (N, 2) per-keyframe ground shifts from the GPS drift prior
    scales: np.ndarray  # (N,) per-keyframe scales about ``nadirs`` from the heights (drift.py; 1: none)
    nadirs: np.ndarray  # (N, 2) each keyframe's nadir point on the ground before its correction
    model: str  # "similarity", "homography" (from the GPS) or "homography levelled by the gimbal"
    hfov: float | None
    track: FlightLog
    prior: SimilarityPrior | None
    notes: list[str] = field(default_factory=list)  # what the summary should say besides
    warnings: list[str] = field(default_factory=list)  # said even with -q (mosaic: warning: ...)

    @property
    def crs(self) -> str:
        return self.projection.name

    def correction(self, k: int) -> np.ndarray:
        """Keyframe k's drift correction on the ground: scaled about its nadir point, then shifted."""
        s = float(self.scales[k])
        (x, y), (dx, dy) = self.nadirs[k], self.shifts[k]
        return np.array([[s, 0, x - s * x + dx], [0, s, y - s * y + dy], [0, 0, 1.0]])

    def frame_to_ground(self, k: int, placement: np.ndarray) -> np.ndarray:
        """Keyframe k's frame pixels -> (east, north), from its placement in the reference frame."""
        return normalize(self.correction(k) @ self.mosaic_to_ground @ placement)

    def placements_in_pixels(self, placements: list[np.ndarray]) -> list[np.ndarray]:
        return [normalize(self.ground_to_pixels @ self.frame_to_ground(k, H)) for k, H in enumerate(placements)]

    def straightened(self, placements: list[np.ndarray]) -> list[np.ndarray]:
        """The placements (in the reference frame) moved by the GPS drift shifts."""
        back = np.linalg.inv(self.mosaic_to_ground)
        return [normalize(back @ self.frame_to_ground(k, H)) for k, H in enumerate(placements)]

    def summary(self) -> str:
        agreeing = int(self.fit.inliers.sum())
        heading = (math.degrees(self.fit.rotation) + 180.0) % 360.0 - 180.0
        return (
            f"georeferenced in {self.crs}: {agreeing} of {len(self.fit.inliers)} keyframe fixes agree "
            f"(scatter {self.fit.sigma:.1f} m, {self.model}), {self.gsd * 100:.1f} cm per pixel, mosaic heading {heading:+.1f} deg"
            + "".join(f"; {note}" for note in self.notes)
        )


class TooFewFixes(BadInput):
    """The log places too few of the keyframes to lay them on the ground (``fixes`` of ``keyframes``)."""

    def __init__(self, fixes: int, keyframes: int, message: str):
        super().__init__(message)
        self.fixes, self.keyframes = fixes, keyframes


def georeference(
    placements: list[np.ndarray],
    ref: int,
    frame_indices: list[int],
    frame_size: tuple[int, int],
    fps: float,
    track: FlightLog,
    options: GeorefOptions,
) -> Georeference:
    """Tie keyframe ``placements`` (frame pixels -> pixels of keyframe ``ref``) to ``track``."""
    times = np.asarray(frame_indices, dtype=np.float64) / fps
    aligned = align_to_frames(track.shifted(options.offset), times, options.align)
    fixes = aligned.fix
    if not track.has_fix.any():
        raise BadInput(f"{track.source}: no GPS fix in {len(track)} samples (all without coordinates)")
    if fixes.sum() < max(2, options.min_coverage * len(times)):
        raise TooFewFixes(int(fixes.sum()), len(times),
            f"{track.source}: the telemetry does not cover the video: fixes span {aligned.span[0]:.1f}-{aligned.span[1]:.1f} s, "
            f"the stitched frames {times[0]:.1f}-{times[-1]:.1f} s ({int(fixes.sum())} of {len(times)} keyframes have a position); "
            f"check --telemetry-offset"
        )
    hfov = options.hfov
    if hfov is None and np.isfinite(aligned.hfov).any():
        hfov = float(np.nanmedian(aligned.hfov))

    # 2. the mosaic's plane made the ground's, and each keyframe's point below the camera
    w, h = frame_size
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    if hfov is not None:
        f = focal_pixels(w, hfov)
        flatten = untilt(frame_size, f, aligned.pitch[ref], aligned.roll[ref])
        nadirs = [nadir_pixel(frame_size, f, aligned.pitch[k], aligned.roll[k]) for k in range(len(placements))]
    else:
        f, flatten = None, np.eye(3)
        nadirs = [centre] * len(placements)
    attitude = _attitude_views(placements, flatten, frame_size, f, aligned, options.attitude_accuracy)
    notes: list[str] = []
    if attitude is not None:
        # levelled by every keyframe's gimbal, not by the reference's alone (adjust.py) ...
        level = level_mosaic(attitude[0])
        if level.agrees():
            flatten = level.matrix @ flatten
            attitude[0].views = np.stack([normalize(level.matrix @ V) for V in attitude[0].views])
        else:  # ... unless its angles and the images disagree: then none is used, the tilt is the GPS's
            attitude, flatten, nadirs = None, np.eye(3), [centre] * len(placements)
            notes.append(f"the gimbal's angles disagree with the images ({level.residual:.1f} x its accuracy): not used")
    mosaic = project(flatten @ np.stack(placements), np.stack(nadirs)[:, None])[:, 0]
    heights = None
    if f is not None:
        heights = height_scale(aligned.height, f, _untilted_scales(placements, flatten, frame_size, attitude),
                               options.height_accuracy, options.fov_accuracy)

    # 3. the fit, in the site's UTM zone, as (east, -north) so that image y (down) stays y
    lat0 = float(np.nanmedian(aligned.lat[fixes]))
    lon0 = float(np.nanmedian(aligned.lon[fixes]))
    projection = Projection.utm_for(lat0, lon0)
    ground = projection.to_map(aligned.lat[fixes], aligned.lon[fixes]) * np.array([1.0, -1.0])
    prior = None
    if heights is not None:
        # the keyframes' heights over the focal length: metres per pixel (prior.py); the reference's top edge points at yaw
        yaw = math.radians(float(aligned.yaw[ref])) if np.isfinite(aligned.yaw[ref]) else None
        prior = SimilarityPrior(heights.mosaic_scale, yaw, heights.sigma, math.radians(options.compass_accuracy))
    extent = float(np.linalg.norm(np.ptp(ground, axis=0)))
    if (prior is None or prior.rotation is None) and extent < 30.0:
        raise BadInput(
            f"{track.source}: the GPS track spans only {extent:.0f} m, too little to fix scale and heading against GPS "
            f"noise; the telemetry needs a height, a heading and a field of view (--hfov) to place such a short flight"
        )
    dof = gps_dof(times[fixes], options.drift.correlation)
    floor = gps_floor(dof)
    fit = fit_similarity(mosaic[fixes], ground, prior, min_sigma=floor, times=times[fixes], correlation=options.drift.correlation)

    # 4. does the telemetry belong to these images?
    agreeing = float(fit.inliers.mean())
    if fit.sigma > options.max_scatter or agreeing < options.min_agreeing:
        raise BadInput(
            f"{track.source}: the telemetry disagrees with the images: only {agreeing:.0%} of the fixes agree with the "
            f"mosaic's shape (scatter {fit.sigma:.0f} m); wrong log, wrong clock (--telemetry-offset), or a lost track; "
            f"stitch without --telemetry for a plain panorama"
        )
    if prior is not None and not 0.5 < fit.scale / prior.scale < 2.0:
        raise BadInput(
            f"{track.source}: the telemetry disagrees with the images: the GPS track implies {fit.scale * 100:.1f} cm per pixel, "
            f"the height and field of view {prior.scale * 100:.1f} cm; check --hfov and the log"
        )
    warnings: list[str] = []
    if prior is not None:
        fit, prior = _check_height_scale(fit, prior, mosaic[fixes], ground, times[fixes], dof, options, hfov, warnings)
    to_ground = fit.matrix
    model = "similarity"
    inliers, sigma = fit.inliers, fit.sigma
    if attitude is not None:
        # the tilt the images leave open from every keyframe's gimbal, the rest from the GPS (adjust.py)
        views, known = attitude
        prior_view = int(np.searchsorted(known, ref)) if ref in known else None
        view_scales = heights.per_keyframe[known] if heights is not None and prior is not None and prior.sigma is not None else None
        adjusted = adjust_to_ground(mosaic[fixes], ground, times[fixes], fit.matrix, views, prior, prior_view, view_scales,
                                    min_sigma=floor, correlation=options.drift.correlation)
        to_ground, model = adjusted.matrix, "homography levelled by the gimbal"
        inliers, sigma = adjusted.inliers, adjusted.sigma
        a, b = adjusted.scale * math.cos(adjusted.rotation), adjusted.scale * math.sin(adjusted.rotation)
        scale_and_heading = np.array([[a, -b, fit.matrix[0, 2]], [b, a, fit.matrix[1, 2]], [0, 0, 1.0]])
        fit = SimilarityFit(scale_and_heading, adjusted.residuals, inliers, sigma)
    elif fixes.sum() >= options.min_fixes_for_perspective:
        # the perspective a long flight's chained registrations bend the mosaic with
        placed = project(fit.matrix, mosaic[fixes])
        better = refine_homography(placed, ground, min_sigma=floor)
        if better.sigma < options.perspective_gain * fit.sigma and better.inliers.mean() >= options.min_agreeing:
            to_ground, model = better.matrix @ fit.matrix, "homography"
            inliers, sigma = better.inliers, better.sigma
    mosaic_to_ground = FLIP @ to_ground @ flatten
    used = np.zeros(len(placements), bool)
    used[np.nonzero(fixes)[0][inliers]] = True

    # what bending is left: GPS shifts per keyframe, and the heights' scales, stiffly linked by the images (drift.py)
    nadir_ground = project(mosaic_to_ground @ np.stack(placements), np.stack(nadirs)[:, None])[:, 0]
    height_scales = None
    if heights is not None and f is not None and options.level_ground:
        seen = _untilted_scales(placements, flatten, frame_size, attitude, then=FLIP @ to_ground)
        height_scales = np.log(heights.per_keyframe / seen)
    all_fixes = np.full((len(placements), 2), np.nan)
    all_fixes[fixes] = ground * np.array([1.0, -1.0])
    footprint_m = float(np.median([np.sqrt(abs(np.linalg.det(_jacobian(mosaic_to_ground @ H, centre)))) for H in placements])) * max(w, h)
    # sigma is the robust scatter of the fixes' distances: the drift correction wants the per-axis sigma
    if options.bend_to_gps:
        drift = drift_correction(nadir_ground, all_fixes, used.astype(float), times, footprint_m, max(axis_sigma(sigma), 0.5),
                                 options.drift, height_scales)
    else:
        drift = DriftCorrection(np.zeros((len(placements), 2)), np.ones(len(placements)))

    if track.photos is not None:
        _name_rejected_fixes(track, frame_indices, fixes, used, nadir_ground, all_fixes, warnings)

    # Output pixels: north-up at the keyframes' median ground sample, anchored at the reference's centre.
    gsd = footprint_m / max(w, h)
    anchor = project(mosaic_to_ground, centre[None])[0]
    ground_to_pixels = np.array([[1 / gsd, 0, -anchor[0] / gsd], [0, -1 / gsd, anchor[1] / gsd], [0, 0, 1.0]])
    if sigma > options.loose_scatter:
        warnings.append(
            f"the GPS fixes scatter {sigma:.0f} m about where the images place them, more than a receiver errs (about "
            f"{GPS_TYPICAL:.1f} m): ground far from one plane (relief, tall trees) or an oblique camera, which one flat map "
            f"cannot hold; the map is placed to about {sigma:.0f} m (a surface model, as OpenDroneMap builds, places such ground)"
        )
    fit.sigma = sigma
    fit.inliers = inliers
    return Georeference(projection, mosaic_to_ground, ground_to_pixels, gsd, fit, aligned, list(frame_indices), used, drift.shifts,
                        drift.scales, nadir_ground, model, hfov, track, prior, notes, warnings)


def gps_dof(times: np.ndarray, correlation: float) -> float:
    """The degrees of freedom GPS fixes at ``times`` (seconds) give their own scatter: 2 x what
    they are worth as independent fixes (fit.fix_weights: errors correlated over
    ``correlation`` seconds), less a similarity's four parameters."""
    worth = float(fix_weights(np.asarray(times, np.float64), np.ones(len(times), bool), correlation).sum())
    return max(2.0 * worth - 4.0, 0.0)


def gps_floor(dof: float) -> float:
    """The least robust scatter (metres) to take GPS fixes of ``dof`` degrees of freedom
    (``gps_dof``) as having: GPS_FLOOR, or where the fixes tell little of their own, the typical
    receiver's weighed in against them: a 10 s track's handful of fixes leave about 3 m, a
    minute's 1.3 m; from about two minutes on, GPS_FLOOR."""
    return max(GPS_FLOOR, GPS_TYPICAL * math.sqrt(GPS_TYPICAL_DOF / (dof + GPS_TYPICAL_DOF)))


def disagreement_limit(sigmas: float, dof: float) -> float:
    """How far apart, in estimated sigmas, two scales may lie when the GPS's sigma is itself
    estimated on ``dof`` degrees of freedom (with the typical receiver's): as unlikely as
    ``sigmas`` normal sigmas, in Student's t.  About ``sigmas`` for a long track, more for a
    short one (8 degrees of freedom: 3.5 -> 5.7)."""
    from scipy.stats import norm, t

    return float(t.isf(norm.sf(sigmas), dof + GPS_TYPICAL_DOF))


def _check_height_scale(fit: SimilarityFit, prior: SimilarityPrior, mosaic: np.ndarray, ground: np.ndarray,
                        times: np.ndarray, dof: float, options: GeorefOptions, hfov: float | None,
                        warnings: list[str]) -> tuple[SimilarityFit, SimilarityPrior]:
    """The fit and the prior to go on with: as they are when the prior has no scale, or when
    the height x field of view scale agrees with the GPS track's own within
    ``options.max_scale_disagreement`` combined sigmas (as unlikely, in Student's t, where the
    GPS's sigma comes from few fixes: ``disagreement_limit``); else (a wrong --hfov, a nominal focal
    length of another video mode, ground far below the take-off point) the GPS's scale, and a
    warning.  The GPS positions are what was measured on this flight: where the track is long
    enough to tell them apart, they are trusted.  ``dof``: the fixes' degrees of freedom (``gps_dof``)."""
    from dataclasses import replace

    if prior.sigma is None:
        return fit, prior
    gps = fit_similarity(mosaic, ground, replace(prior, sigma=None), min_sigma=gps_floor(dof), times=times,
                         correlation=options.drift.correlation)
    inliers = gps.inliers
    weights = fix_weights(times, inliers, options.drift.correlation)
    gps_sigma = scale_sigma(ground[inliers], weights[inliers], axis_sigma(gps.sigma))
    apart = sigmas_apart(gps.scale, gps_sigma, prior.scale, prior.sigma)
    if apart <= disagreement_limit(options.max_scale_disagreement, dof):
        return fit, prior
    warnings.append(
        f"the height and field of view ({hfov or math.nan:.1f} deg) make the map {100 * (prior.scale / gps.scale - 1):+.1f}% the size the "
        f"GPS track does ({apart:.1f} sigmas apart): the GPS's scale is used; check --hfov and the log's height"
    )
    return gps, replace(prior, sigma=None)


def _untilted_scales(placements: list[np.ndarray], flatten: np.ndarray, frame_size: tuple[int, int],
                     attitude: tuple[AttitudeViews, np.ndarray] | None, then: np.ndarray | None = None) -> np.ndarray:
    """(N,) mosaic pixels per pixel of each keyframe's view undone of its gimbal tilt (the
    ``attitude`` views, for the keyframes they hold; else its frame as it is), in the flattened
    mosaic, or in what ``then`` maps the flattened mosaic to (the ground: metres per pixel)."""
    then = np.eye(3) if then is None else then
    corners = np.broadcast_to(frame_corners(*frame_size), (len(placements), 4, 2))
    out = np.abs(similarity_ratios(corners, project(normalize(then @ flatten @ np.stack(placements)), corners)))
    if attitude is not None:
        views, known = attitude
        out[known] = np.abs(similarity_ratios(views.corners, project(normalize(then @ views.views), views.corners)))
    return out


def _attitude_views(placements: list[np.ndarray], flatten: np.ndarray, frame_size: tuple[int, int], focal: float | None,
                    aligned: AlignedTelemetry, accuracy: float | None) -> tuple[AttitudeViews, np.ndarray] | None:
    """The keyframes of known pitch (and a field of view) as seen undone of their tilt, in the
    flattened mosaic, with their positions among all keyframes; None when none is known (or
    the gimbal is not to be used)."""
    if focal is None or accuracy is None:
        return None
    known = np.nonzero(np.isfinite(aligned.pitch))[0]
    if len(known) == 0:
        return None
    corners = frame_corners(*frame_size)
    unt = [untilt(frame_size, focal, aligned.pitch[k], aligned.roll[k]) for k in known]
    views = np.stack([normalize(flatten @ placements[k] @ np.linalg.inv(U)) for k, U in zip(known, unt)])
    return AttitudeViews(views, project(np.stack(unt), corners), attitude_sigma(frame_size, focal, accuracy)), known


def _jacobian(H: np.ndarray, point: np.ndarray) -> np.ndarray:
    """2x2 derivative of the homography ``H`` at ``point``."""
    x, y = point
    den = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    u = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / den
    v = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / den
    return np.array([[H[0, 0] - u * H[2, 0], H[0, 1] - u * H[2, 1]], [H[1, 0] - v * H[2, 0], H[1, 1] - v * H[2, 1]]]) / den


def _name_rejected_fixes(track: FlightLog, frame_indices, fixes: np.ndarray, used: np.ndarray, nadir_ground: np.ndarray,
                         all_fixes: np.ndarray, warnings: list[str]) -> None:
    """A photo folder's fixes the fit set aside, by photo, in one warning: each photo is placed
    by its pixels, and a wrong fix is worth knowing of (a GPS glitch, a photo from another flight)."""
    assert track.photos is not None
    rejected = [(track.photos[frame_indices[k]].path.name, float(np.linalg.norm(nadir_ground[k] - all_fixes[k])))
                for k in np.nonzero(fixes & ~used)[0] if 0 <= frame_indices[k] < len(track.photos)]
    if rejected:
        named = ", ".join(f"{name} ({metres:.0f} m)" for name, metres in rejected)
        warnings.append(f"{len(rejected)} photo GPS fix{'es' if len(rejected) > 1 else ''} far from where the photos' pixels "
                        f"place {'them' if len(rejected) > 1 else 'it'}, not used: {named}")
