"""Many flights, one map (issue 52, mosaic_cli/stitch/flights.py), against the simulator's exact
ground truth: flights cut from one simulated survey (each a video with its own DJI log beside it)
must be placed as the truth places them where they overlap; flights over ground apart are laid
on one map by their logs, within the logs' accuracy."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks.flights import cut_flight, fly_apart, ground_errors, placement_spread
from mosaic_cli.errors import BadInput
from mosaic_cli.stitch.flights import expand_flights
from tests.conftest import assert_one_line_error, mosaic_run, run_cli


@pytest.fixture(scope="module")
def survey(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("flights")
    full = folder / "full.mp4"
    mosaic_run("simulate", "-p", "survey", "-n", "400", "--size", "320x180", "-o", full, "-q", "--telemetry", "srt", "--seed", "3",
               "--preset", "ultrafast")
    cut_flight(full, 0, 240, folder / "a.mp4")
    cut_flight(full, 160, 400, folder / "b.mp4")
    return folder


@pytest.mark.slow
def test_two_overlapping_flights_make_one_map_placed_as_the_truth(survey):
    out, js = survey / "map.tif", survey / "map.json"
    run = mosaic_run("stitch", survey / "a.mp4", survey / "b.mp4", "-o", out, "--transforms", js)
    # the summary names each flight's part, and the one map holds both
    assert f"flight a.mp4: 240 frames -> {out}" in run.stderr and f"flight b.mp4: 240 frames -> {out}" in run.stderr, run.stderr
    transforms = json.loads(js.read_text())
    assert {Path(f["flight"]).name for f in transforms["frames"]} == {"a.mp4", "b.mp4"}  # both flights, on one map
    assert not (survey / "map-2.tif").exists()
    truth = json.loads((survey / "full.gt.json").read_text())
    spread, seen_by = placement_spread(transforms, truth, {"a.mp4": 0, "b.mp4": 160})
    assert seen_by == {"a.mp4", "b.mp4"} and spread < 2.0
    import rasterio

    with rasterio.open(out) as ds:
        assert ds.crs.to_epsg() == 32632 and ds.count == 4


@pytest.mark.slow
def test_flights_over_ground_apart_are_laid_on_one_map_by_their_logs(tmp_path):
    """Two flights over two different maps 150 m apart (nothing to register between them): one
    map, each keyframe where the truth has it within the logs' accuracy (3 m RMS of GPS error)."""
    from mosaic_cli.telemetry.align import local_metres

    west, east = fly_apart(tmp_path, 150.0)
    out, js, fp = tmp_path / "map.tif", tmp_path / "map.json", tmp_path / "fp.geojson"
    run = mosaic_run("stitch", west, east, "-o", out, "--transforms", js, "--footprints", fp)
    assert sorted(p.name for p in tmp_path.glob("map*.tif")) == ["map.tif"]
    errors = ground_errors(json.loads(js.read_text()), tmp_path)
    assert set(errors) == {"east", "west"}
    assert all(np.median(e) < 3.0 for e in errors.values()), errors
    # The logs' summary counts the flights, not the pause between them as a gap or as time flown
    # (each log has a sample a frame, at 30 fps).
    (summary,) = [line for line in run.stderr.splitlines() if "west.SRT" in line and "samples" in line]
    assert "samples (30.0 Hz) over 2 flights" in summary and "gap" not in summary, summary
    # and the GPS track is drawn a line a flight, none joining the two 150 m apart
    lines = [f["geometry"]["coordinates"] for f in json.loads(fp.read_text())["features"] if f["properties"]["kind"] == "gps track"]
    assert len(lines) == 2
    lon0, lat0 = lines[0][0]
    metres = [local_metres(np.array(c)[:, 1], np.array(c)[:, 0], lat0, lon0) for c in lines]
    assert all(np.ptp(m, axis=0).max() < 100.0 for m in metres)  # each flight's line stays over its own ground
    assert np.linalg.norm(metres[0].mean(axis=0) - metres[1].mean(axis=0)) > 100.0


def test_a_folder_of_videos_or_of_photo_folders_is_its_flights(tmp_path):
    videos = tmp_path / "day"
    videos.mkdir()
    for name in ("DJI_0002.MP4", "DJI_0001.MP4", "notes.txt"):
        (videos / name).write_bytes(b"")
    assert expand_flights([videos]) == [str(videos / "DJI_0001.MP4"), str(videos / "DJI_0002.MP4")]
    photos = tmp_path / "survey"
    for part in ("battery1", "battery2"):
        (photos / part).mkdir(parents=True)
        (photos / part / "IMG_0001.JPG").write_bytes(b"")
    assert expand_flights([photos]) == [str(photos / "battery1"), str(photos / "battery2")]
    with pytest.raises(BadInput, match="named twice"):
        expand_flights([videos / "DJI_0001.MP4", videos / "DJI_0001.MP4"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(BadInput, match="no photos, videos or photo folders"):
        expand_flights([tmp_path / "empty"])


@pytest.mark.parametrize("extra,said", [
    (["--telemetry", "{a}"], "names one log for several flights"),
    (["--dry-run"], "take one flight"),
    (["--rolling-shutter", "0.5"], "one flight at a time"),
])
def test_what_several_flights_cannot_take_is_one_line_before_any_work(capsys, tmp_path, plain_160x90, extra, said):
    other = tmp_path / "other.mp4"
    other.write_bytes(plain_160x90.read_bytes())
    args = [a.replace("{a}", str(plain_160x90)) for a in extra]
    code, err = run_cli(capsys, "stitch", plain_160x90, other, "-o", tmp_path / "p.png", "-q", "--estimator", "orb", *args)
    assert_one_line_error(code, err, said)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.mp4"]


def test_flights_of_different_sizes_or_kinds_are_refused_in_one_line(capsys, tmp_path, plain_160x90):
    bigger = tmp_path / "bigger.mp4"
    mosaic_run("simulate", "-n", "12", "--size", "192x108", "-o", bigger, "-q", "--preset", "ultrafast")
    code, err = run_cli(capsys, "stitch", plain_160x90, bigger, "-o", tmp_path / "p.png", "-q", "--estimator", "orb")
    assert_one_line_error(code, err, "the flights' frames differ in size")
    photos = tmp_path / "photos"
    photos.mkdir()
    import cv2

    cv2.imwrite(str(photos / "a.png"), np.zeros((90, 160, 3), np.uint8))
    code, err = run_cli(capsys, "stitch", plain_160x90, photos, "-o", tmp_path / "p.png", "-q", "--estimator", "orb")
    assert_one_line_error(code, err, "photo folders and videos cannot be stitched together")
