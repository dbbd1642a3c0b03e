"""The flight log every telemetry reader produces (:class:`FlightLog`): one row per sample, times in seconds.

Angles follow one convention whatever the source (see :mod:`mosaic_cli.geo.camera`):
``yaw`` is the compass direction of the frame's top edge (degrees clockwise from north),
``pitch`` the camera's pitch (-90 looks straight down, above -90 tilts toward the frame's
top), ``roll`` its roll (positive tilts toward the frame's right).  ``height`` is the height
above the ground (DJI's rel_alt: above the take-off point), ``alt`` the absolute altitude.
Unknown values are NaN; a sample without a GPS fix has NaN latitude and longitude.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mosaic_cli.telemetry.photo_tags import PhotoTags

FIELDS = ("lat", "lon", "alt", "height", "yaw", "pitch", "roll", "hfov")


@dataclass
class FlightLog:
    source: str  # what was read, for messages: "flight.SRT (DJI SRT, per-frame)"
    time: np.ndarray  # (N,) seconds; from the video's start once aligned
    lat: np.ndarray
    lon: np.ndarray
    alt: np.ndarray
    height: np.ndarray
    yaw: np.ndarray
    pitch: np.ndarray
    roll: np.ndarray
    hfov: np.ndarray
    clock_time: bool = False  # times were wall-clock times (GPX, CSV, KLV) made relative to the first sample
    notes: list[str] = field(default_factory=list)
    # A photo folder's log: each sample's photo (its name, camera and what its metadata lacked).
    photos: list[PhotoTags] | None = None
    # Several flights' logs merged (stitch/flights.py): when each flight after the first begins
    # (seconds); the pause before each is no gap in any one log.
    breaks: list[float] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.time)

    @property
    def has_fix(self) -> np.ndarray:
        return np.isfinite(self.lat) & np.isfinite(self.lon)

    def known(self, name: str) -> bool:
        return bool(np.isfinite(getattr(self, name)).any())

    def select(self, keep: np.ndarray) -> FlightLog:
        photos = None if self.photos is None else [p for p, k in zip(self.photos, keep) if k]
        return FlightLog(self.source, self.time[keep], *(getattr(self, f)[keep] for f in FIELDS), self.clock_time, list(self.notes), photos,
                         list(self.breaks))

    def flight_at(self, times: np.ndarray) -> np.ndarray:
        """Which of the merged flights (0, 1, ...; see ``breaks``) each of ``times`` falls in."""
        return np.searchsorted(np.asarray(self.breaks, float), times, side="right")

    def shifted(self, seconds: float) -> FlightLog:
        out = self.select(np.ones(len(self), bool))
        out.time = out.time + float(seconds)
        out.breaks = [b + float(seconds) for b in self.breaks]
        return out


class FlightLogBuilder:
    """Collects samples as dicts (missing keys: unknown) and makes a time-sorted ``FlightLog``."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, dict[str, float]]] = []

    def add(self, time: float, **values: float | None) -> None:
        self.rows.append((float(time), {k: float(v) for k, v in values.items() if v is not None}))

    def build(self, source: str, clock_time: bool = False) -> FlightLog:
        self.rows.sort(key=lambda r: r[0])
        n = len(self.rows)
        cols = {f: np.full(n, np.nan) for f in FIELDS}
        for i, (_, values) in enumerate(self.rows):
            for k, v in values.items():
                cols[k][i] = v
        # (0, 0) is how DJI and many loggers write "no fix"; so is an out-of-range coordinate.
        no_fix = ~(np.abs(cols["lat"]) <= 90) | ~(np.abs(cols["lon"]) <= 180) | ((cols["lat"] == 0) & (cols["lon"] == 0))
        cols["lat"][no_fix] = np.nan
        cols["lon"][no_fix] = np.nan
        time = np.array([r[0] for r in self.rows], dtype=np.float64)
        return FlightLog(source, time, **cols, clock_time=clock_time)
