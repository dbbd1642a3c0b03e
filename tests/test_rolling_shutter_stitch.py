"""stitch --rolling-shutter: each keyframe's row bands drawn where the simulator's truth puts
them (``ground_truth_band_placement``), the pixels too, and the option's refusals."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest

from conftest import cli_exit
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import make_estimator
from mosaic_cli.geometry import project
from mosaic_cli.geometry.rolling_shutter import band_centres
from mosaic_cli.simulate import RollingShutter, SimulateOptions, load_ground_truth, plan_simulated_flight, simulate_flight
from mosaic_cli.stabilize.wobble import ground_truth_band_placement
from mosaic_cli.stitch import StitchOptions, stitch
from mosaic_cli.stitch.compose import Roi, warp_into
from mosaic_cli.video import open_video

SIZE = (640, 360)


def test_band_placement_score_is_zero_for_the_truth_and_not_for_one_homography():
    plan = plan_simulated_flight((2048, 2048), SimulateOptions(profile="fast", frames=30, size=SIZE, seed=1,
                                                               rolling=RollingShutter(0.8, 12.0, 5.0)))
    G = np.array([[0.5, 0.1, 30.0], [-0.1, 0.5, 10.0], [0.0, 0.0, 1.0]])  # any map -> panorama
    keys = range(0, 30, 6)
    transforms = [(i, G @ np.linalg.inv(plan.map_to_frame[i])) for i in keys]
    truth = [G @ np.linalg.inv(plan.row_bands[i]) for i in keys]
    assert ground_truth_band_placement(plan.row_bands, plan.map_to_frame, SIZE, transforms, truth)["rms"] < 1e-4
    one = ground_truth_band_placement(plan.row_bands, plan.map_to_frame, SIZE, transforms, None)
    assert one["shape"] > 0.3  # in panorama px at half scale: the rows' wobble


def test_row_map_samples_each_canvas_pixel_through_its_row():
    """warp_into with a row map: a shift of +3 px for the lower half of the rows lands there."""
    image = np.zeros((40, 60, 3), np.uint8)
    image[:, 30] = 255  # one bright column
    H = np.eye(3)

    def rows(x, y):  # points of the mid-time pose -> the image's own pixels: lower rows moved 3 px left
        return x - np.where(y >= 20, 3.0, 0.0), y

    warped, mask = warp_into(image, H, Roi(0, 0, 60, 40), rows=rows)
    assert np.argmax(warped[5, :, 0]) == 30 and np.argmax(warped[35, :, 0]) == 33
    assert mask[5, 2] == 255 and mask[35, 1] == 0  # sampled from outside the image: not covered


def test_refusals(tmp_path):
    with pytest.raises(BadInput, match="--rolling-shutter"):
        StitchOptions(rolling_shutter="sometimes")
    folder = tmp_path / "photos"
    folder.mkdir()
    for i in range(2):
        cv2.imwrite(str(folder / f"{i:03d}.png"), np.full((64, 64, 3), 40 * i, np.uint8))
    with pytest.raises(BadInput, match="photo folders"):
        stitch(folder, tmp_path / "p.png", make_estimator("orb"), StitchOptions(rolling_shutter="auto"), show_progress=False)


@pytest.mark.slow
def test_auto_places_the_row_bands(tmp_path):
    clip = tmp_path / "rs.mp4"
    simulate_flight(clip, None, SimulateOptions(profile="fast", frames=120, size=SIZE, seed=3, preset="ultrafast",
                                                rolling=RollingShutter(0.7, 15.0, 4.0)), show_progress=False)
    gt = load_ground_truth(clip)
    est = make_estimator("orb")
    off = stitch(clip, tmp_path / "off.png", est, StitchOptions(rolling_shutter="off"), show_progress=False)
    auto = stitch(clip, tmp_path / "auto.png", est, StitchOptions(rolling_shutter="auto"), show_progress=False)
    assert off.rolling is None and off.panoramas[0].bands is None
    assert auto.rolling is not None and auto.rolling.applied and abs(auto.rolling.readout - 0.7) < 0.14
    p_off, p_auto = off.panoramas[0], auto.panoramas[0]
    assert p_auto.bands is not None and len(p_auto.bands) == len(p_auto.transforms) >= 4
    s_off = ground_truth_band_placement(gt.row_bands, gt.map_to_frame, gt.size, p_off.transforms, None)
    s_auto = ground_truth_band_placement(gt.row_bands, gt.map_to_frame, gt.size, p_auto.transforms, p_auto.bands)
    assert s_off["rms"] > 0.8 and s_auto["rms"] < 0.5 * s_off["rms"]
    # the bands reported are what was drawn: a band's centre row lies on the panorama where its
    # transform says (the panorama's pixels against the keyframe's own, through the band's homography)
    pano = cv2.imread(str(tmp_path / "auto.png"), cv2.IMREAD_UNCHANGED)
    frame_index, _ = p_auto.transforms[len(p_auto.transforms) // 2]
    with open_video(clip) as frames:
        frame = next(itertools.islice(frames, frame_index, None))
    k = 8
    y = band_centres(SIZE[1], 16)[k]
    xs = np.arange(100, 540, 4.0)
    q = project(p_auto.bands[len(p_auto.transforms) // 2][k], np.stack([xs, np.full(len(xs), y)], 1))
    drawn = cv2.remap(cv2.cvtColor(pano[..., :3], cv2.COLOR_BGR2GRAY).astype(np.float32), q[:, 0].astype(np.float32)[None],
                      q[:, 1].astype(np.float32)[None], cv2.INTER_LINEAR)[0]
    seen = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY).astype(np.float32)[int(round(y)), 100:540:4]
    assert np.corrcoef(drawn, seen)[0, 1] > 0.8


@pytest.mark.slow
def test_auto_is_the_default_for_a_video_file_and_off_for_photo_folders(tmp_path, capsys):
    clip = tmp_path / "rs.mp4"
    simulate_flight(clip, None, SimulateOptions(profile="fast", frames=60, size=SIZE, seed=3, preset="ultrafast",
                                                rolling=RollingShutter(0.7, 15.0, 4.0)), show_progress=False)
    assert cli_exit(["stitch", str(clip), "-o", str(tmp_path / "p.png"), "-e", "orb"]) == 0
    assert "(estimated), each row band drawn where it belongs" in capsys.readouterr().err
    folder = tmp_path / "photos"
    folder.mkdir()
    with open_video(clip) as frames:
        for i, frame in enumerate(itertools.islice(frames, 0, 60, 6)):
            cv2.imwrite(str(folder / f"{i:03d}.png"), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    assert cli_exit(["stitch", str(folder), "-o", str(tmp_path / "photos.png"), "-q"]) == 0
    assert cli_exit(["stitch", str(folder), "-o", str(tmp_path / "refused.png"), "--rolling-shutter", "auto", "-q"]) == 2
