"""Telemetry aligned to video frames: interpolation between fixes, with outliers, dropouts
and gaps found and reported, never silently bridged or dropped."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mosaic_cli.telemetry.flight_log import FlightLog

EARTH_RADIUS = 6_371_000.0


@dataclass
class AlignOptions:
    max_gap: float = 3.0  # seconds: frames in a longer stretch without fixes get none
    outlier_metres: float = 15.0  # a fix this far from its neighbours' median track is an outlier
    outlier_window: float = 2.0  # seconds each side for that median
    # A photo folder's fixes are each photo's own: a photo without one gets none from its
    # neighbours (it is placed by its pixels), where a video frame between fixes is interpolated;
    # and a fix is judged by the images (the fit's inliers), not by its neighbours in time, which
    # at a survey line's turn are on the next line.
    per_photo: bool = False

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """No flag sets these: a bad value is a bug (ValueError), not the user's input."""
        if min(self.max_gap, self.outlier_metres, self.outlier_window) <= 0:
            raise ValueError(f"alignment options must be positive: {self}")


@dataclass
class AlignedTelemetry:
    """Per-frame values (NaN where unknown); ``fix`` says which frames have a position."""

    frame_times: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    height: np.ndarray
    yaw: np.ndarray
    pitch: np.ndarray
    roll: np.ndarray
    hfov: np.ndarray
    fix: np.ndarray
    samples: int
    without_fix: int
    outliers: int
    gaps: list[tuple[float, float]] = field(default_factory=list)  # (start, length) seconds
    span: tuple[float, float] = (0.0, 0.0)  # first and last usable fix
    source: str = ""
    notes: list[str] = field(default_factory=list)
    # over the track's samples: the fixes dropped as outliers (``outliers`` of them), which no
    # frame's position comes from and no drawn track should join
    dropped: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    flights: int = 1  # logs merged (several flights): their pauses are neither gaps nor time flown
    paused: float = 0.0  # seconds between the merged flights' logs

    def summary(self) -> str:
        flown = self.span[1] - self.span[0] - self.paused
        rate = (self.samples - self.flights) / max(flown, 1e-9) if self.samples > self.flights else 0.0
        over = (f"{self.flights} flights ({flown:.1f} s of log)" if self.flights > 1
                else f"{self.span[0]:.1f}-{self.span[1]:.1f} s")
        parts = [f"{self.samples} samples ({rate:.1f} Hz) over {over}"]
        if self.without_fix:
            parts.append(f"{self.without_fix} without a GPS fix")
        if self.outliers:
            parts.append(f"{self.outliers} outlying fixes dropped")
        if self.gaps:
            longest = max(self.gaps, key=lambda g: g[1])
            parts.append(f"{len(self.gaps)} gaps (longest {longest[1]:.1f} s at {longest[0]:.1f} s)")
        uncovered = int((~self.fix).sum())
        if uncovered:
            parts.append(f"{uncovered} of {len(self.fix)} frames without a position")
        return f"{self.source}: " + ", ".join(parts + self.notes)


def local_metres(lat: np.ndarray, lon: np.ndarray, lat0: float, lon0: float) -> np.ndarray:
    """(N, 2) east/north metres around (lat0, lon0), equirectangular (for outlier tests only)."""
    x = np.radians(lon - lon0) * EARTH_RADIUS * np.cos(np.radians(lat0))
    y = np.radians(lat - lat0) * EARTH_RADIUS
    return np.stack([x, y], 1)


def find_outliers(times: np.ndarray, xy: np.ndarray, options: AlignOptions) -> np.ndarray:
    """Fixes farther than ``outlier_metres`` from the median of the fixes around them."""
    out = np.zeros(len(times), bool)
    lo = np.searchsorted(times, times - options.outlier_window, "left")
    hi = np.searchsorted(times, times + options.outlier_window, "right")
    for i in range(len(times)):
        a, b = lo[i], hi[i]
        if b - a < 5:  # too few neighbours to judge; widen to the five nearest
            a, b = max(0, i - 2), min(len(times), i + 3)
            if b - a < 3:
                continue
        centre = np.median(xy[a:b], axis=0)
        out[i] = np.linalg.norm(xy[i] - centre) > options.outlier_metres
    return out


def _interp(t: np.ndarray, times: np.ndarray, values: np.ndarray, angle: bool = False) -> np.ndarray:
    ok = np.isfinite(values)
    if ok.sum() == 0:
        return np.full(len(t), np.nan)
    v = values[ok]
    if angle:
        v = np.degrees(np.unwrap(np.radians(v)))
    out = np.interp(t, times[ok], v)
    if angle:
        out = (out + 180.0) % 360.0 - 180.0
    return out


def align_to_frames(track: FlightLog, frame_times: np.ndarray, options: AlignOptions | None = None) -> AlignedTelemetry:
    options = options or AlignOptions()
    t = np.asarray(frame_times, dtype=np.float64)
    fixed = track.has_fix
    times = track.time[fixed]
    lat, lon = track.lat[fixed], track.lon[fixed]
    outliers = np.zeros(len(times), bool)
    if len(times) >= 3 and not options.per_photo:
        xy = local_metres(lat, lon, float(np.median(lat)), float(np.median(lon)))
        outliers = find_outliers(times, xy, options)
    good_t, good_lat, good_lon = times[~outliers], lat[~outliers], lon[~outliers]
    dropped = np.zeros(len(track), bool)
    dropped[np.nonzero(fixed)[0][outliers]] = True
    n = len(t)
    frame_lat = np.full(n, np.nan)
    frame_lon = np.full(n, np.nan)
    fix = np.zeros(n, bool)
    gaps: list[tuple[float, float]] = []
    span, paused = (0.0, 0.0), 0.0
    if len(good_t):
        span = (float(good_t[0]), float(good_t[-1]))
        step = float(np.median(np.diff(good_t))) if len(good_t) > 1 else 1.0
        # A frame between fixes farther apart than the gap limit has no position; frames
        # just past either end get one only within half a sample interval.
        reach = max(options.max_gap, 2.5 * step)
        dt = np.diff(good_t)
        between = np.diff(track.flight_at(good_t)) != 0  # the pause from one merged flight to the next
        paused = float(dt[between].sum())
        for k in np.nonzero((dt > max(1.0, 2.5 * step)) & ~between)[0]:
            gaps.append((float(good_t[k]), float(dt[k])))
        right = np.clip(np.searchsorted(good_t, t, "left"), 0, len(good_t) - 1)
        left = np.clip(right - 1, 0, len(good_t) - 1)
        exact = np.abs(good_t[right] - t) < 1e-9
        inside = (t >= good_t[0] - step / 2) & (t <= good_t[-1] + step / 2)
        bridged = np.where(exact, 0.0, good_t[right] - good_t[left])
        fix = inside & (bridged <= reach)
        if options.per_photo:
            fix &= exact
        frame_lat = np.where(fix, np.interp(t, good_t, good_lat), np.nan)
        frame_lon = np.where(fix, np.interp(t, good_t, good_lon), np.nan)
    all_t = track.time
    return AlignedTelemetry(
        t, frame_lat, frame_lon,
        _interp(t, all_t, track.height), _interp(t, all_t, track.yaw, angle=True),
        _interp(t, all_t, track.pitch), _interp(t, all_t, track.roll), _interp(t, all_t, track.hfov),
        fix, len(track), int((~fixed).sum()), int(outliers.sum()), gaps, span, track.source, list(track.notes), dropped,
        1 + len(track.breaks), paused,
    )
