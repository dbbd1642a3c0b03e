"""Georeferenced outputs, written atomically: a Cloud Optimized GeoTIFF with alpha, the
keyframes' ground footprints and the flight track as GeoJSON (WGS84), and the map
homographies for the transforms JSON."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from mosaic_cli.atomic import atomic_path, signals_held, temporary_beside, write_json
from mosaic_cli.errors import ProcessingError, require_geo
from mosaic_cli.geo.georef import Georeference
from mosaic_cli.geometry import frame_corners, normalize, project

BLOCK = 512
ROWS_PER_WRITE = 1024  # strips keep the extra memory of the write to a few rows


def canvas_to_ground(georef: Georeference, to_canvas: np.ndarray) -> np.ndarray:
    """Panorama pixel centres -> (east, north): north-up, so an axis-aligned scale and shift."""
    return np.linalg.inv(georef.ground_to_pixels) @ np.linalg.inv(to_canvas)


def geotransform(georef: Georeference, to_canvas: np.ndarray):
    """rasterio's Affine (pixel corners -> CRS) of the panorama."""
    from affine import Affine

    G = canvas_to_ground(georef, to_canvas) @ np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1.0]])
    G = G / G[2, 2]
    return Affine(G[0, 0], G[0, 1], G[0, 2], G[1, 0], G[1, 1], G[1, 2])


def _write_geotiff(path: Path, rgba: np.ndarray, georef: Georeference, to_canvas: np.ndarray, overviews: bool = False) -> None:
    """A plain tiled RGBA GeoTIFF (alpha band), written in strips; with ``overviews``, averaged
    ones down to a tile (what a reader warping the whole map at a coarser scale wants)."""
    import rasterio
    from rasterio.enums import ColorInterp, Resampling
    from rasterio.windows import Window

    height, width = rgba.shape[:2]
    profile = dict(driver="GTiff", width=width, height=height, count=4, dtype="uint8", crs=georef.projection.crs.to_wkt(),
                   transform=geotransform(georef, to_canvas), tiled=True, blockxsize=BLOCK, blockysize=BLOCK, compress="deflate",
                   photometric="RGB", ALPHA="YES", BIGTIFF="IF_SAFER")
    with rasterio.open(path, "w", **profile) as dst:
        dst.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]
        for r0 in range(0, height, ROWS_PER_WRITE):
            r1 = min(height, r0 + ROWS_PER_WRITE)
            dst.write(np.ascontiguousarray(rgba[r0:r1].transpose(2, 0, 1)), window=Window(0, r0, width, r1 - r0))
        if overviews:
            factors = [2**k for k in range(1, 32) if max(width, height) / 2 ** (k - 1) > BLOCK]
            if factors:
                dst.build_overviews(factors, Resampling.average)


@contextlib.contextmanager
def staged_geotiff(out: str | Path, rgba: np.ndarray, georef: Georeference, to_canvas: np.ndarray) -> Iterator[Path]:
    """The panorama as a temporary GeoTIFF beside ``out`` (with overviews), for the writers that
    read a georeferenced raster (KMZ, web tiles, the quick-look page); removed on leaving."""
    import rasterio

    staging = None
    try:
        with signals_held():
            staging = temporary_beside(Path(out), ".staging.tif")
        try:
            _write_geotiff(staging, rgba, georef, to_canvas, overviews=True)
        except rasterio.errors.RasterioError as exc:
            raise ProcessingError(f"{out}: could not write the map's staging GeoTIFF ({exc})") from None
        yield staging
    finally:
        if staging is not None:
            with contextlib.suppress(FileNotFoundError):
                staging.unlink()


def write_cog(out: str | Path, rgba: np.ndarray, georef: Georeference, to_canvas: np.ndarray) -> None:
    """RGBA panorama -> Cloud Optimized GeoTIFF: 512-px internal tiles, deflate, overviews
    (averaged), transparency as an alpha band."""
    require_geo("rasterio", "rio_cogeo")
    import rasterio
    from rio_cogeo.cogeo import cog_translate
    from rio_cogeo.profiles import cog_profiles
    from rio_cogeo.utils import get_maximum_overview_level

    out = Path(out)
    height, width = rgba.shape[:2]
    staging = None
    try:
        with signals_held():
            staging = temporary_beside(out, ".staging.tif")
        _write_geotiff(staging, rgba, georef, to_canvas)
        cog = cog_profiles.get("deflate")
        cog.update(blockxsize=BLOCK, blockysize=BLOCK, BIGTIFF="IF_SAFER")
        with atomic_path(out) as tmp:
            # at least one overview level, also for a panorama smaller than a tile
            levels = max(1, get_maximum_overview_level(width, height, minsize=BLOCK))
            cog_translate(str(staging), str(tmp), cog, overview_level=levels, overview_resampling="average", quiet=True,
                          in_memory=False, use_cog_driver=False)
    except rasterio.errors.RasterioError as exc:
        raise ProcessingError(f"{out}: could not write the GeoTIFF ({exc})") from None
    finally:
        if staging is not None:
            with contextlib.suppress(FileNotFoundError):
                staging.unlink()


def write_footprints(path: str | Path, georef: Georeference, map_h: list[np.ndarray], frame_size: tuple[int, int], fps: float) -> None:
    """The footprints GeoJSON (see :func:`footprint_collection`), written atomically."""
    write_json(path, footprint_collection(georef, map_h, frame_size, fps))


def footprint_collection(georef: Georeference, map_h: list[np.ndarray], frame_size: tuple[int, int], fps: float) -> dict:
    """GeoJSON (RFC 7946, WGS84 lon/lat): a Polygon per keyframe's ground footprint (``gps``:
    whether its fix agreed with the images, was an outlier, or was missing; ``centre``: where
    the frame's centre lies, lon/lat), the GPS track as read (a LineString of every fix but those
    dropped as outliers), each dropped fix apart (a Point, ``kind`` "dropped gps fix", with its
    ``sample`` number and ``time`` in the log), and the camera path as placed."""
    corners = frame_corners(*frame_size)
    proj = georef.projection

    def lonlat(points: np.ndarray) -> list[list[float]]:
        return [[round(float(x), 9), round(float(y), 9)] for x, y in proj.to_wgs84(points[:, 0], points[:, 1])]

    w, h = frame_size
    centre = np.array([[(w - 1) / 2.0, (h - 1) / 2.0]])
    features = []
    for k, (index, M) in enumerate(zip(georef.frame_indices, map_h)):
        ring = project(M, corners)
        gps = "agrees" if georef.used[k] else ("outlier" if georef.telemetry.fix[k] else "none")
        features.append({
            "type": "Feature",
            "geometry": {"type": "Polygon", "coordinates": [lonlat(np.vstack([ring, ring[:1]]))]},
            "properties": {"kind": "footprint", "frame": int(index), "time": round(index / fps, 4), "gps": gps,
                           "centre": lonlat(project(M, centre))[0]},
        })
    track = georef.track
    dropped = georef.telemetry.dropped if len(georef.telemetry.dropped) == len(track) else np.zeros(len(track), bool)
    kept = track.has_fix & ~dropped
    if kept.sum() >= 2:
        coords = [[round(float(lon), 9), round(float(lat), 9)] for lat, lon in zip(track.lat[kept], track.lon[kept])]
        features.append({"type": "Feature", "geometry": {"type": "LineString", "coordinates": coords},
                         "properties": {"kind": "gps track", "source": track.source}})
    for i in np.nonzero(dropped)[0]:  # never joined into the track: each on its own
        features.append({"type": "Feature",
                         "geometry": {"type": "Point", "coordinates": [round(float(track.lon[i]), 9), round(float(track.lat[i]), 9)]},
                         "properties": {"kind": "dropped gps fix", "sample": int(i), "time": round(float(track.time[i]), 3),
                                        "source": track.source}})
    if len(map_h) >= 2:
        path_ground = np.array([project(M, centre)[0] for M in map_h])
        features.append({"type": "Feature", "geometry": {"type": "LineString", "coordinates": lonlat(path_ground)},
                         "properties": {"kind": "frame centres"}})
    return {"type": "FeatureCollection", "features": features}


def transforms_extra(georef: Georeference, map_h: list[np.ndarray]) -> tuple[dict, list[dict]]:
    """The transforms JSON's additions: the CRS at the top, each keyframe's ``map_H`` (frame
    pixels -> east, north metres in that CRS)."""
    top = {"crs": georef.crs, "gsd_m": georef.gsd}
    return top, [{"map_H": [[float(v) for v in row] for row in normalize(M)]} for M in map_h]
