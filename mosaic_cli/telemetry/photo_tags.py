"""What one photo says of itself (:class:`PhotoTags`), as :mod:`.photos` reads it from its EXIF and
XMP: the sample of a photo folder's ``FlightLog`` (``FlightLog.photos``) and its line in
``stitch --dry-run``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from mosaic_cli.video.info import TURN_DEGREES, shown_size

FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)  # what a 35 mm-equivalent focal length is relative to


@dataclass
class PhotoTags:
    """What one photo says of itself; NaN (or None) where it says nothing."""

    path: Path
    width: int = 0
    height_px: int = 0
    lat: float = math.nan
    lon: float = math.nan
    alt: float = math.nan  # GPS altitude, metres above sea level
    height: float = math.nan  # DJI RelativeAltitude: metres above the take-off point
    yaw: float = math.nan  # degrees: the gimbal's, else the aircraft's (DJI FlightYawDegree)
    pitch: float = math.nan
    roll: float = math.nan
    time: str | None = None  # EXIF DateTimeOriginal (with sub-seconds when given)
    make: str | None = None
    model: str | None = None
    focal_mm: float = math.nan
    focal_35mm: float = math.nan
    sensor_width_mm: float = math.nan  # from the focal plane resolution, when given
    problems: list[str] = field(default_factory=list)  # damaged or partial metadata, said once per photo
    orientation: int = 1  # EXIF Orientation: how the stored pixels are turned to be shown (1: as stored)

    @property
    def has_fix(self) -> bool:
        return math.isfinite(self.lat) and math.isfinite(self.lon)

    @property
    def camera(self) -> str | None:
        name = " ".join(s for s in (self.make, self.model) if s)
        return name or None

    @property
    def shown_size(self) -> tuple[int, int]:
        """(w, h) of the photo as shown, its EXIF orientation applied (as OpenCV reads it)."""
        return shown_size((self.width, self.height_px), self.orientation)

    @property
    def shown_yaw(self) -> float:
        """The heading of the shown photo's top edge, degrees: the camera's ``yaw`` turned as the
        photo is to be shown; NaN for a mirrored one (no turn of the ground gives its footprint)."""
        # Turned clockwise to be shown, its top edge is what was its left: the heading less the turn.
        return self.yaw - TURN_DEGREES[self.orientation] if self.orientation in TURN_DEGREES else math.nan

    @property
    def hfov(self) -> float:
        """The field of view across the photo as shown, degrees, from the 35 mm-equivalent focal
        length (defined on the diagonal) or from the focal length and the sensor's width; NaN when
        neither is given."""
        if self.width <= 0 or self.height_px <= 0:
            return math.nan
        shown_width = self.shown_size[0]
        if self.focal_35mm > 0:
            across = FULL_FRAME_DIAGONAL_MM * shown_width / math.hypot(self.width, self.height_px)
            return math.degrees(2.0 * math.atan(across / (2.0 * self.focal_35mm)))
        if self.focal_mm > 0 and self.sensor_width_mm > 0:
            across = self.sensor_width_mm * shown_width / self.width  # (square pixels)
            return math.degrees(2.0 * math.atan(across / (2.0 * self.focal_mm)))
        return math.nan

    def describe(self) -> str:
        """One line for ``stitch --dry-run``."""
        turned = f" (EXIF orientation {self.orientation})" if self.orientation != 1 else ""
        parts = [self.path.name, f"{self.shown_size[0]}x{self.shown_size[1]}{turned}"]
        parts.append(f"{self.lat:.7f}, {self.lon:.7f}" if self.has_fix else "no GPS")
        if math.isfinite(self.alt):
            parts.append(f"alt {self.alt:.1f} m")
        if math.isfinite(self.height):
            parts.append(f"height {self.height:.1f} m")
        attitude = [f"{name} {v:.1f}" for name, v in (("yaw", self.yaw), ("pitch", self.pitch), ("roll", self.roll)) if math.isfinite(v)]
        if attitude:
            parts.append(" ".join(attitude))
        if math.isfinite(self.hfov):
            parts.append(f"hfov {self.hfov:.1f} deg")
        if self.camera:
            parts.append(self.camera)
        if self.time:
            parts.append(self.time)
        parts += [f"({p})" for p in self.problems]
        return "  ".join(parts)
