"""Rolling shutter in the simulator: each row sees the camera at its own time, exactly as the
ground truth's row bands say; global-shutter flights stay as they were."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from conftest import cli_exit
from mosaic_cli.errors import BadInput
from mosaic_cli.geometry import project
from mosaic_cli.geometry.rolling_shutter import band_centres, row_frame_to_ref
from mosaic_cli.simulate import (
    RollingShutter,
    SimulateOptions,
    load_ground_truth,
    parse_vibration,
    plan_simulated_flight,
    procedural_map,
    render_frames,
    write_flight,
)
from mosaic_cli.simulate.render import MapPyramid, render_view

SIZE = (320, 180)


@pytest.fixture(scope="module")
def small_map():
    return procedural_map((1024, 1024), seed=5)


def _plan(readout=0.0, hz=0.0, px=0.0, frames=6, size=SIZE, profile="paper", seed=3):
    options = SimulateOptions(profile=profile, frames=frames, size=size, seed=seed, rolling=RollingShutter(readout, hz, px))
    return plan_simulated_flight((1024, 1024), options)


def test_global_shutter_is_the_flight_of_before(small_map):
    plain = plan_simulated_flight((1024, 1024), SimulateOptions(profile="shaky", frames=6, size=SIZE, seed=3))
    explicit = _plan(0.0, 0.0, 0.0, profile="shaky")
    assert explicit.row_bands is None and explicit.rolling is None
    assert np.array_equal(plain.map_to_frame, explicit.map_to_frame)
    for a, b in zip(render_frames(small_map, plain), render_frames(small_map, explicit)):
        assert np.array_equal(a, b)


def test_row_bands_follow_the_row_times():
    """Without vibration the bands sample the same path at their rows' times: the last band of
    a full-readout frame is nearly the next frame's first; the mid pose is the centre row's."""
    plan = _plan(readout=1.0, frames=8)
    gs = _plan(frames=8)
    assert plan.row_bands.shape == (8, 16, 3, 3)
    h = SIZE[1]
    centre = np.array([[SIZE[0] / 2, SIZE[1] / 2]])
    # band k of frame t at time t + y_k / h: between frames t and t+1 of the global-shutter path
    for t in (2, 5):
        for k in (0, 7, 15):
            a = band_centres(h, 16)[k] / h
            expected = (1 - a) * project(gs.map_to_frame[t], project(np.linalg.inv(gs.map_to_frame[2]), centre)) \
                + a * project(gs.map_to_frame[t + 1], project(np.linalg.inv(gs.map_to_frame[2]), centre))
            got = project(plan.row_bands[t, k], project(np.linalg.inv(gs.map_to_frame[2]), centre))
            assert np.abs(got - expected).max() < 0.05  # a smooth path: linear in between to 0.05 px
    # the frame's own pose is the one of its centre row, half a readout in
    mid = project(plan.map_to_frame[3], centre)
    between = 0.5 * (project(plan.row_bands[3, 7], centre) + project(plan.row_bands[3, 8], centre))
    assert np.abs(mid - between).max() < 0.05


def test_vibration_oscillates_at_its_frequency():
    plan = _plan(readout=0.0, hz=7.5, px=4.0, frames=120, size=(640, 360))
    centre = np.array([[320.0, 180.0]])
    shake = np.array([project(M, project(np.linalg.inv(G), centre))[0] for M, G in zip(plan.map_to_frame, plan.smooth_map_to_frame)]) - centre
    spectrum = np.abs(np.fft.rfft(shake[:, 0] - shake[:, 0].mean()))
    freqs = np.fft.rfftfreq(120, 1 / 30.0)
    assert freqs[np.argmax(spectrum)] == pytest.approx(7.5, abs=0.3)
    assert 1.0 < np.abs(shake).max() < 2.5  # 4 px at 1280 wide: 2 px at 640, plus the rotation's bit


def _dot_map(size: int = 1024, count: int = 500, lo: float = 100, hi: float = 924):
    """A dark ``size``-square map of ``count`` bright round dots (anti-aliased, blurred), their
    centres uniform in [lo, hi]; the map and the centres (count, 2)."""
    rng = np.random.default_rng(0)
    m = np.full((size, size, 3), 20, np.uint8)
    pts = rng.uniform(lo, hi, size=(count, 2))
    for x, y in pts:
        cv2.circle(m, (int(round(x * 16)), int(round(y * 16))), 3 * 16, (255, 255, 255), -1, cv2.LINE_AA, shift=4)
    return cv2.GaussianBlur(m, (0, 0), 2.0), pts


def test_known_points_land_where_their_rows_say():
    """Bright dots on a dark map: their centroids in a rolling-shutter frame follow the rows'
    homographies of the ground truth (to 0.3 px), and not the frame's single mid-time pose."""
    m, pts = _dot_map()
    plan = _plan(readout=0.9, hz=10.0, px=12.0, frames=4, size=(640, 360), seed=1)
    t = 2
    frame = list(render_frames(m, plan))[t]
    gray = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY).astype(np.float64)
    mid = project(plan.map_to_frame[t], pts)
    bands_back = np.linalg.inv(plan.row_bands[t])  # frame -> map per band
    # where each dot is: the frame point whose own row's homography maps the dot there (a fixed point)
    x = mid.copy()
    for _ in range(4):
        row_back = row_frame_to_ref(bands_back, x[:, 1], 360)  # (P, 3, 3) frame -> map of each point's row
        x = np.array([project(np.linalg.inv(F), p[None])[0] for F, p in zip(row_back, pts)])
    errors, single = [], []
    for (px, py), (qx, qy) in zip(x, mid):
        if 12 <= px < 640 - 12 and 12 <= py < 360 - 12:
            x0, y0 = int(round(px)), int(round(py))
            win = np.clip(gray[y0 - 6:y0 + 7, x0 - 6:x0 + 7] - 20, 0, None)
            yy, xx = np.mgrid[-6:7, -6:7]
            cx, cy = (win * xx).sum() / win.sum() + x0, (win * yy).sum() / win.sum() + y0
            errors.append(np.hypot(cx - px, cy - py))
            single.append(np.hypot(cx - qx, cy - qy))
    assert len(errors) > 20
    assert np.median(errors) < 0.3, np.median(errors)
    assert np.median(single) > 1.0, np.median(single)  # the wobble is there to see


def test_band_centre_rows_are_their_bands_views(small_map):
    plan = _plan(readout=0.8, hz=12.0, px=10.0, frames=3, size=(640, 360))
    frame = list(render_frames(small_map, plan))[1].astype(np.int16)
    pyramid = MapPyramid(small_map)
    rows = np.round(band_centres(360, 16)).astype(int)
    for k in (1, 8, 14):
        own = render_view(pyramid, plan.row_bands[1, k], (640, 360)).astype(np.int16)
        other = render_view(pyramid, plan.row_bands[1, (k + 8) % 16], (640, 360)).astype(np.int16)
        row = int(round(band_centres(360, 16)[k]))
        # (the centre row lies half a row from a pixel row: compare at the nearest one)
        assert row in rows
        same = np.abs(frame[row, 20:-20] - own[row, 20:-20]).mean()
        differs = np.abs(frame[row, 20:-20] - other[row, 20:-20]).mean()
        assert same < 3.0 and differs > 3 * same, (same, differs)


def test_ground_truth_round_trip(tmp_path, small_map):
    plan = _plan(readout=0.6, hz=15.0, px=3.0, frames=5)
    gt = write_flight(tmp_path / "rs.mp4", small_map, plan, show_progress=False, preset="ultrafast")
    data = json.loads((tmp_path / "rs.gt.json").read_text())
    rs = data["rolling_shutter"]
    assert rs["readout"] == 0.6 and rs["vibration_hz"] == 15.0 and rs["vibration_px"] == 3.0 and rs["bands"] == 16
    assert np.array(rs["row_bands"]).shape == (5, 16, 3, 3) and len(rs["band_rows"]) == 16
    loaded = load_ground_truth(tmp_path / "rs.gt.json")
    assert loaded.readout == 0.6 and gt.readout == 0.6
    np.testing.assert_allclose(loaded.row_bands, plan.row_bands, rtol=0, atol=1e-12)
    np.testing.assert_allclose(loaded.map_to_frame, plan.map_to_frame, rtol=0, atol=1e-12)
    write_flight(tmp_path / "gs.mp4", small_map, _plan(frames=5), show_progress=False, preset="ultrafast")
    assert "rolling_shutter" not in json.loads((tmp_path / "gs.gt.json").read_text())
    assert load_ground_truth(tmp_path / "gs.gt.json").row_bands is None


def test_options_refuse_bad_values():
    with pytest.raises(BadInput, match="--rolling-shutter must be in"):
        RollingShutter(1.5)
    with pytest.raises(BadInput, match="--vibration"):
        RollingShutter(0.5, -1.0, 2.0)
    with pytest.raises(BadInput, match="--vibration must be HZ,PX"):
        parse_vibration("12")
    assert parse_vibration("12,3") == (12.0, 3.0) and parse_vibration(None) == (0.0, 0.0)


def test_simulate_command_rolling_shutter(tmp_path, capsys):
    out = tmp_path / "f.mp4"
    assert cli_exit(["simulate", "-o", str(out), "-n", "4", "--size", "160x96", "--rolling-shutter", "0.5",
                     "--vibration", "12,3", "--preset", "ultrafast", "--seed", "3", "-q"]) == 0  # (seed 3: a map made once)
    gt = load_ground_truth(out)
    assert gt.readout == 0.5 and gt.row_bands is not None and gt.rolling["vibration_hz"] == 12.0
    assert cli_exit(["simulate", "-o", str(out), "--rolling-shutter", "2", "-q"]) == 2
    assert "--rolling-shutter must be in [0, 1]" in capsys.readouterr().err
    assert cli_exit(["simulate", "-o", str(out), "--vibration", "fast", "-q"]) == 2
    assert "--vibration must be HZ,PX" in capsys.readouterr().err
