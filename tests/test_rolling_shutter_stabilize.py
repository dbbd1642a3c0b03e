"""stabilize --rolling-shutter: the wobble scored exactly against the simulator's bands, the
readout read from the video, global-shutter footage left alone."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import cli_exit
from mosaic_cli.errors import BadInput
from mosaic_cli.geometry.rolling_shutter import band_centres
from mosaic_cli.simulate import RollingShutter, SimulateOptions, load_ground_truth, plan_simulated_flight, simulate_flight
from mosaic_cli.stabilize import StabilizeOptions, stabilize
from mosaic_cli.stabilize.rolling import parse_rolling_shutter
from mosaic_cli.stabilize.wobble import ground_truth_wobble, video_wobble

SIZE = (640, 360)


def test_wobble_of_the_truth_is_zero_and_of_the_raw_frames_is_not():
    plan = plan_simulated_flight((2048, 2048), SimulateOptions(frames=40, size=SIZE, seed=1, rolling=RollingShutter(0.8, 12.0, 5.0)))
    raw = ground_truth_wobble(plan.row_bands, plan.map_to_frame, SIZE)
    assert raw > 1.0
    # each band taken to its frame's mid-time pose: a rigid frame, no wobble at all
    perfect = np.einsum("nij,nkjl->nkil", plan.map_to_frame, np.linalg.inv(plan.row_bands))
    assert ground_truth_wobble(plan.row_bands, plan.map_to_frame, SIZE, band_warps=perfect) < 1e-6
    # a steady distortion is not wobble: the same rows' skew in every frame scores 0
    gs = plan_simulated_flight((2048, 2048), SimulateOptions(frames=40, size=SIZE, seed=1, rolling=RollingShutter(0.0, 12.0, 5.0)))
    assert ground_truth_wobble(gs.row_bands, gs.map_to_frame, SIZE) < 1e-9


def test_parse_rolling_shutter():
    assert parse_rolling_shutter("auto") == "auto" and parse_rolling_shutter("OFF") == "off"
    assert parse_rolling_shutter("0.7") == 0.7 and parse_rolling_shutter("0") == "off"
    for bad in ("1.5", "jello"):
        with pytest.raises(BadInput, match="--rolling-shutter must be auto, off or a readout"):
            parse_rolling_shutter(bad)
    with pytest.raises(BadInput, match="--rolling-shutter"):
        StabilizeOptions(rolling_shutter="-1")


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    folder = tmp_path_factory.mktemp("rs")
    rs, gs = folder / "rs.mp4", folder / "gs.mp4"
    simulate_flight(rs, None, SimulateOptions(frames=90, size=SIZE, seed=3, preset="ultrafast", rolling=RollingShutter(0.7, 12.0, 5.0)),
                    show_progress=False)
    simulate_flight(gs, None, SimulateOptions(frames=90, size=SIZE, seed=3, preset="ultrafast", rolling=RollingShutter(0.0, 12.0, 5.0)),
                    show_progress=False)
    return rs, gs


@pytest.mark.slow
def test_auto_takes_out_the_wobble(flights, tmp_path):
    rs, _ = flights
    gt = load_ground_truth(rs)
    off = stabilize(rs, tmp_path / "off.mp4", StabilizeOptions(rolling_shutter="off"), show_progress=False)
    auto = stabilize(rs, tmp_path / "auto.mp4", StabilizeOptions(rolling_shutter="auto"), show_progress=False)
    assert off.rolling is None and auto.rolling is not None and auto.rolling.applied
    assert abs(auto.rolling.readout - 0.7) < 0.14
    bands = auto.rolling.band_warps(auto.warps, band_centres(SIZE[1], 16))
    before = ground_truth_wobble(gt.row_bands, gt.map_to_frame, SIZE, off.warps)
    after = ground_truth_wobble(gt.row_bands, gt.map_to_frame, SIZE, auto.warps, bands)
    assert before > 1.0 and after < 0.25 * before, (before, after)
    # and the pixels agree: the output video wobbles less
    assert video_wobble(tmp_path / "auto.mp4") < 0.5 * video_wobble(tmp_path / "off.mp4")


@pytest.mark.slow
def test_auto_leaves_a_global_shutter_alone(flights, tmp_path):
    _, gs = flights  # (the command line's run of it: the test below)
    auto = stabilize(gs, tmp_path / "auto.mp4", StabilizeOptions(rolling_shutter="auto"), show_progress=False)
    off = stabilize(gs, tmp_path / "off.mp4", StabilizeOptions(rolling_shutter="off"), show_progress=False)
    assert auto.rolling is not None and not auto.rolling.applied and auto.rolling.readout < 0.1
    np.testing.assert_array_equal(auto.warps, off.warps)


def test_rolling_shutter_refused_live(capsys, tmp_path):
    assert cli_exit(["stabilize", str(tmp_path / "in.mp4"), "-", "--rolling-shutter", "auto", "-q"]) == 2
    err = capsys.readouterr().err
    assert "--rolling-shutter" in err


@pytest.mark.slow
def test_auto_is_the_default_for_a_video_file_and_off_for_a_live_run(flights, tmp_path, capsys):
    """Without --rolling-shutter, stabilize reads a file's rows (a rolling shutter found and
    taken out, a global one left alone); a one-pass run (--latency) goes on without, and only an
    explicit --rolling-shutter there is refused."""
    rs, gs = flights
    assert cli_exit(["stabilize", str(rs), str(tmp_path / "rs.mp4")]) == 0
    assert "(estimated), each row corrected" in capsys.readouterr().err
    assert cli_exit(["stabilize", str(gs), str(tmp_path / "gs.mp4")]) == 0
    assert "a global shutter: left alone" in capsys.readouterr().err
    assert cli_exit(["stabilize", str(rs), str(tmp_path / "live.mp4"), "--latency", "1", "-q"]) == 0
    assert cli_exit(["stabilize", str(rs), str(tmp_path / "live2.mp4"), "--latency", "1", "--rolling-shutter", "auto", "-q"]) == 2
