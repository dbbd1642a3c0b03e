"""Maps people open (issue 28): the KMZ super-overlay, web tiles (XYZ folder, MBTiles) and the
quick-look page, each read back by an independent reader: a KML parser (zipfile + ElementTree)
for the KMZ, GDAL (rasterio) and morecantile's tile grid for the tiles, headless Chromium for
the page.  The writers are tested on a small synthetic UTM GeoTIFF; `mosaic stitch` end to end
on a short simulated flight."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import zipfile
from pathlib import Path
from xml.etree import ElementTree as ET

import cv2
import numpy as np
import pytest

from tests.conftest import assert_one_line_error, mosaic_run, run_cli

KML = "{http://www.opengis.net/kml/2.2}"
CRS = "EPSG:32632"
ORIGIN = (465_700.0, 5_249_500.0)  # UTM 32N, near Zurich
RES = 0.1


mosaic = mosaic_run  # in this process: none of these tests is about the process itself


@pytest.fixture(scope="module")
def geotiff(tmp_path_factory):
    """A 640 x 420 RGBA map at 10 cm in UTM 32N: a colour gradient with texture, its lower-left
    corner transparent (ground no frame saw)."""
    import rasterio
    from rasterio.enums import ColorInterp
    from rasterio.transform import from_origin

    path = tmp_path_factory.mktemp("maps") / "map.tif"
    h, w = 420, 640
    yy, xx = np.mgrid[0:h, 0:w]
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 3)
    rgba = np.zeros((4, h, w), np.uint8)
    rgba[0] = np.clip(40 + 180 * xx / w, 0, 255)
    rgba[1] = np.clip(200 - 150 * yy / h, 0, 255)
    rgba[2] = np.clip(texture, 0, 255)
    rgba[3] = np.where(xx + (h - yy) < 150, 0, 255)
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=4, dtype="uint8", crs=CRS,
                       transform=from_origin(ORIGIN[0], ORIGIN[1] + h * RES, RES, RES), photometric="RGB", ALPHA="YES",
                       tiled=True, blockxsize=256, blockysize=256) as ds:
        ds.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]
        ds.write(rgba)
    return path


def features(n_track: int = 30) -> dict:
    """A footprints GeoJSON as geo/output.py writes it: two footprints, a GPS track."""
    from pyproj import Transformer

    to_ll = Transformer.from_crs(CRS, "EPSG:4326", always_xy=True)
    feats = []
    for frame, (e, n) in enumerate([(ORIGIN[0] + 20, ORIGIN[1] + 20), (ORIGIN[0] + 40, ORIGIN[1] + 20)]):
        ring = [to_ll.transform(e + dx, n + dy) for dx, dy in ((-10, -8), (10, -8), (10, 8), (-10, 8), (-10, -8))]
        feats.append({"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [ring]},
                      "properties": {"kind": "footprint", "frame": frame * 30, "time": frame * 1.0, "gps": "agrees",
                                     "centre": list(to_ll.transform(e, n))}})
    track = [list(to_ll.transform(ORIGIN[0] + 5 + 2 * i, ORIGIN[1] + 20 + (i % 3))) for i in range(n_track)]
    feats.append({"type": "Feature", "geometry": {"type": "LineString", "coordinates": track},
                  "properties": {"kind": "gps track", "source": "test.SRT"}})
    return {"type": "FeatureCollection", "features": feats}


def wgs84_bounds(geotiff):
    import rasterio
    from rasterio.warp import transform_bounds

    with rasterio.open(geotiff) as ds:
        return transform_bounds(ds.crs, "EPSG:4326", *ds.bounds, densify_pts=21)


def bounds_apart_m(a, b) -> float:
    """The largest distance, metres, between the matching edges of two (west, south, east,
    north) boxes.  GDAL's super-overlay box is its warped raster's, cut to whole pixels of it
    (and written to 6 decimals): within a few of the map's pixels of the exact outline."""
    lat = np.radians((a[1] + a[3]) / 2)
    metres = np.array([111_320 * np.cos(lat), 110_540] * 2)
    return float(np.max(np.abs(np.subtract(a, b)) * metres))


def read_kmz(path: Path) -> tuple[zipfile.ZipFile, ET.Element]:
    z = zipfile.ZipFile(path)
    assert z.namelist()[0] == "doc.kml"
    return z, ET.fromstring(z.read("doc.kml"))


def test_kmz_is_a_region_super_overlay_with_track_and_footprints(geotiff, tmp_path):
    from mosaic_cli.geo.kmz import write_kmz

    out = tmp_path / "site.kmz"
    fc = features()
    write_kmz(out, geotiff, fc)
    z, root = read_kmz(out)
    assert root.find(f"{KML}Document/{KML}name").text == "site"
    link = root.find(f"{KML}Document/{KML}NetworkLink")
    box = link.find(f"{KML}Region/{KML}LatLonAltBox")
    assert link.find(f"{KML}Region/{KML}Lod/{KML}minLodPixels") is not None
    got = [float(box.find(KML + k).text) for k in ("west", "south", "east", "north")]
    assert bounds_apart_m(got, wgs84_bounds(geotiff)) < 4 * RES
    # the pyramid: every linked KML is in the archive, every level's tiles decode
    names = set(z.namelist())
    href = link.find(f"{KML}Link/{KML}href").text
    assert href in names
    child = ET.fromstring(z.read(href))
    assert child.find(f".//{KML}Region/{KML}Lod") is not None and child.find(f".//{KML}GroundOverlay") is not None
    tiles = [n for n in names if n.endswith((".png", ".jpg"))]
    assert len(tiles) > 1 and len({n.split("/")[0] for n in tiles}) > 1  # several levels
    image = cv2.imdecode(np.frombuffer(z.read(tiles[0]), np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.shape[0] > 0
    # the layers: the track's positions as given, a polygon per footprint
    folders = {f.find(f"{KML}name").text: f for f in root.iter(f"{KML}Folder")}
    coords = folders["Flight track"].find(f".//{KML}LineString/{KML}coordinates").text.split()
    track = [f for f in fc["features"] if f["properties"]["kind"] == "gps track"][0]["geometry"]["coordinates"]
    np.testing.assert_allclose([[float(v) for v in c.split(",")[:2]] for c in coords], track, atol=1e-9)
    polygons = folders["Footprints"].findall(f".//{KML}Polygon")
    assert len(polygons) == 2
    assert "frame 30" in [p.text for p in folders["Footprints"].iter(f"{KML}name")]


def test_zoom_range_follows_the_ground_resolution(geotiff):
    from mosaic_cli.geo.tiles import web_mercator, zoom_range

    zooms = zoom_range(geotiff)
    tms = web_mercator()
    lat = (zooms.bounds[1] + zooms.bounds[3]) / 2
    merc_res = RES / np.cos(np.radians(lat))  # the map's 10 cm in Web Mercator metres there
    res = [tms.matrix(z).cellSize for z in range(25)]
    assert res[zooms.maxzoom] <= merc_res < res[zooms.maxzoom - 1]  # the first zoom finer than the map
    span = max(640, 420) * merc_res
    assert 256 * res[zooms.minzoom] >= span > 256 * res[zooms.minzoom + 1]  # the map fits one tile's span, not the next's
    assert 1 <= len(list(tms.tiles(*zooms.bounds, zooms=[zooms.minzoom]))) <= 4


def _reprojected(geotiff, bounds, size=256, resampling="bilinear"):
    """The map warped by GDAL (rasterio.warp.reproject) onto a tile's bounds: the truth."""
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.transform import from_bounds
    from rasterio.warp import reproject

    dst = np.zeros((4, size, size), np.uint8)
    with rasterio.open(geotiff) as ds:
        reproject(rasterio.band(ds, [1, 2, 3, 4]), dst, dst_transform=from_bounds(*bounds, size, size), dst_crs="EPSG:3857",
                  resampling=Resampling[resampling], src_alpha=4, dst_alpha=4)
    return dst.transpose(1, 2, 0)


def test_xyz_folder_tiles_are_the_map_warped_to_their_bounds(geotiff, tmp_path):
    from pyproj import Transformer

    from mosaic_cli.geo.tiles import METADATA, write_tiles

    out = tmp_path / "tiles"
    zooms = write_tiles(out, geotiff)
    meta = json.loads((out / METADATA).read_text())
    assert meta["tiles"] == ["{z}/{x}/{y}.png"] and (meta["minzoom"], meta["maxzoom"]) == (zooms.minzoom, zooms.maxzoom)
    levels = sorted(int(p.name) for p in out.iterdir() if p.is_dir())
    assert levels == list(range(zooms.minzoom, zooms.maxzoom + 1))
    # the deepest level: each tile is GDAL's warp of the map onto the tile's bounds, which are
    # computed here from the XYZ scheme's formula (not morecantile)
    to_merc = Transformer.from_crs("EPSG:4326", "EPSG:3857", always_xy=True)
    half = to_merc.transform(180, 0)[0]
    z, checked = zooms.maxzoom, 0
    for png in sorted((out / str(z)).glob("*/*.png")):
        x, y = int(png.parent.name), int(png.stem)
        size = 2 * half / 2**z
        bounds = (-half + x * size, half - (y + 1) * size, -half + (x + 1) * size, half - y * size)
        tile = cv2.cvtColor(cv2.imread(str(png), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA)
        truth = _reprojected(geotiff, bounds)
        inside = cv2.erode((truth[..., 3] == 255).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        outside = cv2.dilate((truth[..., 3] > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) == 0
        assert (tile[..., 3][inside] == 255).all() and (tile[..., 3][outside] == 0).all()  # transparent off the map
        if inside.sum() > 1000:
            diff = np.abs(tile[..., :3].astype(int) - truth[..., :3].astype(int))[inside]
            assert diff.mean() < 2.0 and np.percentile(diff, 99) <= 8, (png, diff.mean())
            checked += 1
    assert checked >= 2
    # the shallowest level: the map averaged down (the whole map in one to four tiles)
    z = zooms.minzoom
    for png in sorted((out / str(z)).glob("*/*.png")):
        x, y = int(png.parent.name), int(png.stem)
        size = 2 * half / 2**z
        bounds = (-half + x * size, half - (y + 1) * size, -half + (x + 1) * size, half - y * size)
        tile = cv2.cvtColor(cv2.imread(str(png), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA)
        truth = _reprojected(geotiff, bounds, resampling="average")
        inside = cv2.erode((truth[..., 3] == 255).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        if inside.sum() > 100:
            assert np.abs(tile[..., :3].astype(int) - truth[..., :3].astype(int))[inside].mean() < 3.0
            checked += 1
    assert checked >= 3


def test_mbtiles_by_gdal_reads_back_in_web_mercator(geotiff, tmp_path):
    import sqlite3

    import rasterio
    from rasterio.warp import transform_bounds

    from mosaic_cli.geo.tiles import write_mbtiles

    out = tmp_path / "site.mbtiles"
    zooms = write_mbtiles(out, geotiff)
    with rasterio.open(out) as ds:
        assert ds.crs.to_epsg() == 3857 and ds.count == 4
        assert len(ds.overviews(1)) == zooms.maxzoom - zooms.minzoom
        got = transform_bounds(ds.crs, "EPSG:4326", *ds.bounds)
    west, south, east, north = wgs84_bounds(geotiff)
    # GDAL's MBTiles dataset is cut to whole pixels of the deepest zoom: within one of them (15 cm)
    assert got == pytest.approx((west, south, east, north), abs=3e-6)
    with sqlite3.connect(out) as db:
        meta = dict(db.execute("SELECT name, value FROM metadata"))
        assert meta["name"] == "site" and (int(meta["minzoom"]), int(meta["maxzoom"])) == (zooms.minzoom, zooms.maxzoom)
        assert db.execute("SELECT COUNT(*) FROM tiles WHERE zoom_level = ?", (zooms.minzoom,)).fetchone()[0] >= 1


def test_mbtiles_of_a_map_finer_than_zoom_22_opens_in_gdal_and_says_what_it_kept(geotiff, tmp_path, capsys):
    """GDAL's MBTiles driver (QGIS's) opens zooms up to 22 only (about 3 cm a pixel): a 1-cm map
    (a drone's at 40 m) is tiled to zoom 22, which GDAL opens, and one warning line says so."""
    import shutil

    import rasterio
    from rasterio.transform import from_origin

    from mosaic_cli.geo.tiles import MBTILES_DEEPEST, write_mbtiles, zoom_range

    fine = tmp_path / "fine.tif"
    shutil.copy(geotiff, fine)
    with rasterio.open(fine, "r+") as ds:
        ds.transform = from_origin(ORIGIN[0], ORIGIN[1] + ds.height * 0.01, 0.01, 0.01)
    assert zoom_range(fine).maxzoom > MBTILES_DEEPEST  # the map's own detail needs deeper zooms
    out = tmp_path / "fine.mbtiles"
    zooms = write_mbtiles(out, fine)
    assert zooms.maxzoom == MBTILES_DEEPEST
    with rasterio.open(out) as ds:
        assert ds.crs.to_epsg() == 3857 and len(ds.overviews(1)) == zooms.maxzoom - zooms.minzoom
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"mosaic: warning: {out}: MBTiles kept to zoom 22") and ".pmtiles" in err and "\n" not in err, err


def test_pmtiles_archive_holds_the_same_tiles(geotiff, tmp_path):
    from pmtiles.reader import MmapSource, Reader
    from pmtiles.tile import TileType

    from mosaic_cli.geo.tiles import write_pmtiles, write_tiles

    out = tmp_path / "site.pmtiles"
    zooms = write_pmtiles(out, geotiff)
    write_tiles(tmp_path / "tiles", geotiff)
    with open(out, "rb") as f:
        reader = Reader(MmapSource(f))
        header = reader.header()
        assert header["tile_type"] == TileType.PNG and (header["min_zoom"], header["max_zoom"]) == (zooms.minzoom, zooms.maxzoom)
        west, south, east, north = wgs84_bounds(geotiff)
        assert header["min_lon_e7"] / 1e7 == pytest.approx(west, abs=1e-6) and header["max_lat_e7"] / 1e7 == pytest.approx(north, abs=1e-6)
        pngs = sorted((tmp_path / "tiles").glob("*/*/*.png"))
        for png in pngs:
            z, x, y = int(png.parent.parent.name), int(png.parent.name), int(png.stem)
            assert reader.get(z, x, y) == png.read_bytes()  # every tile of the folder, the same bytes
        assert reader.get(zooms.maxzoom + 1, 0, 0) is None
        assert reader.metadata()["name"] == "site"


def test_tiles_folder_replaces_its_own_tiles_but_not_other_files(tmp_path, capsys):
    from mosaic_cli.errors import BadInput
    from mosaic_cli.geo.tiles import check_tiles_folder
    from mosaic_cli.stitch.output import check_outputs, numbered, output_format

    assert output_format(f"{tmp_path}/new/") == "tiles" and output_format(tmp_path) == "tiles"
    assert output_format(tmp_path / "m.kmz") == "kmz" and output_format(tmp_path / "m.mbtiles") == "mbtiles"
    assert str(numbered("tiles/", 1)) == "tiles-2/" and str(numbered("tiles/", 0)) == "tiles/"
    check_outputs(f"{tmp_path}/new/", None, None)  # a new folder
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "metadata.json").write_text("{}")
    check_tiles_folder(tmp_path / "old")  # tiles written before: replaced
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(BadInput, match="holds other files"):
        check_outputs(tmp_path / "other", None, None)
    with pytest.raises(BadInput, match="does not exist"):
        check_outputs(f"{tmp_path}/missing/deeper/", None, None)


# --- mosaic stitch end to end ---------------------------------------------------------------


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    d = tmp_path_factory.mktemp("mapflight")
    video = d / "flight.mp4"
    mosaic("simulate", "-o", video, "-p", "survey", "-n", "90", "--size", "320x180", "--preset", "ultrafast", "-q",
           "--seed", "2", "--telemetry", "srt", "--gps-noise", "0", "--gps-dropouts", "0.03", "--gsd", "0.05")
    return video


def srt_positions(path: Path) -> np.ndarray:
    """(lon, lat) of every cue of a DJI SRT with a fix (0, 0: none), read with a regular expression."""
    text = path.read_text()
    lat = [float(v) for v in re.findall(r"\[latitude\s*:\s*([-\d.]+)\]", text)]
    lon = [float(v) for v in re.findall(r"\[long?t?itude\s*:\s*([-\d.]+)\]", text)]
    return np.array([(x, y) for x, y in zip(lon, lat) if (x, y) != (0.0, 0.0)])


@pytest.mark.slow
def test_stitch_writes_kmz_tiles_and_html(flight, tmp_path):
    import rasterio

    srt = flight.with_suffix(".SRT")
    kmz, html, tif = tmp_path / "map.kmz", tmp_path / "q.html", tmp_path / "map.tif"
    mosaic("stitch", flight, "--telemetry", srt, "-o", kmz, "--html", html, "-q")
    mosaic("stitch", flight, "--telemetry", srt, "-o", tif, "-q")
    _, root = read_kmz(kmz)
    box = root.find(f"{KML}Document/{KML}NetworkLink/{KML}Region/{KML}LatLonAltBox")
    got = [float(box.find(KML + k).text) for k in ("west", "south", "east", "north")]
    with rasterio.open(tif) as ds:
        gsd = ds.res[0]
    assert bounds_apart_m(got, wgs84_bounds(tif)) < 4 * gsd  # the same map as the COG, where the COG is
    folders = {f.find(f"{KML}name").text: f for f in root.iter(f"{KML}Folder")}
    coords = folders["Flight track"].find(f".//{KML}LineString/{KML}coordinates").text.split()
    track = np.array([[float(v) for v in c.split(",")[:2]] for c in coords])
    truth = srt_positions(srt)
    assert len(truth) < 90  # some cues without a fix: left out of the track
    np.testing.assert_allclose(track, truth, atol=1e-7)  # the telemetry's positions, every fix (none an outlier here)
    assert html.stat().st_size > 10_000 and "L.imageOverlay" in html.read_text()
    if CHROMIUM is not None:  # the page of a real stitch loads without an error
        dom = chromium("--dump-dom", html.resolve().as_uri())
        body = re.search(r"<body[^>]*>", dom.stdout).group(0)
        assert 'data-ready="1"' in body and "data-errors" not in body and not page_console(dom.stderr), (body, page_console(dom.stderr))
    tiles = tmp_path / "tiles"
    mosaic("stitch", flight, "--telemetry", srt, "-o", f"{tiles}/", "-q")
    meta = json.loads((tiles / "metadata.json").read_text())
    assert meta["bounds"] == pytest.approx(list(wgs84_bounds(tif)), abs=1e-9)
    assert list((tiles / str(meta["maxzoom"])).glob("*/*.png"))
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left behind


@pytest.mark.slow
@pytest.mark.parametrize("args", [["-o", "m.kmz"], ["-o", "m.mbtiles"], ["-o", "m.pmtiles"], ["-o", "tiles/"], ["-o", "m.png", "--html", "q.html"]])
@pytest.mark.parametrize("telemetry", [None, "none"])
def test_map_outputs_without_telemetry_are_one_line_before_any_work(capsys, tmp_path, monkeypatch, args, telemetry, plain_video):
    monkeypatch.chdir(tmp_path)
    extra = ["--telemetry", "none"] if telemetry else []
    code, err = run_cli(capsys, "stitch", plain_video, *args, *extra, "-q", "--estimator", "orb")
    assert_one_line_error(code, err, "needs telemetry")
    assert not list(tmp_path.iterdir())


@pytest.fixture(scope="module")
def plain_video(plain_160x90):
    return plain_160x90  # (conftest: test_georef's too)


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


def chromium(*args: str) -> subprocess.CompletedProcess:
    """Debian's chromium, headless, on a page from disk (no sandbox: tests may run as root)."""
    command = [CHROMIUM, "--headless=new", "--disable-gpu", "--no-sandbox", "--hide-scrollbars", "--force-device-scale-factor=1",
               "--window-size=1000,700", "--virtual-time-budget=5000", "--enable-logging=stderr", "--v=0", *args]
    return subprocess.run(command, capture_output=True, text=True, timeout=120)


def page_console(stderr: str) -> list[str]:
    """What the page said on its console (chromium's own warnings left out)."""
    return [line for line in stderr.splitlines() if "CONSOLE" in line or "Uncaught" in line]


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="needs chromium (apt-get install chromium)")
def test_quicklook_page_draws_the_map_where_it_belongs_in_a_browser(geotiff, tmp_path):
    from pyproj import Transformer

    from mosaic_cli.geo.quicklook import write_quicklook

    page = tmp_path / "quick look.html"
    fc = features()
    dropped_at = Transformer.from_crs(CRS, "EPSG:4326", always_xy=True).transform(ORIGIN[0] + 50, ORIGIN[1] + 32)
    fc["features"].append({"type": "Feature", "geometry": {"type": "Point", "coordinates": list(dropped_at)},
                           "properties": {"kind": "dropped gps fix", "sample": 7, "time": 0.7, "source": "test.SRT"}})
    write_quicklook(page, geotiff, fc, title="site")
    text = page.read_text()
    assert not re.search(r"<(script|link|img)\b[^>]*\b(src|href)=", text)  # one file: nothing loaded from beside it or online
    assert "BSD 2-Clause License" in text  # Leaflet's licence travels with it
    url = page.resolve().as_uri()
    dom = chromium("--dump-dom", url)
    assert dom.returncode == 0, dom.stderr[-2000:]
    body = re.search(r"<body[^>]*>", dom.stdout).group(0)  # the page's script marks its <body> when done, and on an error
    assert 'data-ready="1"' in body and "data-errors" not in body, body
    assert not page_console(dom.stderr), page_console(dom.stderr)
    shot = tmp_path / "shot.png"
    run = chromium(f"--screenshot={shot}", url)
    assert run.returncode == 0 and shot.exists(), run.stderr[-2000:]
    assert not page_console(run.stderr), page_console(run.stderr)
    image = cv2.cvtColor(cv2.imread(str(shot)), cv2.COLOR_BGR2RGB).astype(int)
    assert image.shape[:2] == (700, 1000)

    background = np.array([221, 221, 221])  # the page's grey

    def off_map(pixels: np.ndarray) -> np.ndarray:
        return np.abs(pixels - background).max(axis=-1) <= 3

    # where the map is drawn: across the middle row and column, from the page's grey to it and back
    row, column = ~off_map(image[350]), ~off_map(image[:, 500])
    x0, x1 = np.argmax(row), len(row) - np.argmax(row[::-1])
    y0, y1 = np.argmax(column), len(column) - np.argmax(column[::-1])
    from rasterio.warp import transform_bounds

    west, south, east, north = wgs84_bounds(geotiff)
    left, bottom, right, top = transform_bounds("EPSG:4326", "EPSG:3857", west, south, east, north)
    assert (x1 - x0) / (y1 - y0) == pytest.approx((right - left) / (top - bottom), rel=0.02)  # its shape in Web Mercator
    assert (x0 + x1) / 2 == pytest.approx(500, abs=3) and (y0 + y1) / 2 == pytest.approx(350, abs=3)  # fitted: centred
    assert x1 - x0 > 500

    def at(u: float, v: float) -> np.ndarray:
        """The screenshot's median colour around the map's point (u, v) (fractions of its width, height from the top)."""
        x, y = round(x0 + u * (x1 - x0)), round(y0 + v * (y1 - y0))
        return np.median(image[y - 3:y + 4, x - 3:x + 4].reshape(-1, 3), axis=0)

    for u, v in ((0.5, 0.85), (0.9, 0.5), (0.3, 0.9)):  # away from the footprints and the track
        expected = (40 + 180 * u, 200 - 150 * v)  # the synthetic map's red and green there
        assert np.abs(at(u, v)[:2] - expected).max() < 20, (u, v, at(u, v), expected)
    assert off_map(at(0.03, 0.97)[None])[0]  # the map's transparent corner shows the page
    # the track is drawn on the map where it is on the ground: its first fix, 5 m east and 20 m north of the corner
    x, y = round(x0 + 5 / 64 * (x1 - x0)), round(y0 + (1 - 20 / 42) * (y1 - y0))
    red = image[y - 2:y + 3, x - 2:x + 3].reshape(-1, 3)
    assert ((red[:, 0] > 180) & (red[:, 1] < 80) & (red[:, 2] < 100)).any(), red
    # a dropped fix: a magenta dot of its own where it is (50 m east, 32 m north of the corner)
    x, y = round(x0 + 50 / 64 * (x1 - x0)), round(y0 + (1 - 32 / 42) * (y1 - y0))
    dot = image[y - 2:y + 3, x - 2:x + 3].reshape(-1, 3)
    assert ((dot[:, 0] > 200) & (dot[:, 1] < 120) & (dot[:, 2] > 200)).sum() >= 9, dot


# -- GPS fixes dropped as outliers: drawn apart, never joined into the track (issue 40) ------------

SPIKES = (12, 25, 26)  # the fixes 40-60 m off the line


def spiky_collection() -> tuple[dict, np.ndarray, np.ndarray]:
    """The footprints GeoJSON (geo/output.py's) of a track along the synthetic map, one fix a
    frame, with three far-off fixes (two in a row) that alignment drops as outliers; and the
    (lon, lat) of the fixes kept and of those dropped."""
    from types import SimpleNamespace

    from mosaic_cli.geo.crs import Projection
    from mosaic_cli.geo.output import footprint_collection
    from mosaic_cli.telemetry import align_to_frames
    from mosaic_cli.telemetry.flight_log import FlightLog

    n = 40
    east = ORIGIN[0] + 5 + 1.5 * np.arange(n)
    north = ORIGIN[1] + 20 + 0.3 * np.sin(np.arange(n))
    for i, (de, dn) in zip(SPIKES, ((0, 45), (-30, -50), (-28, -52))):
        east[i], north[i] = east[i] + de, north[i] + dn
    projection = Projection(CRS)
    lonlat = projection.to_wgs84(east, north)
    nan = np.full(n, np.nan)
    track = FlightLog("spiky.SRT", np.arange(n) / 10.0, lonlat[:, 1], lonlat[:, 0], nan, nan, nan, nan, nan, nan)
    aligned = align_to_frames(track, np.arange(n) / 10.0)
    assert aligned.outliers == len(SPIKES)
    georef = SimpleNamespace(projection=projection, frame_indices=[], used=np.zeros(0, bool), telemetry=aligned, track=track)
    fc = footprint_collection(georef, [], (640, 360), 10.0)
    dropped = np.isin(np.arange(n), SPIKES)
    return fc, lonlat[~dropped], lonlat[dropped]


def test_dropped_fixes_are_points_apart_from_the_track_line():
    fc, kept, dropped = spiky_collection()
    (track,) = [f for f in fc["features"] if f["properties"]["kind"] == "gps track"]
    assert track["geometry"]["type"] == "LineString"
    np.testing.assert_allclose(track["geometry"]["coordinates"], kept, rtol=0, atol=1e-8)  # every kept fix, none dropped
    points = [f for f in fc["features"] if f["properties"]["kind"] == "dropped gps fix"]
    assert [f["geometry"]["type"] for f in points] == ["Point"] * len(SPIKES)
    assert [f["properties"]["sample"] for f in points] == list(SPIKES)
    np.testing.assert_allclose([f["geometry"]["coordinates"] for f in points], dropped, rtol=0, atol=1e-8)


LEAFLET_STUB = r"""
const fs = require("fs");
const data = fs.readFileSync(process.argv[2], "utf8"), script = fs.readFileSync(process.argv[3], "utf8");
function layer(o) { o.addTo = () => o; o.bindPopup = () => o; return o; }
let overlays = null;
global.window = {addEventListener() {}};
global.document = {getElementById: () => ({textContent: data}), body: {setAttribute(k, v) { if (k === "data-errors") throw new Error(v); }}};
global.L = {
  map: () => layer({on() {}, fitBounds() {}}),
  tileLayer: () => layer({type: "tiles"}),
  imageOverlay: () => layer({type: "image"}),
  layerGroup: (items) => layer({type: "group", items: items || []}),
  circleMarker: (latlng, options) => layer({type: "marker", latlng, options}),
  geoJSON: (fc, options) => {
    fc.features.forEach((f) => options.onEachFeature && options.onEachFeature(f, layer({})));
    return layer({type: "geojson", features: fc.features, styles: fc.features.map((f) => options.style ? options.style(f) : null)});
  },
  control: {layers: (base, over) => { overlays = over; return layer({}); }, scale: () => layer({})},
  Control: {extend: () => function () { return layer({}); }},
  DomUtil: {create: () => ({})},
  popup: () => layer({setLatLng() { return this; }, setContent() { return this; }, openOn() { return this; }}),
};
eval(script);
process.stdout.write(JSON.stringify(overlays));
"""


def page_layers(page: Path, tmp_path: Path) -> dict:
    """The quick-look page's script run in node against a stand-in for Leaflet: the overlays of
    its layers control (the legend), by their labels, as the script made them."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("needs node")
    text = page.read_text()
    data = re.search(r'<script type="application/json" id="mosaic-data">(.*?)</script>', text, re.S).group(1)
    script = re.findall(r"<script>\n(.*?)\n</script>", text, re.S)[-1]
    paths = [tmp_path / "data.json", tmp_path / "script.js", tmp_path / "stub.js"]
    for path, content in zip(paths, (data.replace("<\\/", "</"), script.replace("<\\/", "</"), LEAFLET_STUB)):
        path.write_text(content)
    run = subprocess.run([node, str(paths[2]), str(paths[0]), str(paths[1])], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


def test_quicklook_draws_dropped_fixes_in_a_layer_and_colour_of_their_own(geotiff, tmp_path):
    from mosaic_cli.geo.quicklook import write_quicklook

    fc, kept, dropped = spiky_collection()
    page = tmp_path / "q.html"
    write_quicklook(page, geotiff, fc, title="site")
    overlays = page_layers(page, tmp_path)
    (track_label,) = [k for k in overlays if "GPS track" in k]
    (dropped_label,) = [k for k in overlays if "dropped" in k.lower()]
    track, points = overlays[track_label], overlays[dropped_label]
    # the track's line: every kept fix, not one dropped
    lines = [f["geometry"]["coordinates"] for f in track["features"]]
    assert [f["geometry"]["type"] for f in track["features"]] == ["LineString"]
    np.testing.assert_allclose(lines[0], kept, rtol=0, atol=1e-8)
    assert not any(np.allclose(v, d, rtol=0, atol=1e-8) for v in lines[0] for d in dropped)
    # the dropped fixes: markers of their own, where they are, in a colour that is not the track's
    assert points["type"] == "group" and all(m["type"] == "marker" for m in points["items"])
    np.testing.assert_allclose([m["latlng"][::-1] for m in points["items"]], dropped, rtol=0, atol=1e-8)
    fill = {m["options"]["fillColor"] for m in points["items"]}
    assert len(fill) == 1 and fill != {track["styles"][0]["color"]}
    # the legend names them, with their count and their colour
    assert "(3)" in dropped_label and f"background:{fill.pop()}" in dropped_label
    assert f"background:{track['styles'][0]['color']}" in track_label

    # a track without outliers has no such legend entry
    fc["features"] = [f for f in fc["features"] if f["properties"]["kind"] != "dropped gps fix"]
    write_quicklook(page, geotiff, fc, title="site")
    assert not [k for k in page_layers(page, tmp_path) if "dropped" in k.lower()]


def test_kmz_puts_dropped_fixes_in_a_folder_of_their_own(geotiff, tmp_path):
    from mosaic_cli.geo.kmz import write_kmz

    fc, kept, dropped = spiky_collection()
    out = tmp_path / "site.kmz"
    write_kmz(out, geotiff, fc)
    _, root = read_kmz(out)
    folders = {f.find(f"{KML}name").text: f for f in root.iter(f"{KML}Folder")}
    coords = folders["Flight track"].find(f".//{KML}LineString/{KML}coordinates").text.split()
    np.testing.assert_allclose([[float(v) for v in c.split(",")[:2]] for c in coords], kept, rtol=0, atol=1e-8)
    points = folders["GPS fixes dropped as outliers (3)"].findall(f".//{KML}Point/{KML}coordinates")
    np.testing.assert_allclose([[float(v) for v in p.text.split(",")[:2]] for p in points], dropped, rtol=0, atol=1e-8)
