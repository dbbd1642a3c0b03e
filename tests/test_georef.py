"""Georeferenced stitching: the robust fit, the camera model, and ``mosaic stitch --telemetry``
end to end against the simulator's exact truth (COG, CRS, bounds, footprints, map homographies)."""

from __future__ import annotations

import json
import math
import subprocess

import numpy as np
import pytest

from mosaic_cli.geo.camera import focal_pixels, intrinsics, nadir_pixel, tilt_rotation, untilt
from mosaic_cli.geo.fit import SimilarityPrior, fit_similarity
from mosaic_cli.geo.score import score_files
from mosaic_cli.geometry import project
from mosaic_cli.simulate import load_ground_truth
from tests.conftest import FFMPEG, assert_one_line_error, mosaic_run, run_cli


def similarity(scale, angle, tx, ty):
    c, s = scale * math.cos(angle), scale * math.sin(angle)
    return np.array([[c, -s, tx], [s, c, ty], [0, 0, 1.0]])


def test_fit_ignores_bad_fixes_and_averages_noise():
    rng = np.random.default_rng(4)
    src = rng.uniform(0, 4000, (120, 2))
    M = similarity(0.05, 0.7, 465_000.0, -5_249_000.0)
    dst = project(M, src) + rng.normal(0, 2.0, (120, 2))
    bad = rng.choice(120, 8, replace=False)
    dst[bad] += rng.uniform(30, 80, (8, 2))
    fit = fit_similarity(src, dst)
    assert set(np.nonzero(~fit.inliers)[0]) == set(bad)
    assert fit.scale == pytest.approx(0.05, rel=0.01)
    assert fit.rotation == pytest.approx(0.7, abs=math.radians(0.3))
    centre = src.mean(0)[None]
    assert np.linalg.norm(project(fit.matrix, centre) - project(M, centre)) < 0.8
    plain = np.linalg.lstsq(np.c_[src, np.ones(120)], dst, rcond=None)[0]  # what bad fixes do to least squares
    assert np.linalg.norm(np.c_[centre, [[1]]] @ plain - project(M, centre)) > 2 * np.linalg.norm(project(fit.matrix, centre) - project(M, centre))


def test_fit_prior_fixes_a_hovering_track():
    rng = np.random.default_rng(5)
    src = rng.uniform(0, 40, (30, 2))  # 2 m of ground: GPS noise alone says nothing about rotation
    M = similarity(0.05, -1.2, 1000.0, 2000.0)
    dst = project(M, src) + rng.normal(0, 2.0, (30, 2))
    fit = fit_similarity(src, dst, SimilarityPrior(0.051, -1.2 + math.radians(2), 0.1))
    assert fit.scale == pytest.approx(0.051, rel=0.02)
    assert fit.rotation == pytest.approx(-1.2 + math.radians(2), abs=math.radians(1))


def test_untilt_makes_a_tilted_view_of_the_ground_a_similarity():
    size, hfov = (640, 360), 70.0
    f = focal_pixels(size[0], hfov)
    K = intrinsics(size, f)
    R = tilt_rotation(-84.0, 3.0)
    ground_to_frame = K @ R @ np.array([[1, 0, -5], [0, 1, 7], [0, 0, 40.0]])  # camera 40 units up
    flat = untilt(size, f, -84.0, 3.0) @ ground_to_frame
    flat /= flat[2, 2]
    assert abs(flat[2, 0]) < 1e-12 and abs(flat[2, 1]) < 1e-12  # affine ...
    np.testing.assert_allclose(flat[:2, :2] / flat[0, 0], np.eye(2), atol=1e-12)  # ... and a similarity
    below = project(ground_to_frame, np.array([[5.0, -7.0]]))[0]
    np.testing.assert_allclose(below, nadir_pixel(size, f, -84.0, 3.0), atol=1e-9)
    # -84: tilted toward the frame's top, so the point below shows under the centre
    assert below[1] > (size[1] - 1) / 2


mosaic = mosaic_run  # in this process: none of these tests is about the process itself


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    d = tmp_path_factory.mktemp("georef")
    out = {}
    for name, noise in (("exact", "0"), ("noisy", "3")):
        video = d / f"{name}.mp4"
        mosaic("simulate", "-o", video, "-p", "survey", "-n", "150", "--size", "320x180", "--preset", "ultrafast", "-q",
               "--seed", "2", "--telemetry", "srt", "--gps-noise", noise, "--gps-dropouts", "0.02" if name == "noisy" else "0",
               "--baro-bias", "0.5" if name == "noisy" else "0",
               "--gsd", "0.05")
        out[name] = video
    return out


@pytest.mark.slow
def test_stitch_with_exact_telemetry_lands_where_the_truth_is(flights, tmp_path):
    """Without GPS error the whole chain (SRT, UTM, tilt, fit, COG) must land within centimetres."""
    video = flights["exact"]
    tif, tr, fp = tmp_path / "map.tif", tmp_path / "t.json", tmp_path / "f.geojson"
    mosaic("stitch", video, "--telemetry", video.with_suffix(".SRT"), "-o", tif, "--transforms", tr, "--footprints", fp, "-q")
    gt = load_ground_truth(video)
    score = score_files(tr, gt, video.with_name("exact.geo.json"))
    frame_gsd = json.loads(tr.read_text())["gsd_m"]
    assert score.median_m < 2 * frame_gsd and score.max_m < 8 * frame_gsd, score
    assert abs(score.scale_error) < 0.005 and abs(score.heading_error_deg) < 0.3, score

    import rasterio
    from rio_cogeo.cogeo import cog_validate

    valid, errors, _ = cog_validate(str(tif), quiet=True)
    assert valid, errors
    truth = json.loads(video.with_name("exact.geo.json").read_text())
    with rasterio.open(tif) as ds:
        assert ds.crs.to_epsg() == int(truth["crs"].split(":")[1])
        assert ds.count == 4 and ds.colorinterp[3].name == "alpha" and ds.overviews(1)
        assert ds.block_shapes[0] == (512, 512)
        bounds = ds.bounds
        alpha = ds.read(4)
        # every true ground position of every frame's centre lies inside the map and is covered
        M = np.array(truth["map_to_crs"])
        w, h = gt.size
        for t in range(0, gt.frames, 10):
            east, north = project(M @ np.linalg.inv(gt.map_to_frame[t]), np.array([[(w - 1) / 2, (h - 1) / 2]]))[0]
            assert bounds.left < east < bounds.right and bounds.bottom < north < bounds.top
            row, col = ds.index(east, north)
            assert alpha[row, col] == 255

    data = json.loads(tr.read_text())
    assert data["crs"] == truth["crs"] and all("map_H" in f for f in data["frames"])
    geo = json.loads(fp.read_text())
    kinds = [f["properties"]["kind"] for f in geo["features"]]
    assert kinds.count("footprint") == len(data["frames"]) and "gps track" in kinds
    lon, lat = geo["features"][0]["geometry"]["coordinates"][0][0]
    assert abs(lat - 47.3977) < 0.01 and abs(lon - 8.5456) < 0.01  # WGS84, lon/lat order, near the origin


@pytest.mark.slow
def test_the_dji_log_beside_a_video_is_its_telemetry(flights, tmp_path):
    """DJI_0001.MP4 with DJI_0001.srt beside it (either case): the same map as with --telemetry
    naming it; --telemetry none keeps the panorama plain."""
    import shutil

    video, log = tmp_path / "DJI_0001.MP4", tmp_path / "DJI_0001.srt"
    shutil.copy(flights["exact"], video)
    shutil.copy(flights["exact"].with_suffix(".SRT"), log)
    found, given, plain = tmp_path / "found.json", tmp_path / "given.json", tmp_path / "plain.json"
    mosaic("stitch", video, "-o", tmp_path / "found.tif", "--transforms", found, "-q", "--estimator", "orb")
    mosaic("stitch", video, "--telemetry", log, "-o", tmp_path / "given.tif", "--transforms", given, "-q", "--estimator", "orb")
    mosaic("stitch", video, "--telemetry", "none", "-o", tmp_path / "plain.png", "--transforms", plain, "-q", "--estimator", "orb")
    found_js, given_js = json.loads(found.read_text()), json.loads(given.read_text())
    assert "crs" in found_js and found_js["frames"] == given_js["frames"] and found_js["crs"] == given_js["crs"]
    assert "crs" not in json.loads(plain.read_text())


@pytest.mark.slow
def test_subtitles_beside_a_video_that_are_no_flight_log(capsys, tmp_path, plain_160x90):
    """Captions beside a video (an .srt with no GPS): a panorama is made as without them; a map
    asked for is refused in one line that names them."""
    import shutil

    video = tmp_path / "clip.mp4"
    shutil.copy(plain_160x90, video)
    video.with_suffix(".srt").write_text("1\n00:00:00,000 --> 00:00:01,000\nHello from the beach\n\n")
    code, err = run_cli(capsys, "stitch", video, "-o", tmp_path / "p.png", "-q", "--estimator", "orb")
    assert code == 0 and (tmp_path / "p.png").exists(), err
    code, err = run_cli(capsys, "stitch", video, "-o", tmp_path / "m.tif", "--footprints", tmp_path / "f.geojson", "-q", "--estimator", "orb")
    assert_one_line_error(code, err, "clip.srt", "no GPS telemetry")
    assert not (tmp_path / "m.tif").exists()


@pytest.mark.slow
def test_stitch_with_noisy_gps_keeps_shape_and_place(flights, tmp_path):
    video = flights["noisy"]
    tr = tmp_path / "t.json"
    run = mosaic("stitch", video, "--telemetry", video.with_suffix(".SRT"), "-o", tmp_path / "m.tif", "--transforms", tr)
    assert "georeferenced in EPSG:32632" in run.stdout + run.stderr
    score = score_files(tr, load_ground_truth(video), video.with_name("noisy.geo.json"))
    # a 5-second flight: the GPS error (3 m RMS, correlated over 2 s) barely averages out; the
    # height x field of view and the compass hold scale and heading (GPS alone: 2 degrees off here)
    assert score.median_m < 4.0 and abs(score.heading_error_deg) < 1.5 and abs(score.scale_error) < 0.01, score
    assert "warning" not in run.stderr, run.stderr


def test_a_short_tracks_few_fixes_are_taken_at_a_receivers_error_not_their_own_scatter():
    """Five fixes over 10 s say little of their own scatter (the similarity takes 4 of their 10
    coordinates): the floor under it is a typical receiver's until the track is long enough."""
    from mosaic_cli.geo.georef import GPS_FLOOR, GPS_TYPICAL, gps_dof, gps_floor

    short = gps_floor(gps_dof(np.arange(0.0, 10.0, 2.0), 2.0))
    assert GPS_FLOOR < short < GPS_TYPICAL
    assert gps_floor(gps_dof(np.arange(0.0, 60.0, 2.0), 2.0)) < short
    assert gps_floor(gps_dof(np.arange(0.0, 251.0, 2.1), 2.0)) == GPS_FLOOR  # the mapping flights: their own scatter
    # and a scale that far from the height's is judged by Student's t on those few degrees of
    # freedom: 3.5 normal sigmas are 5.7 on eight, and tend to 3.5 as the track grows
    from mosaic_cli.geo.georef import disagreement_limit

    assert disagreement_limit(3.5, 4.0) == pytest.approx(5.68, abs=0.02)  # t(8), a tail of 2.3e-4: between the tables' 5.04 (5e-4) and 6.44 (1e-4)
    assert 3.5 < disagreement_limit(3.5, 110.0) < 3.65 and disagreement_limit(3.5, 1e6) == pytest.approx(3.5, abs=1e-3)


def test_drift_shifts_leave_the_maps_scale_and_heading_to_the_global_fit():
    """GPS 5% too large and turned 2 degrees along a straight flight: a steady trend costs the
    bending terms nothing, yet the shifts must not take it: the global fit weighed it against
    the height and the compass (a slow bend they still take out: the test above)."""
    from mosaic_cli.geo.drift import drift_correction

    times = np.arange(0, 60, 2.0)
    truth = np.stack([3.0 * times, np.zeros_like(times)], 1)
    centre = truth.mean(0)
    turn = 1.05 * np.exp(1j * np.radians(2.0))
    z = (truth[:, 0] - centre[0]) + 1j * (truth[:, 1] - centre[1])
    gps = np.stack([(turn * z).real, (turn * z).imag], 1) + centre
    weights = np.ones(len(times))
    shifts = drift_correction(truth, gps, weights, times, 30.0, 3.0).shifts
    moved = truth + shifts
    assert np.abs(moved - moved.mean(0) - (truth - centre)).max() < 1e-6  # no trend taken: at most a common offset


@pytest.mark.slow
def test_embedded_track_is_used_without_telemetry_option(flights, tmp_path):
    video = flights["exact"]
    muxed = tmp_path / "with_srt.mkv"
    subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-y", "-i", str(video), "-i", str(video.with_suffix(".SRT")),
                    "-map", "0:v", "-map", "1:0", "-c", "copy", str(muxed)], check=True)
    import rasterio

    mosaic("stitch", muxed, "-o", tmp_path / "auto.tif", "-q")
    with rasterio.open(tmp_path / "auto.tif") as ds:
        assert ds.crs is not None and ds.crs.to_epsg() == 32632
    mosaic("stitch", muxed, "-o", tmp_path / "plain.tif", "-q", "--telemetry", "none")
    with rasterio.open(tmp_path / "plain.tif") as ds:
        assert ds.crs is None


@pytest.mark.slow
def test_klv_log_gives_the_same_map(flights, tmp_path):
    from mosaic_cli.simulate.telemetry import GpsErrors, MapGeo, write_telemetry

    video = tmp_path / "k.mp4"
    for suffix in (".mp4", ".gt.json"):
        (tmp_path / f"k{suffix}").write_bytes(flights["exact"].with_name("exact" + suffix).read_bytes())
    gt = load_ground_truth(video)
    truth = json.loads(flights["exact"].with_name("exact.geo.json").read_text())
    geo = MapGeo(truth["crs"], np.array(truth["map_to_crs"]), truth["gsd"])
    log = write_telemetry(video, gt, geo, "klv", GpsErrors(rms=0.0, dropouts=0.0, bad_fixes=0.0))
    tr = tmp_path / "t.json"
    mosaic("stitch", video, "--telemetry", log, "-o", tmp_path / "m.tif", "--transforms", tr, "-q")
    score = score_files(tr, gt, video.with_name("k.geo.json"))
    assert score.median_m < 0.3, score  # KLV altitudes are 0.3 m steps: a little less exact than SRT
    # the same KLV as a data stream of an MPEG-TS, found without --telemetry
    ts = tmp_path / "k.ts"
    subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-y", "-i", str(video), "-f", "data", "-i", str(log),
                    "-map", "0:v", "-map", "1:0", "-c", "copy", "-f", "mpegts", str(ts)], check=True)
    tr_ts = tmp_path / "t_ts.json"
    mosaic("stitch", ts, "-o", tmp_path / "ts.tif", "--transforms", tr_ts, "-q")
    assert score_files(tr_ts, gt, video.with_name("k.geo.json")).median_m < 0.3


@pytest.mark.slow
def test_live_stitch_with_telemetry_file_is_georeferenced(flights, tmp_path):
    """The live stitch shares finish_stitch: an explicit log gives it the same COG, footprints
    and map homographies as the offline one."""
    video = flights["exact"]
    tif, tr, fp = tmp_path / "live.tif", tmp_path / "t.json", tmp_path / "f.geojson"
    mosaic("stitch", video, "--live", "--telemetry", video.with_suffix(".SRT"), "-o", tif, "--transforms", tr,
           "--footprints", fp, "-q")
    gt = load_ground_truth(video)
    score = score_files(tr, gt, video.with_name("exact.geo.json"))
    frame_gsd = json.loads(tr.read_text())["gsd_m"]
    assert score.median_m < 2 * frame_gsd and score.max_m < 8 * frame_gsd, score
    import rasterio

    with rasterio.open(tif) as ds:
        assert ds.crs is not None and ds.crs.to_epsg() == 32632
    kinds = [f["properties"]["kind"] for f in json.loads(fp.read_text())["features"]]
    assert kinds.count("footprint") == len(json.loads(tr.read_text())["frames"])


@pytest.mark.parametrize("flag", ["--footprints", "--level-ground"])
def test_live_stream_georef_flags_need_a_telemetry_file(capsys, tmp_path, flag):
    """A stream cannot be searched for an embedded track: --footprints and --level-ground need
    --telemetry (said before the stream is read)."""
    extra = [flag, tmp_path / "f.geojson"] if flag == "--footprints" else [flag]
    code, err = run_cli(capsys, "stitch", "-", "-o", tmp_path / "m.tif", *extra, "-q", "--estimator", "orb")
    assert_one_line_error(code, err, flag, "--telemetry")
    assert not (tmp_path / "m.tif").exists()


@pytest.mark.slow
@pytest.mark.parametrize("flag", ["--footprints", "--level-ground"])
def test_georef_flags_on_a_video_without_a_track_are_one_clear_line(capsys, tmp_path, flag, plain_160x90):
    """A video with no telemetry inside and no --telemetry: a georeferencing flag is an error,
    not silently dropped."""
    video = plain_160x90
    extra = [flag, tmp_path / "f.geojson"] if flag == "--footprints" else [flag]
    code, err = run_cli(capsys, "stitch", video, "-o", tmp_path / "m.png", *extra, "-q", "--estimator", "orb")
    assert_one_line_error(code, err, f"{flag} needs telemetry")
    assert not (tmp_path / "m.png").exists()


@pytest.mark.slow
def test_photo_folder_refuses_a_telemetry_file(capsys, tmp_path, flights):
    """A photo folder's positions are its EXIF GPS (tests/test_photo_gps.py): a log is refused."""
    import cv2

    folder = tmp_path / "photos"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for k in range(2):
        cv2.imwrite(str(folder / f"p{k}.png"), rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))
    code, err = run_cli(capsys, "stitch", folder, "-o", tmp_path / "m.tif", "--telemetry",
                        flights["exact"].with_suffix(".SRT"), "-q", "--estimator", "orb")
    assert_one_line_error(code, err, "a photo folder's positions are its photos' EXIF GPS")


@pytest.mark.slow
@pytest.mark.parametrize("case", ["offset", "no-fix", "other-flight", "footprints-without", "level-ground-without"])
def test_unusable_telemetry_is_one_clear_line(flights, tmp_path, case):
    video = flights["exact"]
    srt = video.with_suffix(".SRT")
    args = ["stitch", video, "-o", tmp_path / "m.tif", "-q"]
    if case == "offset":
        args += ["--telemetry", srt, "--telemetry-offset", "600"]
        expect = "does not cover the video"
    elif case == "no-fix":
        text = srt.read_text()
        import re

        text = re.sub(r"\[latitude: [-\d.]+\] \[longitude: [-\d.]+\]", "[latitude: 0.000000] [longitude: 0.000000]", text)
        (tmp_path / "nofix.SRT").write_text(text)
        args += ["--telemetry", tmp_path / "nofix.SRT"]
        expect = "no GPS fix"
    elif case == "other-flight":
        # another flight's log: 300 m in these 5 seconds at 30 m above ground (the images: a few metres)
        (tmp_path / "other.csv").write_text("time,lat,lon,alt,height,yaw,hfov\n" + "".join(
            f"{t / 10:.2f},{47.3977 + 0.00005 * t:.7f},{8.5456 + 0.00002 * t:.7f},400,30,0,53.13\n" for t in range(60)))
        args += ["--telemetry", tmp_path / "other.csv"]
        expect = "disagrees with the images"
    elif case == "footprints-without":
        args += ["--telemetry", "none", "--footprints", tmp_path / "f.geojson"]
        expect = "--footprints needs telemetry"
    else:
        args += ["--telemetry", "none", "--level-ground"]
        expect = "--level-ground needs telemetry"
    run = mosaic(*args, check=False)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mosaic: error:") and expect in lines[0], run.stderr
    assert not (tmp_path / "m.tif").exists()


def test_drift_shifts_remove_slow_bending_but_not_follow_gps_noise():
    from mosaic_cli.geo.drift import drift_correction
    from mosaic_cli.simulate.telemetry import gauss_markov

    rng = np.random.default_rng(7)
    times = np.arange(0, 240, 2.0)  # a keyframe every 2 s, 4 minutes
    truth = np.stack([3.0 * times, np.zeros_like(times)], 1)  # 720 m straight line
    bend = np.stack([np.zeros_like(times), 15.0 * np.sin(np.pi * times / 240)], 1)  # the images bent it 15 m
    gps = truth + np.stack([gauss_markov(rng, times, 2.1, 2.0), gauss_markov(rng, times, 2.1, 2.0)], 1)
    weights = np.ones(len(times))
    shifts = drift_correction(truth + bend, gps, weights, times, 30.0, 2.1).shifts
    after = np.linalg.norm(truth + bend + shifts - truth, axis=1)
    assert np.median(after) < 1.0 and after.max() < 4.0  # from 15 m
    # an unbent mosaic stays put: the shifts stay well under the GPS noise
    still = drift_correction(truth, gps, weights, times, 30.0, 2.1).shifts
    assert np.median(np.linalg.norm(still, axis=1)) < 1.0
    # consecutive keyframes (6 m apart) move together to decimetres: no GPS jitter in the mosaic
    assert np.abs(np.diff(shifts, axis=0)).max() < 0.6


def test_drift_correction_undoes_the_images_scale_drift_by_the_heights():
    """Chained registrations drift in scale: here the mosaic's keyframes shrink to 4% small
    toward the middle of a 720 m line, their spacing with them, and the global fit has scaled
    it onto the truth as a whole.  The heights (0.3 m noise per keyframe at 32 m, and one
    unknown offset) give each keyframe's scale back to within about a percent; the GPS (3 m
    noise) cannot see a keyframe's size, and without heights nothing is scaled."""
    from mosaic_cli.geo.drift import drift_correction
    from mosaic_cli.simulate.telemetry import gauss_markov

    rng = np.random.default_rng(11)
    times = np.arange(0, 240, 2.0)
    truth = np.stack([3.0 * times, np.zeros_like(times)], 1)
    shrink = 0.04 * np.sin(np.pi * times / 240)  # the mosaic's scale error: log(mosaic / true), 0 at both ends
    step = np.diff(truth[:, 0]) * np.exp(-0.5 * (shrink[1:] + shrink[:-1]))
    mosaic = np.stack([np.concatenate([[0.0], np.cumsum(step)]), np.zeros_like(times)], 1)
    # as the global fit leaves it: the best similarity onto the truth (the map's scale is that fit's)
    (a, b), *_ = np.linalg.lstsq(np.stack([mosaic[:, 0], np.ones(len(times))], 1), truth[:, 0], rcond=None)
    mosaic[:, 0] = a * mosaic[:, 0] + b
    shrink = shrink - np.log(a)
    gps = truth + np.stack([gauss_markov(rng, times, 3.0, 2.0), gauss_markov(rng, times, 3.0, 2.0)], 1)
    weights = np.ones(len(times))
    heights = shrink + 0.3 / 32.0 * rng.standard_normal(len(times)) + 0.02  # log(height's scale / mosaic's), offset unknown
    fixed = drift_correction(mosaic, gps, weights, times, 30.0, 3.0, height_scales=heights)
    left = np.log(fixed.scales) - shrink  # what scale error is left, up to one figure for the flight
    assert np.ptp(left) < 0.5 * np.ptp(shrink) and np.abs(left - np.median(left)).max() < 0.012
    # the spacing stretches with the scales: the 2 m the chain's shape was off along the line nearly halve
    before = np.abs(mosaic - truth).max()
    assert before > 1.9 and np.abs(mosaic + fixed.shifts - truth).max() < 0.6 * before
    # without heights nothing is scaled
    assert np.all(drift_correction(mosaic, gps, weights, times, 30.0, 3.0).scales == 1.0)


def test_georeferencing_warnings_are_said_even_when_quiet():
    """What the georeferencing warns of (a height x field of view scale far from the GPS's)
    becomes one ``mosaic: warning:`` line per warning, named by panorama when there are several."""
    from pathlib import Path
    from types import SimpleNamespace

    from mosaic_cli.commands.stitch import _notices

    said = "the height and field of view (60.0 deg) make the map +15.6% the size the GPS track does"
    first = SimpleNamespace(path=Path("map.tif"), georef=SimpleNamespace(warnings=[said]), transforms=[(0, None)], spans=[(0, 89)], size=90, shrunk_from=None, off_map=None)
    result = SimpleNamespace(panoramas=[first], georef=first.georef, dropped=[], photos=False, metadata_notes=[])
    assert _notices(Path("v.mp4"), result) == [said]
    second = SimpleNamespace(path=Path("map-2.tif"), georef=SimpleNamespace(warnings=[]), transforms=[(90, None)], spans=[(90, 120)], size=31, shrunk_from=None, off_map=None)
    result = SimpleNamespace(panoramas=[first, second], georef=first.georef, dropped=[], photos=False, metadata_notes=[])
    assert f"map.tif: {said}" in _notices(Path("v.mp4"), result)


@pytest.mark.parametrize("offset, warned", [(2.0, False), (14.0, True)])
def test_fixes_that_scatter_beyond_a_receivers_error_are_said_to_bound_the_maps_placement(offset, warned):
    """A survey's keyframes whose GPS fixes lie ``offset`` metres off where the images place them,
    alternately east and west along each line (as a camera looking ahead of the drone puts its
    view on lines flown both ways): at a receiver's error, no word; at several times it, one
    warning that names the scatter (the map cannot be placed closer with one plane)."""
    from mosaic_cli.geo.crs import Projection
    from mosaic_cli.geo.georef import GeorefOptions, georeference
    from mosaic_cli.telemetry.flight_log import FlightLog

    size, gsd = (640, 360), 0.1  # metres a pixel
    centres = np.array([(x, y) for y in (0.0, 300.0, 600.0) for x in np.arange(0.0, 1200.0, 150.0)])  # 3 lines, reference pixels
    placements = [np.array([[1.0, 0, x - 319.5], [0, 1.0, y - 179.5], [0, 0, 1]]) for x, y in centres]
    line = np.repeat([1.0, -1.0, 1.0], len(centres) // 3)
    rng = np.random.default_rng(1)
    east = 500_000 + centres[:, 0] * gsd + line * offset * np.tile([1.0, -1.0], len(centres) // 2) + rng.normal(0, 0.5, len(centres))
    north = 5_250_000 - centres[:, 1] * gsd + rng.normal(0, 0.5, len(centres))
    projection = Projection.utm_for(47.4, 8.5)
    lon, lat = projection.to_wgs84(east, north).T
    n = len(centres)
    nan = np.full(n, np.nan)
    times = np.arange(n, dtype=float) * 4.0
    track = FlightLog("test log", times, lat, lon, nan, nan, nan, nan, nan, nan)
    georef = georeference(placements, n // 2, list(range(n)), size, 0.25, track, GeorefOptions())
    said = [w for w in georef.warnings if "scatter" in w]
    assert bool(said) == warned, georef.warnings
    if warned:
        assert georef.fit.sigma > 3 * 3.5 and f"scatter {georef.fit.sigma:.0f} m" in said[0]
