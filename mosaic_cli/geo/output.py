"""Georeferenced outputs, written atomically: a Cloud Optimized GeoTIFF with alpha, the
keyframes' ground footprints and the flight track as GeoJSON (WGS84), and the map
homographies for the transforms JSON."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mosaic_cli.atomic import atomic_path, interruptible
from mosaic_cli.errors import gdal_writing, require_geo
from mosaic_cli.geo.georef import Georeference
from mosaic_cli.geometry import frame_corners, normalize, project, rect_corners

BLOCK = 512


def canvas_to_ground(georef: Georeference, to_canvas: np.ndarray) -> np.ndarray:
    """Panorama pixel centres -> (east, north): north-up, so an axis-aligned scale and shift."""
    return np.linalg.inv(georef.ground_to_pixels) @ np.linalg.inv(to_canvas)


def geotransform(georef: Georeference, to_canvas: np.ndarray):
    """rasterio's Affine (pixel corners -> CRS) of the panorama."""
    from affine import Affine

    G = canvas_to_ground(georef, to_canvas) @ np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1.0]])
    G = G / G[2, 2]
    return Affine(G[0, 0], G[0, 1], G[0, 2], G[1, 0], G[1, 1], G[1, 2])


def write_cog(out: str | Path, raster: Path, size: tuple[int, int], for_output: str | Path | None = None) -> None:
    """A georeferenced RGBA GeoTIFF (``raster``, of ``size`` (W, H)) -> the Cloud Optimized
    GeoTIFF ``out``: 512-px internal tiles, deflate, overviews (averaged) down to a tile and at
    least one, transparency as an alpha band; BigTIFF where the map needs it.  GDAL's COG driver
    reads and writes block by block, in one call that a signal does not wait for
    (:func:`interruptible`; its overviews are staged beside the output, in a private folder).
    ``for_output``: the user's output this COG is made for, which an error names (else ``out``)."""
    require_geo("rasterio")
    from rasterio.shutil import copy

    width, height = size
    levels = max(1, sum(1 for k in range(1, 32) if max(width, height) / 2 ** (k - 1) > BLOCK))
    options = dict(COMPRESS="DEFLATE", BLOCKSIZE=str(BLOCK), OVERVIEW_RESAMPLING="AVERAGE", OVERVIEW_COUNT=str(levels),
                   BIGTIFF="IF_SAFER")
    with gdal_writing(for_output or out, "the GeoTIFF" if for_output is None else "the map's overviews"), \
            atomic_path(out, alone=True) as tmp:
        interruptible(lambda: copy(str(raster), str(tmp), driver="COG", **options))


def footprint_collection(georef: Georeference, map_h: list[np.ndarray], frame_size: tuple[int, int], fps: float,
                         boxes: dict[int, tuple[int, int, int, int]] | None = None) -> dict:
    """GeoJSON (RFC 7946, WGS84 lon/lat): a Polygon per keyframe's ground footprint (``gps``:
    whether its fix agreed with the images, was an outlier, or was missing; ``centre``: where
    the frame's centre lies, lon/lat), the GPS track as read (a LineString of every fix but those
    dropped as outliers), each dropped fix apart (a Point, ``kind`` "dropped gps fix", with its
    ``sample`` number and ``time`` in the log), and the camera path as placed.  ``boxes``: where
    a frame's pixels lie in it (x, y, w, h) where they do not fill it (a photo of another shape),
    by frame index."""
    corners = frame_corners(*frame_size)
    proj = georef.projection

    def lonlat(points: np.ndarray) -> list[list[float]]:
        return [[round(float(x), 9), round(float(y), 9)] for x, y in proj.to_wgs84(points[:, 0], points[:, 1])]

    w, h = frame_size
    centre = np.array([[(w - 1) / 2.0, (h - 1) / 2.0]])
    features = []
    for k, (index, M) in enumerate(zip(georef.frame_indices, map_h)):
        box = (boxes or {}).get(int(index))
        ring = project(M, corners if box is None else rect_corners(box[0] - 0.5, box[1] - 0.5, box[2], box[3]))
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
    flight = track.flight_at(track.time)  # several flights: a line each
    for k in np.unique(flight[kept]):
        line = kept & (flight == k)
        if line.sum() < 2:
            continue
        coords = [[round(float(lon), 9), round(float(lat), 9)] for lat, lon in zip(track.lat[line], track.lon[line])]
        features.append({"type": "Feature", "geometry": {"type": "LineString", "coordinates": coords},
                         "properties": {"kind": "gps track", "source": track.source, "flight": int(k)}})
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
