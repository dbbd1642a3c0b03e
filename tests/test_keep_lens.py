"""``stabilize --keep-lens`` (issue 41, item 3): the output keeps the lens's look, its warps
composed with the lens in one resampling; checked against OpenCV's own lens functions and
against the default (undistorted) output carried back through the lens."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from conftest import cli_exit
from mosaic_cli.geometry.lens import distort_by_table, distort_points, distorted_grid, distortion_table, undistort_points, undistorted_camera
from mosaic_cli.geometry.lens_files import read_lens
from mosaic_cli.stabilize.render import KeptLens

SIZE = (480, 270)


@pytest.fixture(scope="module")
def wide_shaky(tmp_path_factory):
    """A shaky flight through a strong barrel lens (k1 -0.30, k2 0.0225; the bench's focal
    length, 1050 px at 1280 wide: the polynomial covers the frame), with its truth (a lens file)."""
    from mosaic_cli.simulate import SimulateOptions, parse_lens, simulate_flight

    out = tmp_path_factory.mktemp("keep_lens") / "wide.mp4"
    lens = parse_lens(f"-0.30,0.0225,f={1050 * SIZE[0] / 1280}", SIZE)
    simulate_flight(out, None, SimulateOptions(profile="shaky", frames=30, size=SIZE, seed=3, lens=lens), show_progress=False)
    return out


def gray_frames(path):
    from mosaic_cli.video import open_video

    with open_video(path, gray=True) as stream:
        return [np.asarray(f, dtype=np.float64) for f in stream]


def test_distortion_table_reads_the_lens_own_distortion(wide_shaky):
    """The table's bilinear look-up against ``distort_points`` (cv2.projectPoints) over the
    whole footprint, the corners the undistorted frame crops included, and a 120-degree fisheye."""
    from mosaic_cli.geometry.lens import fisheye_lens

    wide = read_lens(wide_shaky.with_suffix(".gt.json"))
    for lens, size in ((wide, SIZE), (wide, (1280, 720)), (fisheye_lens((1280, 720), 1280 / (2 * np.radians(60))), (1280, 720))):
        at = lens.at(size)
        P = undistorted_camera(at)
        pts = np.random.default_rng(0).uniform([-0.5, -0.5], [size[0] - 0.5, size[1] - 0.5], (5000, 2))
        pts[:4] = [[-0.5, -0.5], [size[0] - 0.5, -0.5], [-0.5, size[1] - 0.5], [size[0] - 0.5, size[1] - 0.5]]
        u = undistort_points(at, pts, P)
        x, y = distort_by_table(*distortion_table(lens, size), u[:, 0], u[:, 1])
        # (cv2.remap rounds the look-up to 1/32 of the table's step: distort_by_table's doc)
        assert np.abs(np.stack([x, y], 1) - distort_points(at, u, P)).max() < 0.05
        assert np.abs(np.stack([x, y], 1) - pts).max() < 0.05
        # far outside the footprint: off the frame, never folded back into it
        far_x, far_y = distort_by_table(*distortion_table(lens, size), np.array([-5.0 * size[0]]), np.array([0.5 * size[1]]))
        assert far_x[0] < -size[0]


class _Rows:
    """A RowWarpLater's face: the rolling shutter's correction."""

    def __init__(self, rolling):
        self.rolling = rolling

    def correction(self):
        return self.rolling


@pytest.mark.parametrize("rolling", [False, True], ids=["plain", "rolling-shutter"])
def test_kept_lens_maps_compose_the_warp_with_the_lens(wide_shaky, rolling):
    """Each output pixel p samples distort(W^-1 undistort(p)) (OpenCV's undistortPoints and
    projectPoints in float64), after the row's correction where there is one: within 0.02 px
    (the maps are computed on the chroma grid and resized, as the rolling shutter's), exact on
    the chroma grid itself."""
    from mosaic_cli.geometry.rolling_shutter import undo_row_correction
    from mosaic_cli.stabilize.rolling import RollingCorrection

    lens = read_lens(wide_shaky.with_suffix(".gt.json"))
    w, h = SIZE
    at = lens.at(SIZE)
    P = undistorted_camera(at)
    W = np.array([[1.06, 0.02, -18.0], [-0.015, 1.05, -9.0], [2e-5, -1e-5, 1.0]])  # a crop zoom, shift, roll, tilt
    corr = None
    if rolling:
        rng = np.random.default_rng(1)
        corr = RollingCorrection(0.7, rng.normal(0, 1, (3, 8, 4)) * [1.5, 1.5, 0.002, 0.002], SIZE, False)
    kept = KeptLens(lens, SIZE, cv2.BORDER_REPLICATE, (16, 128, 128), _Rows(corr) if rolling else None)
    mx, my, cx, cy = kept.maps(2, W)
    ij = np.random.default_rng(2).integers([2, 2], [w - 2, h - 2], (400, 2))
    u = undistort_points(at, ij.astype(np.float64), P)
    q = np.c_[u, np.ones(len(u))] @ np.linalg.inv(W).T
    x, y = q[:, 0] / q[:, 2], q[:, 1] / q[:, 2]
    if corr is not None:
        x, y = undo_row_correction(corr.row_channels(2, np.arange(h, dtype=np.float64)), SIZE, x, y)
    truth = distort_points(at, np.stack([x, y], 1), P)
    got = np.stack([mx[ij[:, 1], ij[:, 0]], my[ij[:, 1], ij[:, 0]]], 1)
    # (with rows: the correction looked up at each row, where the luma map interpolates between
    # the chroma grid's rows two apart, as RollingCorrection.warper's: these corrections move up
    # to ~0.06 px from one row to the next)
    assert np.abs(got - truth).max() < (0.1 if rolling else 0.02)
    # the chroma maps: the same points in the half-size planes' own pixels
    cij = ij // 2
    centres = cij * 2 + 0.5
    uc = undistort_points(at, centres, P)
    qc = np.c_[uc, np.ones(len(uc))] @ np.linalg.inv(W).T
    xc, yc = qc[:, 0] / qc[:, 2], qc[:, 1] / qc[:, 2]
    if corr is not None:
        xc, yc = undo_row_correction(corr.row_channels(2, np.arange(h, dtype=np.float64)), SIZE, xc, yc)
    chroma_truth = (distort_points(at, np.stack([xc, yc], 1), P) + 0.5) / 2 - 0.5
    assert np.abs(np.stack([cx[cij[:, 1], cij[:, 0]], cy[cij[:, 1], cij[:, 0]]], 1) - chroma_truth).max() < 0.01


@pytest.mark.slow
def test_keep_lens_writes_the_undistorted_output_through_the_lens(wide_shaky, tmp_path, capsys):
    """With the true lens, the kept-lens output is the default (undistorted) output carried back
    through the lens (cv2.remap by the lens's distorted grid: two resamplings where --keep-lens
    does one), within a grey level and a half on the mean away from the borders, and no closer to
    the default output itself (the lens's bend is there); the warps are the same; the kept-lens
    output samples (almost) nothing from outside the input frame."""
    gt = wide_shaky.with_suffix(".gt.json")
    common = ["-e", "orb", "--no-overlay-detect", "--lens", str(gt), "--crf", "0", "--rolling-shutter", "off"]
    assert cli_exit(["stabilize", wide_shaky, tmp_path / "plain.mp4", "-q", "--warps", tmp_path / "plain.json", *common]) == 0
    assert cli_exit(["stabilize", wide_shaky, tmp_path / "kept.mp4", "--keep-lens", "--warps", tmp_path / "kept.json", *common]) == 0
    assert "keeps the lens's look" in capsys.readouterr().err
    plain_warps = np.array(json.loads((tmp_path / "plain.json").read_text())["warps"])
    assert np.array_equal(plain_warps, np.array(json.loads((tmp_path / "kept.json").read_text())["warps"]))
    plain, kept = gray_frames(tmp_path / "plain.mp4"), gray_frames(tmp_path / "kept.mp4")
    assert len(plain) == len(kept) == 30
    lens = read_lens(gt)
    at = lens.at(SIZE)
    gx, gy = distorted_grid(at, undistorted_camera(at))
    w, h = SIZE
    margin = 8  # away from both frames' borders
    inside = (gx > margin) & (gx < w - 1 - margin) & (gy > margin) & (gy < h - 1 - margin)
    inside[:margin], inside[-margin:], inside[:, :margin], inside[:, -margin:] = False, False, False, False
    again, direct = [], []
    for a, b in zip(plain, kept):
        redistorted = cv2.remap(a, gx.astype(np.float32), gy.astype(np.float32), cv2.INTER_LINEAR)
        again.append(np.abs(redistorted - b)[inside].mean())
        direct.append(np.abs(a - b)[inside].mean())
    assert np.mean(again) < 1.5 and np.max(again) < 2.0, again
    assert np.mean(direct) > 3 * np.mean(again), (direct, again)
    kept_lens = KeptLens(lens, SIZE, cv2.BORDER_REPLICATE, (16, 128, 128))
    off = []
    for W in plain_warps:
        mx, my, _, _ = kept_lens.maps(0, W)
        off.append(np.mean((mx < -0.5) | (my < -0.5) | (mx > w - 0.5) | (my > h - 0.5)))
    assert max(off) < 0.001, max(off)


@pytest.mark.slow
def test_keep_lens_without_a_lens_changes_nothing(wide_shaky, tmp_path, capsys):
    common = ["-e", "orb", "--no-overlay-detect", "--crf", "0", "--rolling-shutter", "off"]
    assert cli_exit(["stabilize", wide_shaky, tmp_path / "plain.mp4", "-q", *common]) == 0
    assert cli_exit(["stabilize", wide_shaky, tmp_path / "kept.mp4", "--keep-lens", *common]) == 0
    assert "no lens applied" in capsys.readouterr().err
    plain, kept = gray_frames(tmp_path / "plain.mp4"), gray_frames(tmp_path / "kept.mp4")
    assert len(plain) == len(kept) and all(np.array_equal(a, b) for a, b in zip(plain, kept))
