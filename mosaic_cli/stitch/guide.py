"""Where the GPS says each photo of a folder looks: which photos to pair, and the homography to
guide their matching by.

A geotagged photo's footprint on the ground follows from its position, its height above the
take-off point and the camera's field of view (its scale), and its yaw (its heading).  Two
photos whose footprints, widened by the GPS's error, overlap are worth matching; the others are
not, so the pairs grow with the number of photos, not with its square, and the neighbours across
survey lines are found at once.  Where scale and yaw are both known, the footprints also predict
the homography between the two photos, which the matching is guided by
(:meth:`~mosaic_cli.stitch.features.FeatureMatcher.match_guided`).

Without a height the scale is learned from the pairs registered so far (their GPS distance over
their distance in pixels); without a yaw only the pairing is guided.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mosaic_cli.geo.crs import Projection
from mosaic_cli.telemetry.flight_log import FlightLog


@dataclass
class GuideOptions:
    gps_error: float = 5.0  # metres: the margin the footprints are widened by (consumer GPS, each photo)
    yaw_error: float = 3.0  # degrees: the compass's (and gimbal's) error the guided search allows
    scale_error: float = 0.05  # the heights' and the nominal field of view's relative error, ditto
    # A pair is a candidate when its footprints (circles of half their diagonal) overlap by at
    # least this fraction of one's radius, once widened by the GPS's error.
    min_overlap: float = 0.05
    max_candidates: int = 6  # the nearest candidates a photo is matched against, at most
    max_tilt: float = 15.0  # degrees from nadir (the gimbal's pitch) beyond which matching is not guided

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """No flag sets these: a bad value is a bug (ValueError), not the user's input."""
        if self.gps_error <= 0 or self.yaw_error < 0 or self.max_candidates < 1 or not 0 <= self.max_tilt <= 90:
            raise ValueError(f"guide options out of range: {self}")


class GroundGuide:
    """The photos' predicted footprints, indexed by frame index (photo ``i`` of the folder is
    frame ``first_index + i``... as the scan numbers them: ``index`` below)."""

    def __init__(self, track: FlightLog, source_size: tuple[int, int], options: GuideOptions | None = None):
        self.options = options or GuideOptions()
        self.size = source_size
        self.n = len(track)
        fixed = track.has_fix
        self.positions = np.full((self.n, 2), np.nan)
        if fixed.any():
            lat0, lon0 = float(np.median(track.lat[fixed])), float(np.median(track.lon[fixed]))
            self.positions[fixed] = Projection.utm_for(lat0, lon0).to_map(track.lat[fixed], track.lon[fixed])
        w = source_size[0]
        hfov = np.where(np.isfinite(track.hfov), track.hfov, np.nan)
        # metres per pixel at the image centre, nadir: 2 h tan(hfov / 2) / width
        self.scales = 2.0 * track.height * np.tan(np.radians(hfov) / 2.0) / w
        self.scales[~(self.scales > 0)] = np.nan
        self.yaw = np.radians(track.yaw)
        # A gimbal tilted from nadir sees a trapezoid ahead of the drone, not the footprint below
        # it: such a photo is paired by distance but its matching is not guided.
        self.oblique = np.abs(track.pitch + 90.0) > self.options.max_tilt
        self._learned: list[float] = []  # metres per pixel from registered pairs (no height)
        self._half_diagonal = 0.5 * math.hypot(*source_size)

    # -- what is known of a photo --------------------------------------------------------
    def has_fix(self, index: int) -> bool:
        return 0 <= index < self.n and bool(np.isfinite(self.positions[index]).all())

    def scale(self, index: int) -> float:
        """Metres per pixel of photo ``index``: its height's, else the registrations' so far (NaN)."""
        s = self.scales[index] if 0 <= index < self.n else math.nan
        return float(s) if math.isfinite(s) else self._learned_scale()

    def _learned_scale(self) -> float:
        """Metres per pixel the registered pairs say (their median), NaN before any."""
        return float(np.median(self._learned)) if self._learned else math.nan

    def learn(self, a: int, b: int, H: np.ndarray) -> None:
        """A registered pair (``H``: photo a -> photo b pixels): what it says of the scale."""
        if not (self.has_fix(a) and self.has_fix(b)):
            return
        metres = float(np.linalg.norm(self.positions[a] - self.positions[b]))
        centre = np.array([(self.size[0] - 1) / 2.0, (self.size[1] - 1) / 2.0, 1.0])
        moved = H @ centre
        pixels = float(np.linalg.norm(moved[:2] / moved[2] - centre[:2]))
        # Pairs closer than the GPS error say nothing of the scale.
        if metres > 2.0 * self.options.gps_error and pixels > 1.0:
            self._learned.append(metres / pixels)

    # -- pairing -----------------------------------------------------------------------
    def candidates(self, index: int, others: list[int]) -> list[int] | None:
        """Of ``others`` (frame indices), those whose footprints the GPS says overlap photo
        ``index``'s, nearest first, at most ``max_candidates``; None when the GPS cannot tell
        (the photo has no fix, or no scale is known yet)."""
        if not self.has_fix(index):
            return None
        scale = self.scale(index)
        if not math.isfinite(scale):
            return None
        with_fix = [k for k in others if self.has_fix(k)]
        if not with_fix:
            return []
        distance = np.linalg.norm(self.positions[with_fix] - self.positions[index], axis=1)
        # each photo's own scale, else the registrations', else this photo's (one median, not one a photo)
        learned = self._learned_scale()
        radii = self._half_diagonal * np.where(np.isfinite(self.scales[with_fix]), self.scales[with_fix],
                                               learned if math.isfinite(learned) else scale)
        mine = self._half_diagonal * scale
        reach = mine + radii + 2.0 * self.options.gps_error - self.options.min_overlap * np.minimum(mine, radii)
        order = np.argsort(distance, kind="stable")
        return [with_fix[k] for k in order if distance[k] < reach[k]][: self.options.max_candidates]

    # -- the predicted homography ------------------------------------------------------------
    def to_ground(self, index: int) -> np.ndarray | None:
        """Photo ``index``'s pixels -> (east, north) metres, nadir, from its fix, scale and yaw;
        None when one is unknown."""
        scale = self.scale(index)
        if not (self.has_fix(index) and math.isfinite(scale) and 0 <= index < self.n and math.isfinite(self.yaw[index])):
            return None
        if self.oblique[index]:
            return None
        c, s = math.cos(self.yaw[index]), math.sin(self.yaw[index])
        # image x (right) -> (cos yaw, -sin yaw) east/north; image y (down) -> (-sin yaw, -cos yaw)
        A = scale * np.array([[c, -s], [-s, -c]])
        centre = np.array([(self.size[0] - 1) / 2.0, (self.size[1] - 1) / 2.0])
        G = np.eye(3)
        G[:2, :2] = A
        G[:2, 2] = self.positions[index] - A @ centre
        return G

    def predicted(self, a: int, b: int) -> tuple[np.ndarray, float] | None:
        """(H, radius): photo a -> photo b pixels as the GPS predicts them, and how far (b's
        pixels) a point may be from where H puts it, from the GPS and yaw errors; None when
        either photo lacks a fix, a scale or a yaw."""
        Ga, Gb = self.to_ground(a), self.to_ground(b)
        if Ga is None or Gb is None:
            return None
        H = np.linalg.inv(Gb) @ Ga
        scale = self.scale(b)
        o = self.options
        radius = 2.0 * o.gps_error / scale + (math.radians(o.yaw_error) + o.scale_error) * 2.0 * self._half_diagonal
        return H / H[2, 2], radius
