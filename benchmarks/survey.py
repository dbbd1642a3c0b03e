"""A geotagged photo survey over a georeferenced map, with its exact truth: each photo is the map
seen by a nadir camera at a known position, height and yaw, written as a JPEG with EXIF GPS and
a DJI XMP block whose values carry the noise of a consumer drone's (GPS 2-3 m, yaw 2 degrees,
heights drifting), as mappers' folders do.

    survey = write_survey(folder, rows=3, per_row=6)
    survey.truth[i]       # photo i's pixels -> (east, north) metres, exact (UTM zone of survey.epsg)
    survey.fixes[i]       # the noisy (east, north) its EXIF says
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from PIL import ExifTags, Image

from mosaic_cli.simulate.maps import procedural_map

LAT0, LON0 = 46.52, 7.03  # the survey's site (UTM zone 32 north)
MAP_GSD = 0.05  # metres per map pixel


@dataclass
class Survey:
    folder: Path
    epsg: int
    size: tuple[int, int]  # photo (w, h)
    truth: list[np.ndarray]  # photo px -> (east, north), exact
    fixes: np.ndarray  # (n, 2) the written GPS positions, east/north
    positions: np.ndarray  # (n, 2) the true camera positions
    yaw: np.ndarray  # (n,) true yaw, degrees
    gsd: float  # metres per photo pixel
    names: list[str] = field(default_factory=list)


def ground_matrix(position, yaw_deg: float, gsd: float, size: tuple[int, int]) -> np.ndarray:
    """Photo pixels -> (east, north) metres of a nadir camera at ``position`` whose frame's top edge
    points at compass ``yaw_deg`` (the convention of DJI's GimbalYawDegree)."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    A = gsd * np.array([[c, -s], [-s, -c]])
    centre = np.array([(size[0] - 1) / 2.0, (size[1] - 1) / 2.0])
    G = np.eye(3)
    G[:2, :2] = A
    G[:2, 2] = np.asarray(position, float) - A @ centre
    return G


def _rational(x: float) -> tuple[float, float, float]:
    d = int(x)
    m = int((x - d) * 60)
    return float(d), float(m), round((x - d - m / 60.0) * 3600.0, 4)


def write_photo(path: Path, rgb: np.ndarray, lat: float | None, lon: float | None, alt: float, height: float | None,
                yaw: float | str | None, hfov: float, taken: str, pitch: float = -90.0, xmp: bool = True) -> None:
    """A JPEG with EXIF GPS (signed by its references), camera, time and 35 mm-equivalent focal
    length, and a DJI XMP block (relative altitude, gimbal attitude) as DJI drones write it
    (``yaw`` as text: written as it is, a damaged value)."""
    h, w = rgb.shape[:2]
    exif = Image.Exif()
    exif[271], exif[272] = "DJI", "FC3411"
    detail = exif.get_ifd(ExifTags.IFD.Exif)
    detail[36867] = taken
    across = math.hypot(36.0, 24.0) * w / math.hypot(w, h)
    detail[41989] = int(round(across / (2.0 * math.tan(math.radians(hfov) / 2.0))))
    if lat is not None and lon is not None:
        gps = exif.get_ifd(ExifTags.IFD.GPSInfo)
        gps[1], gps[2] = ("N" if lat >= 0 else "S"), _rational(abs(lat))
        gps[3], gps[4] = ("E" if lon >= 0 else "W"), _rational(abs(lon))
        gps[5], gps[6] = b"\x00", float(alt)
    block = None
    if xmp:
        attributes = [f'drone-dji:GimbalPitchDegree="{pitch:+.2f}"', 'drone-dji:GimbalRollDegree="+0.00"']
        if height is not None:
            attributes.append(f'drone-dji:RelativeAltitude="{height:+.2f}"')
        if yaw is not None:
            text = yaw if isinstance(yaw, str) else f"{yaw:+.2f}"
            attributes += [f'drone-dji:GimbalYawDegree="{text}"', f'drone-dji:FlightYawDegree="{text}"']
        block = ('<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?><x:xmpmeta xmlns:x="adobe:ns:meta/">'
                 '<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description rdf:about="" '
                 'xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" ' + " ".join(attributes) +
                 '/></rdf:RDF></x:xmpmeta><?xpacket end="w"?>').encode()
    Image.fromarray(rgb).save(path, "JPEG", quality=95, exif=exif, **({"xmp": block} if block else {}))


def write_survey(folder: Path, rows: int = 3, per_row: int = 6, size: tuple[int, int] = (800, 600), gsd: float = 0.1,
                 along: float = 26.0, across: float = 40.0, hfov: float = 62.0, gps_noise: float = 2.5, yaw_noise: float = 2.0,
                 seed: int = 0, map_image: np.ndarray | None = None, map_gsd: float = MAP_GSD) -> Survey:
    """``rows`` lawnmower lines of ``per_row`` photos, ``along`` metres apart on a line and ``across``
    between lines (the drone turns at each end: the yaw flips), written to ``folder``.  The GPS
    fixes carry ``gps_noise`` metres of error (RMS, horizontal), the yaw ``yaw_noise`` degrees, the
    heights a drift of 0.02 m per photo and 0.2 m of noise.  The map is ``map_gsd`` metres a pixel
    (``map_image``, else a procedural one)."""
    from pyproj import Transformer

    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    epsg = 32632
    to_utm = Transformer.from_crs("EPSG:4326", f"EPSG:{epsg}", always_xy=True)
    to_wgs = Transformer.from_crs(f"EPSG:{epsg}", "EPSG:4326", always_xy=True)
    e0, n0 = to_utm.transform(LON0, LAT0)
    height = gsd * size[0] / (2.0 * math.tan(math.radians(hfov) / 2.0))
    reach = 0.6 * math.hypot(*size) * gsd
    extent_e = (per_row - 1) * along + 2 * reach
    extent_n = (rows - 1) * across + 2 * reach
    if map_image is None:
        map_image = procedural_map((int(extent_e / map_gsd) + 8, int(extent_n / map_gsd) + 8), seed=seed)
    map_h, map_w = map_image.shape[:2]
    # map pixel -> (east, north): the map's top-left corner at the survey's north-west
    west, north = e0 - map_w * map_gsd / 2.0, n0 + map_h * map_gsd / 2.0
    to_map_px = np.linalg.inv(np.array([[map_gsd, 0, west], [0, -map_gsd, north], [0, 0, 1.0]]))
    smooth = cv2.GaussianBlur(map_image, (0, 0), 0.5 * gsd / map_gsd) if gsd > map_gsd else map_image  # against aliasing at the photos' coarser scale
    truth, fixes, positions, yaws, names = [], [], [], [], []
    k = 0
    for row in range(rows):
        line = range(per_row) if row % 2 == 0 else range(per_row - 1, -1, -1)
        yaw = 90.0 if row % 2 == 0 else -90.0
        for col in line:
            position = np.array([e0 + (col - (per_row - 1) / 2.0) * along, n0 + ((rows - 1) / 2.0 - row) * across])
            true_yaw = yaw + rng.normal(0, 1.0)
            G = ground_matrix(position, true_yaw, gsd, size)
            photo = cv2.warpPerspective(smooth, to_map_px @ G, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
            fix = position + rng.normal(0, gps_noise / math.sqrt(2.0), 2)
            lon, lat = to_wgs.transform(fix[0], fix[1])
            name = f"DJI_{k + 1:04d}.JPG"
            write_photo(folder / name, photo, lat, lon, 512.0 + height, height + 0.02 * k + rng.normal(0, 0.2),
                        true_yaw + rng.normal(0, yaw_noise), hfov, f"2026:05:01 10:{k // 30:02d}:{(2 * k) % 60:02d}")
            truth.append(G)
            fixes.append(fix)
            positions.append(position)
            yaws.append(true_yaw)
            names.append(name)
            k += 1
    return Survey(folder, epsg, size, truth, np.array(fixes), np.array(positions), np.array(yaws), gsd, names)


def project_point(H: np.ndarray, x: float, y: float) -> np.ndarray:
    p = H @ np.array([x, y, 1.0])
    return p[:2] / p[2]


def score_survey(survey: Survey, transforms: dict[str, Any]) -> tuple[list[float], list[float], list[float], list[float], list[float]]:
    """Per photo: the map's error at its centre (m), its raw fix's error (m), the map's scale over
    the truth's and its north error (degrees); and for each overlapping pair the largest corner
    error of their relative placement in the panorama (photo px)."""
    w, h = survey.size
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    frames = {f["index"]: f for f in transforms["frames"]}
    placed, raw, scale, north = [], [], [], []
    for i, G in enumerate(survey.truth):
        M = np.array(frames[i]["map_H"])
        placed.append(float(np.linalg.norm(project_point(M, cx, cy) - project_point(G, cx, cy))))
        raw.append(float(np.linalg.norm(survey.fixes[i] - survey.positions[i])))
        up, true_up = project_point(M, cx, cy - 100) - project_point(M, cx, cy), project_point(G, cx, cy - 100) - project_point(G, cx, cy)
        scale.append(float(np.linalg.norm(up) / np.linalg.norm(true_up)))
        turn = math.degrees(math.atan2(up[0], up[1]) - math.atan2(true_up[0], true_up[1]))
        north.append((turn + 180.0) % 360.0 - 180.0)
    pairs = []
    corners = [(0, 0), (w - 1, 0), (w - 1, h - 1), (0, h - 1)]
    for i in frames:
        for j in frames:
            truth = np.linalg.inv(survey.truth[j]) @ survey.truth[i]
            if j <= i or np.linalg.norm(project_point(truth, cx, cy) - (cx, cy)) > 0.8 * w:
                continue  # not overlapping
            rel = np.linalg.inv(np.array(frames[j]["H"])) @ np.array(frames[i]["H"])
            pairs.append(max(float(np.linalg.norm(project_point(rel, *c) - project_point(truth, *c))) for c in corners))
    return placed, raw, scale, north, pairs
