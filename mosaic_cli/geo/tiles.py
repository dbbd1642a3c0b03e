"""Web map tiles of a georeferenced mosaic: XYZ tiles in Web Mercator (``DIR/{z}/{x}/{y}.png``,
with a TileJSON ``metadata.json``), PMTiles (one file, the ``pmtiles`` package) and MBTiles
(SQLite), the zoom range chosen from the map's ground resolution.

The tile grid is morecantile's WebMercatorQuad (the OSM/Google XYZ scheme); the pixels are
warped by GDAL (a rasterio WarpedVRT per zoom level, aligned to that level's tile grid:
bilinear where a tile pixel is finer than the map's, averaged where coarser).  A folder is
written whole or not at all: into a temporary folder beside it, then renamed."""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import sqlite3
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mosaic_cli.atomic import atomic_path, give_default_permissions, private_folder
from mosaic_cli.errors import BadInput, ProcessingError, warn, write_failed

TILE = 256
METADATA = "metadata.json"  # a TileJSON beside the tiles; also how a folder mosaic wrote is known again
MBTILES_DEEPEST = 22  # the deepest zoom GDAL's MBTiles driver (QGIS's) opens: "zoom_level > 22 not supported"


def web_mercator():
    import morecantile

    return morecantile.tms.get("WebMercatorQuad")


@dataclass(frozen=True)
class ZoomRange:
    minzoom: int
    maxzoom: int
    bounds: tuple[float, float, float, float]  # west, south, east, north (WGS84 degrees)


def zoom_range(geotiff: str | Path) -> ZoomRange:
    """The zooms to tile a map at: the deepest is the first whose tile pixels are finer than
    the map's (in Web Mercator metres, at the map's place); the shallowest the deepest at which
    the whole map fits in one tile's span (so in one to four tiles)."""
    import rasterio
    from rasterio.warp import calculate_default_transform, transform_bounds

    tms = web_mercator()
    with rasterio.open(geotiff) as src:
        transform, width, height = calculate_default_transform(src.crs, "EPSG:3857", src.width, src.height, *src.bounds)
        west, south, east, north = transform_bounds(src.crs, "EPSG:4326", *src.bounds, densify_pts=21)
    res = abs(transform.a)
    top = tms.maxzoom
    maxzoom = next((z for z in range(top + 1) if tms.matrix(z).cellSize <= res), top)
    extent = max(width, height) * res
    minzoom = max((z for z in range(maxzoom + 1) if TILE * tms.matrix(z).cellSize >= extent), default=0)
    return ZoomRange(minzoom, maxzoom, (west, south, east, north))


def _ground_cell(zooms: ZoomRange, z: int) -> float:
    """Metres on the ground a tile pixel of zoom ``z`` spans at the middle of the map."""
    middle = (zooms.bounds[1] + zooms.bounds[3]) / 2
    return web_mercator().matrix(z).cellSize * math.cos(math.radians(middle))


def _map_cell(geotiff: str | Path) -> float:
    """Metres on the ground a pixel of ``geotiff`` spans (its CRS in metres: the UTM zone)."""
    import rasterio

    with rasterio.open(geotiff) as src:
        return abs(src.transform.a)


def check_tiles_folder(out: str | Path) -> None:
    """A tiles folder can be written: its parent exists and is writable; an existing folder is
    empty or holds tiles mosaic wrote before (its metadata.json), which are replaced."""
    out = Path(out)
    parent = out.parent if str(out.parent) else Path(".")
    if out.exists() and not out.is_dir():
        raise BadInput(f"output {out}/ is a file, not a folder for web tiles")
    if not parent.is_dir():
        raise BadInput(f"output folder {parent} does not exist")
    if not os.access(parent, os.W_OK):
        raise BadInput(f"output folder {parent} is not writable (the tiles are written beside it, then renamed)")
    if out.is_dir() and any(out.iterdir()) and not (out / METADATA).is_file():
        raise BadInput(f"output folder {out}/ holds other files: give an empty or new folder for web tiles")


def _levels(src, zooms: ZoomRange):
    """Per zoom: (z, the tiles over the map, a WarpedVRT on that zoom's tile grid, its origin tile)."""
    from rasterio.enums import Resampling
    from rasterio.transform import Affine
    from rasterio.vrt import WarpedVRT

    tms = web_mercator()
    source_res = None
    for z in range(zooms.minzoom, zooms.maxzoom + 1):
        tiles = list(tms.tiles(*zooms.bounds, zooms=[z]))
        if not tiles:
            continue
        x0, y0 = min(t.x for t in tiles), min(t.y for t in tiles)
        x1, y1 = max(t.x for t in tiles), max(t.y for t in tiles)
        left, _, _, top = tms.xy_bounds(x0, y0, z)
        res = tms.matrix(z).cellSize
        if source_res is None:
            from rasterio.warp import calculate_default_transform

            source_res = abs(calculate_default_transform(src.crs, "EPSG:3857", src.width, src.height, *src.bounds)[0].a)
        resampling = Resampling.bilinear if res < source_res * 1.5 else Resampling.average
        vrt = WarpedVRT(src, crs="EPSG:3857", transform=Affine(res, 0, left, 0, -res, top), width=(x1 - x0 + 1) * TILE,
                        height=(y1 - y0 + 1) * TILE, resampling=resampling)
        yield z, tiles, vrt, (x0, y0)


def render_tiles(geotiff: str | Path, zooms: ZoomRange):
    """Yield (z, x, y, RGBA array H x W x 4) for every tile the map touches (fully transparent
    ones left out)."""
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(geotiff) as src:
        for z, tiles, vrt, (x0, y0) in _levels(src, zooms):
            with vrt:
                for t in tiles:
                    bands = vrt.read(window=Window((t.x - x0) * TILE, (t.y - y0) * TILE, TILE, TILE), boundless=False)
                    if bands.shape[0] == 3:  # a source without alpha: GDAL adds none
                        bands = np.concatenate([bands, np.full_like(bands[:1], 255)])
                    rgba = np.ascontiguousarray(bands[:4].transpose(1, 2, 0))
                    if rgba[..., 3].any():
                        yield z, t.x, t.y, rgba


def encode_png(rgba: np.ndarray) -> bytes:
    import cv2

    ok, data = cv2.imencode(".png", cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
    if not ok:
        raise ProcessingError("OpenCV could not encode a PNG tile")
    return data.tobytes()


def tilejson(zooms: ZoomRange, name: str) -> dict:
    west, south, east, north = zooms.bounds
    centre_zoom = min(zooms.maxzoom, zooms.minzoom + 2)
    return {"tilejson": "3.0.0", "name": name, "scheme": "xyz", "tiles": ["{z}/{x}/{y}.png"], "minzoom": zooms.minzoom,
            "maxzoom": zooms.maxzoom, "bounds": [west, south, east, north], "center": [(west + east) / 2, (south + north) / 2, centre_zoom],
            "format": "png", "attribution": "mosaic"}


def write_tiles(out: str | Path, geotiff: str | Path) -> ZoomRange:
    """XYZ PNG tiles of ``geotiff`` in ``out/{z}/{x}/{y}.png`` with ``out/metadata.json``
    (TileJSON); the folder appears whole (a folder of tiles mosaic wrote before is replaced)."""
    out = Path(out)
    check_tiles_folder(out)
    zooms = zoom_range(geotiff)
    with private_folder(out) as staging:  # renamed onto out once whole, else removed
        for z, x, y, rgba in render_tiles(geotiff, zooms):
            folder = staging / str(z) / str(x)
            folder.mkdir(parents=True, exist_ok=True)
            (folder / f"{y}.png").write_bytes(encode_png(rgba))
        (staging / METADATA).write_text(json.dumps(tilejson(zooms, out.name)) + "\n")
        umask = os.umask(0)
        os.umask(umask)
        for root, dirs, files in os.walk(staging):
            for d in dirs:
                os.chmod(Path(root) / d, 0o777 & ~umask)
            for f in files:
                give_default_permissions(Path(root) / f)
        os.chmod(staging, 0o777 & ~umask)
        _swap_in(staging, out)
    return zooms


def _swap_in(staging: Path, out: Path) -> None:
    """Rename the finished folder onto ``out``; an existing one (empty, or tiles written before)
    is moved aside first and removed after."""
    if not out.exists():
        os.replace(staging, out)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent if str(out.parent) else "."))
    try:
        os.replace(out, old / "tiles")
        os.replace(staging, out)
    finally:
        with contextlib.suppress(OSError):
            shutil.rmtree(old)


def write_pmtiles(out: str | Path, geotiff: str | Path) -> ZoomRange:
    """The XYZ tiles as one PMTiles v3 archive (PNG tiles, clustered: each zoom's tiles in
    tile-id order), written atomically."""
    from pmtiles.tile import Compression, TileType, zxy_to_tileid
    from pmtiles.writer import Writer

    zooms = zoom_range(geotiff)
    west, south, east, north = zooms.bounds
    with atomic_path(out) as tmp, open(tmp, "wb") as f:
        writer = Writer(f)
        level: list[tuple[int, bytes]] = []

        def flush() -> None:
            for tile_id, data in sorted(level, key=lambda item: item[0]):
                writer.write_tile(tile_id, data)
            level.clear()

        current = None
        for z, x, y, rgba in render_tiles(geotiff, zooms):
            if z != current:
                flush()
                current = z
            level.append((zxy_to_tileid(z, x, y), encode_png(rgba)))
        flush()
        e7 = 10_000_000
        header = {"tile_type": TileType.PNG, "tile_compression": Compression.NONE, "min_zoom": zooms.minzoom, "max_zoom": zooms.maxzoom,
                  "min_lon_e7": int(west * e7), "min_lat_e7": int(south * e7), "max_lon_e7": int(east * e7), "max_lat_e7": int(north * e7),
                  "center_zoom": min(zooms.maxzoom, zooms.minzoom + 2), "center_lon_e7": int((west + east) / 2 * e7),
                  "center_lat_e7": int((south + north) / 2 * e7)}
        meta = tilejson(zooms, Path(out).stem)
        writer.finalize(header, {k: v for k, v in meta.items() if k not in ("tilejson", "tiles", "scheme")})
    return zooms


def write_mbtiles(out: str | Path, geotiff: str | Path) -> ZoomRange:
    """The XYZ tiles as one MBTiles 1.3 file (SQLite; PNG tiles, rows numbered from the south as
    the specification asks), written atomically (in a private folder: SQLite keeps its journal
    beside the file)."""
    zooms = zoom_range(geotiff)
    if zooms.maxzoom > MBTILES_DEEPEST:
        zooms = ZoomRange(min(zooms.minzoom, MBTILES_DEEPEST), MBTILES_DEEPEST, zooms.bounds)
        warn(f"{out}: MBTiles kept to zoom {MBTILES_DEEPEST} ({100 * _ground_cell(zooms, MBTILES_DEEPEST):.1f} cm a pixel here), the "
             f"deepest GDAL and QGIS open; the map's own detail ({100 * _map_cell(geotiff):.1f} cm) is kept by .pmtiles, a tiles "
             "folder or .tif")
    west, south, east, north = zooms.bounds
    meta = tilejson(zooms, Path(out).stem)
    metadata = {"name": meta["name"], "format": "png", "type": "overlay", "version": "1.3", "description": meta["name"],
                "attribution": meta["attribution"], "minzoom": str(zooms.minzoom), "maxzoom": str(zooms.maxzoom),
                "bounds": f"{west},{south},{east},{north}", "center": ",".join(str(v) for v in meta["center"])}
    try:
        with atomic_path(out, alone=True) as tmp, contextlib.closing(sqlite3.connect(tmp)) as db:
            db.execute("CREATE TABLE metadata (name TEXT, value TEXT)")
            db.execute("CREATE TABLE tiles (zoom_level INTEGER, tile_column INTEGER, tile_row INTEGER, tile_data BLOB)")
            db.executemany("INSERT INTO metadata VALUES (?, ?)", metadata.items())
            for z, x, y, rgba in render_tiles(geotiff, zooms):
                db.execute("INSERT INTO tiles VALUES (?, ?, ?, ?)", (z, x, (1 << z) - 1 - y, encode_png(rgba)))
            db.execute("CREATE UNIQUE INDEX tile_index ON tiles (zoom_level, tile_column, tile_row)")
            db.commit()
    except sqlite3.Error as exc:  # SQLite's own words: "database or disk is full"
        raise write_failed(out, "the MBTiles", str(exc)) from None
    return zooms

