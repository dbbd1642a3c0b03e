"""Telemetry for simulated flights: where the virtual drone was, as a GPS would log it.

The map gets a geotransform (a GeoTIFF's own, or ``--origin LAT,LON --gsd M``), the camera's
exact pose is read back from each frame's ``map_to_frame`` (see trajectory.py: a pinhole of
focal length = frame width above the map), and the log gets realistic GPS errors: a
first-order Gauss-Markov (exponentially correlated) error of ``rms`` metres horizontally,
single-sample bad fixes 20-60 m off, and dropouts (samples without a fix); its barometric
height is off by one offset for the whole flight (``height_bias`` RMS: zeroed at take-off, a
barometer drifts with the weather, temperature and airspeed by about half a metre) plus
white noise (``height_rms``).  The truth goes to
``<stem>.geo.json`` beside the video, so every placement can be scored in metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

from mosaic_cli.atomic import atomic_path, write_json
from mosaic_cli.errors import BadInput
from mosaic_cli.geo.camera import gimbal_angles, hfov_degrees, intrinsics
from mosaic_cli.geo.crs import Projection
from mosaic_cli.simulate.groundtruth import GroundTruth

FORMATS = {"srt": ".SRT", "gpx": ".gpx", "csv": ".csv", "klv": ".klv"}
START_CLOCK = datetime(2026, 6, 1, 10, 0, 0, tzinfo=UTC)  # the flight's (made-up) take-off time
GROUND_ELEVATION = 120.0  # metres above the ellipsoid of the flat simulated ground


def check_origin(lat: float, lon: float, gsd: float) -> None:
    """``--origin`` within the UTM zones, ``--gsd`` a plausible ground sample distance."""
    if not (-80 <= lat <= 84 and -180 <= lon <= 180):
        raise BadInput(f"--origin {lat},{lon} is outside the UTM zones (latitude -80..84, longitude -180..180)")
    if not 0.001 <= gsd <= 100:
        raise BadInput(f"--gsd must be between 0.001 and 100 metres per map pixel, got {gsd}")


@dataclass
class MapGeo:
    """Where a map lies: map pixel centre (x, y, 1) -> projected (east, north) by ``map_to_crs``."""

    crs: str
    map_to_crs: np.ndarray
    gsd: float  # metres per map pixel

    @classmethod
    def from_origin(cls, lat: float, lon: float, gsd: float, map_size: tuple[int, int]) -> MapGeo:
        """A north-up map of ``gsd`` m/px whose centre lies at (lat, lon), in that site's UTM zone."""
        check_origin(lat, lon, gsd)
        proj = Projection.utm_for(lat, lon)
        east, north = proj.to_map([lat], [lon])[0]
        cx, cy = (map_size[0] - 1) / 2.0, (map_size[1] - 1) / 2.0
        M = np.array([[gsd, 0, east - gsd * cx], [0, -gsd, north + gsd * cy], [0, 0, 1.0]])
        return cls(proj.name, M, float(gsd))

    @classmethod
    def from_geotiff(cls, path: str | Path) -> MapGeo | None:
        """The geotransform of a GeoTIFF as ``load_map`` crops it (None: no georeference)."""
        import cv2
        import rasterio

        from mosaic_cli.simulate.maps import nodata_mask, valid_rectangle

        try:
            with rasterio.open(path) as ds:
                crs, transform = ds.crs, ds.transform
        except rasterio.errors.RasterioIOError:
            return None
        if crs is None or transform.is_identity:
            return None
        if not crs.is_projected:
            raise BadInput(f"{path}: its CRS ({crs}) is not projected; reproject it to metres (e.g. UTM) to fly over it")
        # The same crop load_map makes (the largest valid rectangle), so map pixels line up.
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        x, y, _, _ = valid_rectangle(~nodata_mask(img, img[:, :, 3] if img.shape[2] == 4 else None))
        a, b, c, d, e, f = transform.a, transform.b, transform.c, transform.d, transform.e, transform.f
        # rasterio's transform maps pixel corners; map pixels are centres, offset by the crop.
        corner = np.array([[a, b, c], [d, e, f], [0, 0, 1.0]])
        M = corner @ np.array([[1, 0, x + 0.5], [0, 1, y + 0.5], [0, 0, 1.0]])
        gsd = math.sqrt(abs(a * e - b * d))
        epsg = crs.to_epsg()
        return cls(f"EPSG:{epsg}" if epsg else crs.to_wkt(), M, gsd)

    def to_json(self) -> dict:
        return {"crs": self.crs, "map_to_crs": self.map_to_crs.tolist(), "gsd": self.gsd}


@dataclass
class CameraPoses:
    """The exact camera of every frame: map-pixel position, height, gimbal angles, field of view."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray  # height, map pixels
    pitch: np.ndarray
    roll: np.ndarray
    heading: np.ndarray  # radians, the simulator's Rz angle
    hfov: float


def camera_poses(gt: GroundTruth) -> CameraPoses:
    """Decompose each (jitter-free) ``map_to_frame`` = K R [[1,0,-X],[0,1,-Y],[0,0,Z]]."""
    w, h = gt.size
    focal = float(w)  # trajectory.plan_flight's camera
    Kinv = np.linalg.inv(intrinsics((w, h), focal))
    n = gt.frames
    out = {k: np.zeros(n) for k in ("x", "y", "z", "pitch", "roll", "heading")}
    for t, M in enumerate(gt.smooth_map_to_frame):
        A = Kinv @ M
        lam = 1.0 / np.linalg.norm(A[:, 0])
        r1, r2 = lam * A[:, 0], lam * A[:, 1]
        R = np.stack([r1, r2, np.cross(r1, r2)], 1)
        if abs(float(r1 @ r2)) > 1e-6 or abs(np.linalg.norm(r2) - 1) > 1e-6:
            raise BadInput("the flight's camera is not the simulator's pinhole (internal error)")
        v = R.T @ (lam * A[:, 2])
        if v[2] < 0:  # the homography's overall sign
            R[:, :2] *= -1
            v = R.T @ (-lam * A[:, 2])
        out["x"][t], out["y"][t], out["z"][t] = -v[0], -v[1], v[2]
        b = math.asin(max(-1.0, min(1.0, R[0, 2])))
        out["heading"][t] = math.atan2(-R[0, 1], R[0, 0])
        a = math.atan2(-R[1, 2], R[2, 2])
        out["pitch"][t], out["roll"][t] = gimbal_angles(a, b)
    return CameraPoses(**out, hfov=hfov_degrees(w, focal))


@dataclass
class GpsErrors:
    rms: float = 3.0  # horizontal RMS, metres
    correlation: float = 2.0  # seconds (time constant of the Gauss-Markov error)
    dropouts: float = 0.02  # fraction of samples without a fix
    bad_fixes: float = 0.005  # fraction of samples 20-60 m off
    height_rms: float = 0.3  # barometric height noise, metres, independent per sample
    height_bias: float = 0.5  # RMS of the barometric height's offset over a whole flight, metres
    seed: int = 0

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        if not 0 <= self.rms <= 1000:
            raise BadInput(f"--gps-noise must be between 0 and 1000 metres, got {self.rms}")
        if not 0 <= self.dropouts < 1 or not 0 <= self.bad_fixes < 1:
            raise BadInput("--gps-dropouts and bad-fix fractions must be in [0, 1)")
        if self.correlation <= 0:
            raise BadInput(f"GPS error correlation time must be positive, got {self.correlation}")
        if not 0 <= self.height_rms <= 100 or not 0 <= self.height_bias <= 100:
            raise BadInput(f"--baro-bias and the height noise must be between 0 and 100 metres, got {self.height_bias}, {self.height_rms}")


@dataclass
class SimulatedLog:
    time: np.ndarray  # seconds from the first frame
    lat: np.ndarray  # NaN: dropout
    lon: np.ndarray
    alt: np.ndarray
    height: np.ndarray
    yaw: np.ndarray
    pitch: np.ndarray
    roll: np.ndarray
    hfov: float
    true_east: np.ndarray
    true_north: np.ndarray


def gauss_markov(rng: np.random.Generator, times: np.ndarray, sigma: float, tau: float) -> np.ndarray:
    out = np.zeros(len(times))
    if len(times) == 0 or sigma == 0:
        return out
    out[0] = sigma * rng.standard_normal()
    for k in range(1, len(times)):
        phi = math.exp(-(times[k] - times[k - 1]) / tau)
        out[k] = phi * out[k - 1] + math.sqrt(1 - phi * phi) * sigma * rng.standard_normal()
    return out


def height_offset(errors: GpsErrors) -> float:
    """The barometric height's offset over the whole flight, metres (its own random stream, so
    that the horizontal GPS errors of a seed do not depend on it)."""
    return float(errors.height_bias * np.random.default_rng([errors.seed, 4127]).standard_normal())


def simulate_log(gt: GroundTruth, geo: MapGeo, errors: GpsErrors, rate: float | None = None) -> SimulatedLog:
    """The GPS log of the flight: one sample per frame (``rate`` None) or ``rate`` per second."""
    poses = camera_poses(gt)
    frame_t = np.arange(gt.frames) / gt.fps
    times = frame_t if rate is None else np.arange(0.0, frame_t[-1] + 1e-9, 1.0 / rate)

    def at(values):
        return np.interp(times, frame_t, values)

    heading = at(np.unwrap(poses.heading))
    xy1 = np.stack([at(poses.x), at(poses.y), np.ones(len(times))], 1)
    east, north = (xy1 @ geo.map_to_crs.T)[:, :2].T
    # The map's axes in CRS terms: the bearing of map "up" (-y) for turning headings into yaw.
    up = geo.map_to_crs[:2, :2] @ np.array([0.0, -1.0])
    map_up_bearing = math.degrees(math.atan2(up[0], up[1]))
    yaw = (-np.degrees(heading) + map_up_bearing + 180.0) % 360.0 - 180.0
    rng = np.random.default_rng([errors.seed, 4099])
    axis_sigma = errors.rms / math.sqrt(2.0)
    noisy_e = east + gauss_markov(rng, times, axis_sigma, errors.correlation)
    noisy_n = north + gauss_markov(rng, times, axis_sigma, errors.correlation)
    bad = rng.random(len(times)) < errors.bad_fixes
    angle = rng.uniform(0, 2 * np.pi, len(times))
    jump = rng.uniform(20.0, 60.0, len(times))
    noisy_e = np.where(bad, noisy_e + jump * np.cos(angle), noisy_e)
    noisy_n = np.where(bad, noisy_n + jump * np.sin(angle), noisy_n)
    proj = Projection(geo.crs)
    lonlat = proj.to_wgs84(noisy_e, noisy_n)
    drop = rng.random(len(times)) < errors.dropouts
    drop[0] = drop[-1] = False  # the log covers the whole flight
    lat = np.where(drop, np.nan, lonlat[:, 1])
    lon = np.where(drop, np.nan, lonlat[:, 0])
    height = at(poses.z) * geo.gsd
    noisy_height = height + height_offset(errors) + errors.height_rms * rng.standard_normal(len(times))
    return SimulatedLog(
        times, lat, lon, noisy_height + GROUND_ELEVATION + 2.0 * rng.standard_normal(len(times)), noisy_height,
        yaw, at(poses.pitch), at(poses.roll), poses.hfov, east, north,
    )


# ---------------------------------------------------------------------------------------------
# writers


def _srt_time(t: float) -> str:
    ms = int(round(t * 1000))
    return f"{ms // 3600000:02d}:{ms // 60000 % 60:02d}:{ms // 1000 % 60:02d},{ms % 1000:03d}"


def srt_text(log: SimulatedLog) -> str:
    """DJI's per-frame bracketed SRT (Mavic 3 style), 0, 0 coordinates where there is no fix."""
    focal35 = 18.0 / math.tan(math.radians(log.hfov) / 2)
    blocks = []
    times = log.time
    for k, t in enumerate(times):
        end = times[k + 1] if k + 1 < len(times) else t + (times[1] - times[0] if len(times) > 1 else 1 / 30)
        lat = 0.0 if not np.isfinite(log.lat[k]) else log.lat[k]
        lon = 0.0 if not np.isfinite(log.lon[k]) else log.lon[k]
        clock = START_CLOCK + timedelta(seconds=float(t))
        blocks.append(
            f"{k + 1}\n{_srt_time(t)} --> {_srt_time(end)}\n"
            f"<font size=\"28\">FrameCnt: {k + 1}, DiffTime: {int(round((end - t) * 1000))}ms\n"
            f"{clock.strftime('%Y-%m-%d %H:%M:%S')}.{clock.microsecond // 1000:03d}\n"
            f"[iso: 100] [shutter: 1/1000.0] [fnum: 2.8] [ev: 0] [ct: 5500] [color_md: default] "
            f"[focal_len: {focal35:.2f}] [dzoom_ratio: 1.00, delta:0] [latitude: {lat:.7f}] [longitude: {lon:.7f}] "
            f"[rel_alt: {log.height[k]:.3f} abs_alt: {log.alt[k]:.3f}] "
            f"[gb_yaw: {log.yaw[k]:.2f} gb_pitch: {log.pitch[k]:.2f} gb_roll: {log.roll[k]:.2f}] </font>\n"
        )
    return "\n".join(blocks)


def gpx_text(log: SimulatedLog) -> str:
    import gpxpy.gpx

    gpx = gpxpy.gpx.GPX()
    track = gpxpy.gpx.GPXTrack(name="mosaic simulate")
    segment = gpxpy.gpx.GPXTrackSegment()
    for k, t in enumerate(log.time):
        fixed = np.isfinite(log.lat[k])
        point = gpxpy.gpx.GPXTrackPoint(
            float(log.lat[k]) if fixed else 0.0, float(log.lon[k]) if fixed else 0.0,
            elevation=round(float(log.alt[k]), 3), time=START_CLOCK + timedelta(seconds=float(t)),
        )
        if not fixed:
            point.type_of_gpx_fix = "none"
        segment.points.append(point)
    track.segments.append(segment)
    gpx.tracks.append(track)
    return gpx.to_xml()


def csv_text(log: SimulatedLog) -> str:
    lines = ["time,lat,lon,alt,height,yaw,pitch,roll,hfov"]
    for k, t in enumerate(log.time):
        fixed = np.isfinite(log.lat[k])
        lat = f"{log.lat[k]:.8f}" if fixed else ""
        lon = f"{log.lon[k]:.8f}" if fixed else ""
        lines.append(
            f"{t:.4f},{lat},{lon},{log.alt[k]:.3f},{log.height[k]:.3f},{log.yaw[k]:.3f},{log.pitch[k]:.3f},{log.roll[k]:.3f},{log.hfov:.3f}"
        )
    return "\n".join(lines) + "\n"


def klv_bytes(log: SimulatedLog) -> bytes:
    from mosaic_cli.telemetry.klv import encode_packet

    base = int(START_CLOCK.timestamp() * 1_000_000)
    out = bytearray()
    for k, t in enumerate(log.time):
        out += encode_packet(base + int(round(t * 1e6)), {
            "lat": log.lat[k], "lon": log.lon[k], "alt": log.alt[k], "ground_alt": log.alt[k] - log.height[k],
            "platform_heading": log.yaw[k] % 360.0, "sensor_azimuth": 0.0, "sensor_elevation": log.pitch[k],
            "sensor_roll": log.roll[k] % 360.0, "hfov": log.hfov,
        })
    return bytes(out)


def telemetry_path(video: str | Path, fmt: str) -> Path:
    p = Path(video)
    return p.with_name(p.stem + FORMATS[fmt])


def geo_truth_path(video: str | Path) -> Path:
    p = Path(video)
    return p.with_name(p.stem + ".geo.json")


def write_telemetry(video: str | Path, gt: GroundTruth, geo: MapGeo, fmt: str, errors: GpsErrors, rate: float | None = None) -> Path:
    """Write the flight's log in ``fmt`` beside ``video`` and the geographic truth to ``<stem>.geo.json``."""
    log = simulate_log(gt, geo, errors, rate)
    path = telemetry_path(video, fmt)
    if fmt == "klv":
        with atomic_path(path) as tmp:
            tmp.write_bytes(klv_bytes(log))
    else:
        text = {"srt": srt_text, "gpx": gpx_text, "csv": csv_text}[fmt](log)
        with atomic_path(path) as tmp:
            tmp.write_text(text)
    poses = camera_poses(gt)
    write_json(geo_truth_path(video), {
        "kind": "mosaic-geo-truth", "version": 1, **geo.to_json(), "hfov": poses.hfov,
        "telemetry": str(path.name), "format": fmt,
        "gps_errors": {"rms": errors.rms, "correlation": errors.correlation, "dropouts": errors.dropouts,
                       "bad_fixes": errors.bad_fixes, "seed": errors.seed, "height_rms": errors.height_rms,
                       "height_bias": errors.height_bias, "height_offset": height_offset(errors)},
    })
    return path


@dataclass
class TelemetryOptions:
    """``simulate --telemetry FORMAT`` and the flags that shape the log."""

    format: str = "srt"  # one of FORMATS
    origin: str = "47.3977,8.5456"  # LAT,LON of the map's centre, when the map carries no geotransform
    gsd: float = 0.05  # metres per map pixel, likewise
    rate: float = 0.0  # log samples per second; 0: one per frame
    errors: GpsErrors = field(default_factory=GpsErrors)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        if self.format not in FORMATS:
            raise BadInput(f"--telemetry must be one of {', '.join(FORMATS)}, got {self.format!r}")
        if not 0 <= self.rate <= 1000:
            raise BadInput(f"--telemetry-rate must be between 0 and 1000 samples per second, got {self.rate}")
        check_origin(*self.lat_lon, self.gsd)

    @property
    def lat_lon(self) -> tuple[float, float]:
        try:
            lat, lon = (float(v) for v in str(self.origin).split(","))
        except ValueError:
            raise BadInput(f"--origin must look like 47.3977,8.5456 (latitude,longitude), got {self.origin!r}") from None
        return lat, lon


def prepare_telemetry(video, map_image, options: TelemetryOptions):
    """Before rendering: the log's outputs can be written; the map's geotransform (a GeoTIFF's,
    else ``options.origin`` and ``options.gsd``) as a function of the map size giving its ``MapGeo``."""
    from mosaic_cli.atomic import check_writable

    check_writable(telemetry_path(video, options.format))
    check_writable(geo_truth_path(video))
    if map_image is not None and Path(map_image).suffix.lower() in (".tif", ".tiff"):
        geo = MapGeo.from_geotiff(map_image)
        if geo is not None:
            return lambda size: geo
    lat, lon = options.lat_lon
    return lambda size: MapGeo.from_origin(lat, lon, options.gsd, size)
