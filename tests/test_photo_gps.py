"""Geotagged photo folders (issue 51): the metadata read back as written, GPS-guided pairing and
matching, and the map landing where the photos were taken, against the survey's exact truth
(benchmarks/survey.py) and GDAL's reading of the GeoTIFF."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from benchmarks.survey import project_point, score_survey, write_photo, write_survey
from conftest import run_cli
from mosaic_cli.telemetry.photos import PhotoTags, read_photo_tags

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "aerial_sequences"


# -- reading -------------------------------------------------------------------------------
def test_a_drones_exif_and_xmp_are_read_back_as_written(tmp_path):
    rgb = np.full((300, 400, 3), 90, np.uint8)
    path = tmp_path / "south_west.jpg"
    write_photo(path, rgb, -33.8567844, -151.2152967, 58.3, 41.27, -123.4, 70.0, "2026:05:01 10:11:12", pitch=-88.5)
    tags = read_photo_tags(path)
    assert tags.problems == []
    # The references' signs: south and west are negative (EXIF keeps magnitudes and N/S, E/W).
    assert tags.lat == pytest.approx(-33.8567844, abs=1e-7) and tags.lon == pytest.approx(-151.2152967, abs=1e-7)
    assert tags.alt == pytest.approx(58.3) and tags.height == pytest.approx(41.27)
    assert (tags.yaw, tags.pitch, tags.roll) == (pytest.approx(-123.4), pytest.approx(-88.5), pytest.approx(0.0))
    assert (tags.make, tags.model, tags.time) == ("DJI", "FC3411", "2026:05:01 10:11:12")
    # 35 mm-equivalent focal length (an integer in EXIF) -> field of view, by the diagonal's definition
    f35 = Image.open(path).getexif().get_ifd(0x8769)[41989]
    across = 43.2666 * 400 / 500
    assert tags.hfov == pytest.approx(math.degrees(2 * math.atan(across / (2 * f35))), abs=0.01)
    assert abs(tags.hfov - 70.0) < 1.0


def turned_copy(source: Path, target: Path, orientation: int) -> None:
    """``source`` as a camera held turned takes it: its pixels stored turned, with the EXIF
    Orientation that turns them back to be shown, and the gimbal's yaw that of the sensor's top
    edge (the shown top's heading plus the turn, clockwise); its other metadata as it was."""
    import re

    storing = {3: Image.Transpose.ROTATE_180, 6: Image.Transpose.ROTATE_90, 8: Image.Transpose.ROTATE_270}[orientation]
    turn = {3: 180.0, 6: 90.0, 8: 270.0}[orientation]
    with Image.open(source) as image:
        exif = image.getexif()
        exif[0x0112] = orientation
        xmp = re.sub(rb'(YawDegree=")([-+0-9.]+)"', lambda m: m[1] + b"%+.2f\"" % ((float(m[2]) + turn + 180.0) % 360.0 - 180.0),
                     image.info["xmp"])
        image.transpose(storing).save(target, "JPEG", quality=95, exif=exif, xmp=xmp)


def test_a_photo_stored_turned_says_what_the_photo_it_shows_says(tmp_path):
    """A photo stored a quarter or half turn with its EXIF Orientation is the photo it shows: the
    same size, field of view across it and heading of its top edge (OpenCV reads it turned back)."""
    import cv2

    rgb = np.random.default_rng(0).integers(0, 255, (300, 400, 3), np.uint8)
    plain = tmp_path / "plain.jpg"
    write_photo(plain, rgb, 46.5, 6.6, 500.0, 40.0, 30.0, 70.0, "2026:05:01 10:11:12")
    want = read_photo_tags(plain)
    for orientation in (3, 6, 8):
        turned = tmp_path / f"turned_{orientation}.jpg"
        turned_copy(plain, turned, orientation)
        assert cv2.imread(str(turned)).shape == (300, 400, 3)  # shown as the plain one
        tags = read_photo_tags(turned)
        assert tags.orientation == orientation and tags.shown_size == (400, 300)
        assert tags.hfov == pytest.approx(want.hfov, abs=1e-9)
        off = (tags.shown_yaw - want.shown_yaw) % 360.0
        assert min(off, 360.0 - off) < 1e-9
        assert f"400x300 (EXIF orientation {orientation})" in tags.describe()


def test_xmp_written_as_elements_and_partial_or_damaged_metadata_are_told_apart(tmp_path):
    rgb = np.full((200, 300, 3), 120, np.uint8)
    elements = tmp_path / "elements.jpg"
    xmp = ('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
           '<rdf:Description xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"><drone-dji:RelativeAltitude>+35.5'
           '</drone-dji:RelativeAltitude><drone-dji:FlightYawDegree>12.5</drone-dji:FlightYawDegree>'
           '<drone-dji:GimbalPitchDegree>not-a-number</drone-dji:GimbalPitchDegree></rdf:Description></rdf:RDF></x:xmpmeta>')
    Image.fromarray(rgb).save(elements, "JPEG", xmp=xmp.encode())
    tags = read_photo_tags(elements)
    assert tags.height == 35.5 and tags.yaw == 12.5  # the aircraft's yaw where the gimbal's is missing
    assert not tags.has_fix and tags.problems == ["DJI XMP GimbalPitchDegree not a number"]

    partial = tmp_path / "partial.jpg"
    exif = Image.Exif()
    gps = exif.get_ifd(0x8825)
    gps[1], gps[2] = "N", (46.0, 31.0, 0.5)  # a latitude without its longitude
    Image.fromarray(rgb).save(partial, "JPEG", exif=exif)
    assert read_photo_tags(partial).problems == ["GPS position partial or damaged"]

    plain = tmp_path / "plain.png"
    Image.fromarray(rgb).save(plain)
    assert read_photo_tags(plain) == PhotoTags(plain, 300, 200)  # nothing said, nothing wrong


@pytest.fixture(scope="module")
def small_survey(tmp_path_factory):
    """Three geotagged 320x240 photos on one line, written once for the module (a test that
    changes them works on a copy), over the simulator's map of seed 3 (the session makes it once)."""
    from mosaic_cli.simulate import load_map

    return write_survey(tmp_path_factory.mktemp("small_survey") / "photos", rows=1, per_row=3, size=(320, 240), gsd=0.25,
                        map_image=load_map(None, seed=3))


def test_dry_run_prints_what_each_photo_says_and_writes_nothing(small_survey):
    survey = small_survey
    proc = subprocess.run([sys.executable, "-m", "mosaic_cli", "stitch", str(survey.folder), "--dry-run"], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 4
    for name, line in zip(survey.names, lines):
        tags = read_photo_tags(survey.folder / name)
        assert line.startswith(name) and f"{tags.lat:.7f}, {tags.lon:.7f}" in line and f"height {tags.height:.1f} m" in line
    assert lines[-1].startswith("3 photos (DJI FC3411): 3 with GPS, 3 with a yaw, 0 with damaged metadata, one every 2.0 s")
    assert sorted(p.name for p in survey.folder.parent.iterdir()) == ["photos"]
    assert sorted(p.name for p in survey.folder.iterdir()) == sorted(survey.names)


# -- a survey on the map ---------------------------------------------------------------------
@pytest.mark.slow
def test_a_geotagged_survey_lands_on_the_map_better_than_its_gps(tmp_path, capsys):
    """32 photos in 4 lines, GPS off by 2.5 m (RMS), yaw by 2 degrees, heights drifting: every
    photo in the one map, each pair within 2 px of the truth, the map's placement at least 3x
    better than the raw fixes, scale within 1 %, north within 0.5 degrees; the GeoTIFF read by
    GDAL (rasterio) says the same as the transforms."""
    rasterio = pytest.importorskip("rasterio")
    survey = write_survey(tmp_path / "photos", rows=4, per_row=8, size=(640, 480), gsd=0.125, along=22.0, across=34.0, seed=3)
    out, js, feet = tmp_path / "map.tif", tmp_path / "t.json", tmp_path / "f.geojson"
    code, err = run_cli(capsys, "stitch", str(survey.folder), "-o", str(out), "--transforms", str(js), "--footprints", str(feet), "-q")
    assert code == 0 and err == "", err  # one map, nothing set aside
    transforms = json.loads(js.read_text())
    assert sorted(f["index"] for f in transforms["frames"]) == list(range(32))
    placed, raw, scale, north, pairs = score_survey(survey, transforms)
    assert max(pairs) < 2.0, f"pairs off by up to {max(pairs):.2f} px"
    # 3x better than the GPS's noise (2.5 m RMS; the fixes' median error here below)
    assert 3.0 * np.median(placed) <= 2.5, f"map {np.median(placed):.2f} m vs fixes {np.median(raw):.2f} m"
    assert abs(np.median(scale) - 1.0) < 0.01 and abs(np.median(north)) < 0.5

    with rasterio.open(out) as cog:
        assert cog.crs.to_epsg() == survey.epsg and cog.count == 4 and cog.overviews(1)
        to_ground = np.array(cog.transform).reshape(3, 3)
    frame = transforms["frames"][5]
    pano = project_point(np.array(frame["H"]), 100.0, 50.0)
    on_ground = project_point(to_ground, pano[0] + 0.5, pano[1] + 0.5)  # GDAL's pixel corner convention
    assert np.linalg.norm(on_ground - project_point(np.array(frame["map_H"]), 100.0, 50.0)) < 0.5 * transforms["gsd_m"]
    assert len(json.loads(feet.read_text())["features"]) >= 32


@pytest.mark.slow
def test_wrong_missing_and_damaged_metadata_and_another_camera_are_each_said_once_and_every_photo_is_placed(tmp_path, capsys):
    survey = write_survey(tmp_path / "photos", rows=3, per_row=5, size=(640, 480), gsd=0.125, along=22.0, across=34.0, seed=5)
    folder = survey.folder
    from pyproj import Transformer

    to_wgs = Transformer.from_crs(f"EPSG:{survey.epsg}", "EPSG:4326", always_xy=True)

    def rewrite(k: int, fix_shift: tuple[float, float] | None, gps: bool = True, yaw: str | None = None, scale: float = 1.0) -> None:
        path = folder / survey.names[k]
        image = Image.open(path).convert("RGB")
        rgb = np.asarray(image.resize((round(image.width * scale), round(image.height * scale)), Image.Resampling.LANCZOS))
        tags = read_photo_tags(path)
        east, north = survey.fixes[k] + (fix_shift or (0.0, 0.0))
        lon, lat = to_wgs.transform(east, north)
        write_photo(path, rgb, lat if gps else None, lon if gps else None, tags.alt, tags.height, yaw or tags.yaw, tags.hfov,
                    tags.time or "")

    rewrite(3, (200.0, 0.0))  # a GPS glitch: 200 m east
    rewrite(7, None, gps=False)  # no fix
    rewrite(11, None, yaw="+9x.1")  # damaged attitude
    rewrite(13, None, scale=1.25)  # another camera of the same shape (800x600)
    js = tmp_path / "t.json"
    code, err = run_cli(capsys, "stitch", str(folder), "-o", str(tmp_path / "map.tif"), "--transforms", str(js), "-q")
    assert code == 0, err
    warnings = err.strip().splitlines()
    assert len(warnings) == 4, warnings
    assert any(survey.names[3] in w and "far from where" in w and "(2" in w for w in warnings)  # about 200 m
    assert any(w == f"mosaic: warning: 1 of 15 photos have no GPS, placed by their pixels: {survey.names[7]}" for w in warnings)
    assert any(survey.names[11] in w and "GimbalYawDegree, FlightYawDegree not a number" in w for w in warnings)
    assert any(w.endswith(f"1 of 15 photos are not 640x480 like the first (another camera): resized to it, placed by their own pixels: "
                          f"{survey.names[13]} (800x600)") for w in warnings)
    transforms = json.loads(js.read_text())
    assert sorted(f["index"] for f in transforms["frames"]) == list(range(15))
    survey.fixes[3] += (200.0, 0.0)
    placed, raw, _, _, pairs = score_survey(survey, transforms)
    assert max(pairs) < 2.0
    assert placed[3] < 3.0 and placed[7] < 3.0  # placed by their pixels, near the truth


def test_a_folder_without_gps_stitches_as_before_and_a_map_needs_gps(tmp_path, capsys, small_survey):
    survey = small_survey
    folder = tmp_path / "photos"
    folder.mkdir()
    for name in survey.names:  # a copy stripped of the metadata: pixels alone
        path = survey.folder / name
        Image.open(path).convert("RGB").save((folder / name).with_suffix(".png"))
    code, err = run_cli(capsys, "stitch", str(folder), "-o", str(tmp_path / "map.kmz"), "-q")
    assert code == 2 and err.strip().splitlines() == [
        f"mosaic: error: -o {tmp_path / 'map.kmz'} (KMZ) needs GPS (no photo in {folder} has EXIF GPS)"]
    code, err = run_cli(capsys, "stitch", str(folder), "-o", str(tmp_path / "pano.tif"), "-q")
    assert code == 0 and err == "", err


@pytest.mark.slow
@pytest.mark.skipif(not (SHARED / "odm_caliterra").is_dir(), reason="../shared/data is not here")
def test_the_caliterra_folder_lands_where_its_exif_says(tmp_path, capsys):
    """A real geotagged folder (Canon SX260, EXIF GPS, no attitude): every photo in the map, the
    map's photo centres within a consumer GPS's error of their own fixes, and photos 0, 1, 2
    placed within 2 px of a direct full-resolution SIFT registration of each pair (the ruler of
    ``python -m benchmarks stitch photos``; 0-2 was 2.25 px off with a 3-px inlier band)."""
    js = tmp_path / "t.json"
    code, err = run_cli(capsys, "stitch", str(SHARED / "odm_caliterra"), "-o", str(tmp_path / "map.tif"), "--transforms", str(js), "-q")
    assert code == 0, err
    transforms = json.loads(js.read_text())
    assert len(transforms["frames"]) == 7
    from pyproj import Transformer

    to_utm = Transformer.from_crs("EPSG:4326", transforms["crs"], always_xy=True)
    misses = []
    for frame in transforms["frames"]:
        photo = sorted(p for p in (SHARED / "odm_caliterra").iterdir())[frame["index"]]
        tags = read_photo_tags(photo)
        fix = np.array(to_utm.transform(tags.lon, tags.lat))
        misses.append(float(np.linalg.norm(project_point(np.array(frame["map_H"]), (tags.width - 1) / 2, (tags.height_px - 1) / 2) - fix)))
    assert np.median(misses) < 5.0, misses
    from benchmarks.stitch import DirectReference, photo_pairs_gap

    placed = {frame["index"]: np.array(frame["H"]) for frame in transforms["frames"]}
    ruler = DirectReference(sorted(p for p in (SHARED / "odm_caliterra").iterdir()))
    gaps = {(i, j): photo_pairs_gap(np.linalg.inv(placed[j]) @ placed[i], ruler(i, j)) for i, j in [(0, 1), (1, 2), (0, 2)]}
    assert max(gaps.values()) < 2.0, gaps



@pytest.mark.slow
@pytest.mark.skipif(not (SHARED.parent / "aerial_stills" / "deepforest_neon_orthophoto").is_dir(), reason="../shared/data is not here")
def test_a_photo_whose_overlap_is_a_strip_beside_canopy_is_placed_by_its_gps_guided_matches(tmp_path, capsys):
    """Real forest imagery (a NEON orthophoto with a road): the second photo overlaps the first by
    a third of its width, of which only a 12-px strip at its edge is flat ground; elsewhere the
    canopy moves with parallax (a smooth displacement of 20 px RMS), which spoils its matches.
    Without GPS the pair does not register (two panoramas); with the photos' GPS (2.5 m off) and
    yaw (2 degrees off), the guided matching places it within 2 px of the truth."""
    import cv2
    from pyproj import Transformer

    image = cv2.imread(str(SHARED.parent / "aerial_stills" / "deepforest_neon_orthophoto" / "2019_YELL_2_541000_4977000_image_crop.png"))
    ground = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    w, h, shift, strip, x0, y0 = 640, 480, 420, 12, 60, 300
    rng = np.random.default_rng(7)

    def smooth_field() -> np.ndarray:
        f = cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), 12)
        return f / f.std() * 20.0

    dx, dy = smooth_field(), smooth_field()
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    flat = xs < strip
    dx, dy = (cv2.GaussianBlur(np.where(flat, 0, d).astype(np.float32), (0, 0), 3) for d in (dx, dy))
    dx[flat], dy[flat] = 0, 0
    photos = [ground[y0:y0 + h, x0:x0 + w], cv2.remap(ground, xs + x0 + shift + dx, ys + y0 + dy, cv2.INTER_LINEAR)]
    gsd, hfov = 0.1, 60.0
    height = gsd * w / (2 * math.tan(math.radians(hfov) / 2))
    to_wgs = Transformer.from_crs("EPSG:32612", "EPSG:4326", always_xy=True)
    folder = tmp_path / "photos"
    folder.mkdir()
    for k, rgb in enumerate(photos):
        east, north = 541000.0 + (x0 + w / 2 + k * shift) * gsd, 4977000.0 - (y0 + h / 2) * gsd
        east, north = np.array([east, north]) + rng.normal(0, 2.5 / math.sqrt(2), 2)
        lon, lat = to_wgs.transform(east, north)
        write_photo(folder / f"DJI_{k + 1:04d}.JPG", np.ascontiguousarray(rgb), lat, lon, 1500.0, height, rng.normal(0, 2.0), hfov,
                    f"2026:05:01 10:00:{2 * k:02d}")

    code, err = run_cli(capsys, "stitch", str(folder), "-o", str(tmp_path / "plain.png"), "--telemetry", "none", "-q")
    assert code == 0 and "2 panoramas" in err, err  # the pair does not register on its pixels alone
    js = tmp_path / "t.json"
    code, err = run_cli(capsys, "stitch", str(folder), "-o", str(tmp_path / "pano.png"), "--transforms", str(js), "-q")
    assert code == 0 and err == "", err
    frames = {f["index"]: np.array(f["H"]) for f in json.loads(js.read_text())["frames"]}
    assert sorted(frames) == [0, 1]
    placed = np.linalg.inv(frames[0]) @ frames[1]  # photo 2 -> photo 1 pixels
    truth = np.array([[1.0, 0, shift], [0, 1.0, 0], [0, 0, 1.0]])
    error = max(np.linalg.norm(project_point(placed, x, y) - project_point(truth, x, y)) for x, y in [(0, 0), (w - 1, 0), (w - 1, h - 1), (0, h - 1)])
    assert error < 2.0, f"{error:.2f} px"


@pytest.mark.slow
def test_photos_of_other_cameras_are_fitted_into_the_frame_placed_and_drawn_without_the_empty_rest(tmp_path, capsys):
    """A 16:9 camera at twice the size and a portrait photo among a 4:3 survey's photos: each is
    fitted whole into the first's frame, centred (both crops of the survey's own photos, so that
    their fitted frames are exactly the survey's: the truth holds as it is), placed within 2 px,
    the map 3x better than the GPS; the transforms say where each photo lies in its frame, its
    footprint is its own pixels', and the empty rest of its frame is drawn nowhere in the map."""
    import cv2

    rasterio = pytest.importorskip("rasterio")
    survey = write_survey(tmp_path / "photos", rows=3, per_row=4, size=(640, 480), gsd=0.125, along=22.0, across=34.0, seed=7)
    wide, tall = 5, 11  # tall: the last photo, at a corner of the survey, where its empty sides overlap no other photo

    def rewrite(k: int, rgb: np.ndarray, hfov: float) -> None:
        path = survey.folder / survey.names[k]
        tags = read_photo_tags(path)
        write_photo(path, np.ascontiguousarray(rgb), tags.lat, tags.lon, tags.alt, tags.height, tags.yaw, hfov, tags.time or "")

    def pixels(k: int) -> np.ndarray:
        return np.asarray(Image.open(survey.folder / survey.names[k]).convert("RGB"))

    rewrite(wide, cv2.resize(pixels(wide)[60:420], (1280, 720), interpolation=cv2.INTER_CUBIC), 62.0)
    rewrite(tall, pixels(tall)[:, 140:500], math.degrees(2 * math.atan(math.tan(math.radians(31.0)) * 360 / 640)))
    out, js, feet = tmp_path / "map.tif", tmp_path / "t.json", tmp_path / "f.geojson"
    code, err = run_cli(capsys, "stitch", str(survey.folder), "-o", str(out), "--transforms", str(js), "--footprints", str(feet), "-q")
    assert code == 0, err
    assert err.strip().splitlines() == [
        "mosaic: warning: 2 of 12 photos are not 640x480 like the first (another camera): each fitted whole into its frame "
        f"(another shape: the rest left empty), placed by their own pixels: {survey.names[wide]} (1280x720), {survey.names[tall]} (360x480)"]
    transforms = json.loads(js.read_text())
    assert sorted(f["index"] for f in transforms["frames"]) == list(range(12))
    photos = {f["index"]: f["photo"] for f in transforms["frames"] if "photo" in f}
    assert photos == {wide: {"name": survey.names[wide], "size": [1280, 720], "to_frame": [[0.5, 0, 0], [0, 0.5, 60], [0, 0, 1]]},
                      tall: {"name": survey.names[tall], "size": [360, 480], "to_frame": [[1, 0, 140], [0, 1, 0], [0, 0, 1]]}}
    placed, raw, scale, north, pairs = score_survey(survey, transforms)
    assert max(pairs) < 2.0, f"pairs off by up to {max(pairs):.2f} px"
    assert 3.0 * np.median(placed) <= 2.5 and max(placed[wide], placed[tall]) < 1.0, placed

    def area(ring) -> float:
        x, y = np.array(ring).T
        return 0.5 * abs(float(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1))))

    footprints = {f["properties"]["frame"]: area(f["geometry"]["coordinates"][0])
                  for f in json.loads(feet.read_text())["features"] if f["properties"]["kind"] == "footprint"}
    assert footprints[tall] / footprints[0] == pytest.approx(360 / 640, rel=0.03)
    assert footprints[wide] / footprints[0] == pytest.approx(360 / 480, rel=0.03)
    with rasterio.open(out) as cog:
        rgba = cog.read()
    drawn = rgba[3] > 0
    # the survey's ground is never black; the fitted photos' empty sides would be, where drawn
    assert np.count_nonzero(drawn & (rgba[:3].max(axis=0) < 8)) < 1e-4 * np.count_nonzero(drawn)


@pytest.mark.slow
def test_a_survey_whose_first_photo_is_stored_turned_lands_as_the_plain_one(tmp_path, capsys):
    """The first photo of a geotagged survey stored a quarter turn (EXIF Orientation 6): its
    pixels are read as shown, so the folder lands on the map as the plain folder does, against
    the survey's truth.  (Registration places it whatever its metadata says; that its field of
    view and heading are read as shown is the test above's.)"""
    import shutil

    survey = write_survey(tmp_path / "plain", rows=2, per_row=4, size=(640, 480), gsd=0.125, along=22.0, across=34.0, seed=5)
    turned = tmp_path / "turned"
    shutil.copytree(survey.folder, turned)
    turned_copy(survey.folder / survey.names[0], turned / survey.names[0], 6)
    scores = {}
    for name, folder in (("plain", survey.folder), ("turned", turned)):
        js = tmp_path / f"{name}.json"
        code, err = run_cli(capsys, "stitch", str(folder), "-o", str(tmp_path / f"{name}.tif"), "--transforms", str(js), "-q")
        assert code == 0 and err == "", err
        placed, _, scale, north, pairs = score_survey(survey, json.loads(js.read_text()))
        assert max(pairs) < 2.0, name
        scores[name] = np.median(placed), np.median(scale), np.median(north)
    (placed_plain, scale_plain, north_plain), (placed_turned, scale_turned, north_turned) = scores["plain"], scores["turned"]
    assert placed_turned <= 1.1 * placed_plain + 0.05, scores
    assert abs(scale_turned - scale_plain) < 0.002 and abs(north_turned - north_plain) < 0.1, scores


def test_geotagged_photos_that_join_nothing_are_plain_panoramas_each_said_in_one_line(tmp_path, capsys):
    """Two geotagged photos 300 m apart (a real folder, OpenDroneMap's Lewis, shows the same):
    each is a part of one photo, and one GPS fix cannot lay a part on the ground (scale and
    heading need two).  The stitch writes both as plain panoramas, each named in one warning
    line, where it failed ("the telemetry does not cover the video", exit 2)."""
    from conftest import textured_image

    folder = tmp_path / "photos"
    folder.mkdir()
    for k, (seed, lat) in enumerate([(1, 46.5), (2, 46.5027)]):  # 300 m apart: no common ground
        write_photo(folder / f"IMG_{k:04d}.jpg", textured_image(600, 400, seed=seed), lat, 6.6, 500.0, 40.0, 0.0, 70.0, f"2026:05:01 10:11:{12 + 5 * k}")
    out = tmp_path / "pano.png"
    code, err = run_cli(capsys, "stitch", folder, "-o", out, "-q")
    assert code == 0, err
    assert out.is_file() and (tmp_path / "pano-2.png").is_file()
    lines = err.strip().splitlines()
    for name in ("pano.png", "pano-2.png"):
        said = [line for line in lines if f"{name}: its 1 photo gives 1 GPS fix" in line]
        assert len(said) == 1 and said[0].endswith("a plain panorama, not georeferenced"), err
    assert "does not cover" not in err
