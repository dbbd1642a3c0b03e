"""Lenses (issue 41): the camera models against OpenCV, the three lens-file formats with values
checked by hand, bad files, the simulator's lens rendering and ``--lens`` through the pipelines."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from conftest import assert_one_line_error
from mosaic_cli.errors import BadInput
from mosaic_cli.geometry.lens import (
    Lens,
    check_lens_covers,
    corner_displacement,
    distort_points,
    fisheye_lens,
    radial_lens,
    undistort_maps,
    undistort_points,
    undistorted_camera,
)
from mosaic_cli.geometry.lens_files import read_lens

SIZE = (1280, 720)
WIDE = radial_lens(SIZE, 900.0, -0.15, 0.15**2 / 4)  # the issue's test lens: ~71 degrees across
TANGENTIAL = Lens.make("pinhole", SIZE, [[910, 0, 650], [0, 905, 352], [0, 0, 1]], [-0.2, 0.03, 0.001, -0.0015, 0.004])
FISHEYE = fisheye_lens(SIZE, 1280 / (2 * np.radians(60)), (0.02, -0.01, 0.0, 0.0))  # ~120 degrees across


def random_pixels(n=400, size=SIZE, seed=0):
    return np.random.default_rng(seed).uniform([0, 0], [size[0] - 1, size[1] - 1], (n, 2))


@pytest.mark.parametrize("lens", [WIDE, TANGENTIAL, FISHEYE], ids=["radial", "tangential", "fisheye"])
def test_points_round_trip_and_maps_agree_with_opencv(lens):
    pts = random_pixels()
    undist = undistort_points(lens, pts)
    assert np.abs(distort_points(lens, undist) - pts).max() < 1e-3
    # OpenCV's own undistortPoints (default criteria are too loose at the corners: tight ones)
    P = undistorted_camera(lens)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    if lens.model == "fisheye":
        ref = cv2.fisheye.undistortPoints(pts.reshape(-1, 1, 2), lens.K, lens.D, R=np.eye(3), P=P, criteria=crit).reshape(-1, 2)
    else:
        ref = cv2.undistortPoints(pts.reshape(-1, 1, 2), lens.K, lens.D, R=None, P=P, criteria=crit).reshape(-1, 2)
    assert np.abs(undist - ref).max() < 1e-6
    # the remap maps: each undistorted pixel reads the distorted pixel that undistorts onto it
    mx, my = undistort_maps(lens, SIZE)
    ij = random_pixels(200, seed=1).round().astype(int)
    src = np.stack([mx[ij[:, 1], ij[:, 0]], my[ij[:, 1], ij[:, 0]]], 1)
    assert np.abs(undistort_points(lens, src) - ij).max() < 1e-3
    # every undistorted pixel sees the source frame (no black corners): within half a pixel
    assert mx.min() > -0.5 and my.min() > -0.5 and mx.max() < SIZE[0] - 0.5 + 0.5 and my.max() < SIZE[1] - 0.5 + 0.5


def test_new_camera_keeps_square_pixels_and_the_lens_scales_with_the_frame():
    P = undistorted_camera(WIDE)
    assert P[0, 0] == pytest.approx(P[1, 1]) and P[0, 0] < 900  # a barrel lens: zoomed out, not stretched
    half = WIDE.at((640, 360))
    assert half.K[0, 0] == pytest.approx(450.0) and half.K[0, 2] == pytest.approx((639.5 + 0.5) / 2 - 0.5)
    pts = random_pixels(50)
    small = (pts + 0.5) / 2 - 0.5
    assert np.allclose((undistort_points(WIDE, pts, WIDE.K) + 0.5) / 2 - 0.5, undistort_points(half, small, half.K), atol=1e-6)
    with pytest.raises(ValueError, match="aspect"):
        WIDE.at((640, 480))


def test_corner_displacement_of_the_issue_lens():
    # The issue's lens: a 10% radial shift at the corners (radius 734 px at 1280x720)
    radius = np.hypot(639.5, 359.5)
    assert 0.09 * radius < corner_displacement(WIDE) < 0.16 * radius


def test_a_lens_that_folds_inside_the_frame_is_refused():
    with pytest.raises(ValueError, match="folds"):
        check_lens_covers(radial_lens(SIZE, 900.0, -0.30, 0.30**2 / 4))  # corners past the polynomial's turn
    check_lens_covers(radial_lens(SIZE, 1050.0, -0.30, 0.30**2 / 4))


# -- the readers -----------------------------------------------------------------------------------


def write(tmp_path, name, doc):
    path = tmp_path / name
    path.write_text(json.dumps(doc) if not isinstance(doc, str) else doc)
    return path


def test_mosaic_lens_file(tmp_path):
    path = write(tmp_path, "lens.json", TANGENTIAL.to_json())
    assert read_lens(path) == TANGENTIAL


def test_gyroflow_profile(tmp_path):
    # As Gyroflow's calibrator writes one (its lens_profiles database): fisheye_params at calib_dimension
    doc = {
        "name": "GoPro_HERO9 Black_Wide_16by9", "calibrated_by": "test", "camera_brand": "GoPro", "camera_model": "HERO9 Black",
        "lens_model": "Wide", "camera_setting": "", "calib_dimension": {"w": 2704, "h": 1520},
        "orig_dimension": {"w": 2704, "h": 1520}, "output_dimension": {"w": 2704, "h": 1520},
        "frame_readout_time": 8.9, "input_horizontal_stretch": 1.0, "input_vertical_stretch": 1.0, "num_images": 12,
        "fps": 59.94, "official": True, "asymmetrical": False,
        "fisheye_params": {"RMS_error": 0.41, "camera_matrix": [[1184.6, 0.0, 1352.3], [0.0, 1182.9, 758.7], [0.0, 0.0, 1.0]],
                           "distortion_coeffs": [0.051, 0.012, -0.004, 0.0008]},
        "distortion_model": "opencv_fisheye", "calibrator_version": "1.5.0", "date": "2023-04-01",
    }
    lens = read_lens(write(tmp_path, "gopro.json", doc))
    assert lens.model == "fisheye" and lens.size == (2704, 1520)
    assert lens.K[0, 0] == 1184.6 and lens.K[1, 2] == 758.7 and lens.coefficients == (0.051, 0.012, -0.004, 0.0008)
    # at a 1352x760 video, half of everything (pixel centres: cx' = (cx + 0.5) / 2 - 0.5)
    assert lens.at((1352, 760)).K[0, 0] == pytest.approx(592.3) and lens.at((1352, 760)).K[0, 2] == pytest.approx(675.9)
    standard = dict(doc, distortion_model="opencv_standard", fisheye_params={**doc["fisheye_params"], "distortion_coeffs": [-0.2, 0.04, 0.0, 0.0, 0.0]})
    assert read_lens(write(tmp_path, "std.json", standard)).model == "pinhole"
    with pytest.raises(BadInput, match="poly3"):
        read_lens(write(tmp_path, "poly.json", dict(doc, distortion_model="poly3")))


def test_opensfm_cameras_json(tmp_path):
    # ODM writes OpenSfM's cameras.json: focal and principal offsets normalised by max(w, h)
    brown = {"v2 dji fc6310 4000 3000 brown 0.85 rgb": {
        "projection_type": "brown", "width": 4000, "height": 3000, "focal_x": 0.85, "focal_y": 0.8525,
        "c_x": 0.01, "c_y": -0.005, "k1": -0.12, "k2": 0.03, "p1": 0.001, "p2": -0.0005, "k3": -0.002}}
    lens = read_lens(write(tmp_path, "cameras.json", brown))
    assert lens.model == "pinhole" and lens.size == (4000, 3000)
    assert lens.K[0, 0] == pytest.approx(3400.0) and lens.K[1, 1] == pytest.approx(3410.0)
    assert lens.K[0, 2] == pytest.approx(2000 + 40 - 0.5) and lens.K[1, 2] == pytest.approx(1500 - 20 - 0.5)
    assert lens.coefficients == (-0.12, 0.03, 0.001, -0.0005, -0.002)
    fish = {"gopro": {"projection_type": "fisheye", "width": 1920, "height": 1080, "focal": 0.5, "k1": 0.02, "k2": -0.003}}
    lens = read_lens(write(tmp_path, "fish.json", fish))
    assert lens.model == "fisheye" and lens.K[0, 0] == pytest.approx(960.0) and lens.K[1, 2] == pytest.approx(539.5)
    assert lens.coefficients == (0.02, -0.003, 0.0, 0.0)
    persp = {"cam": {"projection_type": "perspective", "width": 1280, "height": 720, "focal": 0.7, "k1": -0.1, "k2": 0.01}}
    assert read_lens(write(tmp_path, "p.json", persp)).coefficients == (-0.1, 0.01, 0.0, 0.0, 0.0)


@pytest.mark.parametrize("content, fragment", [
    ("not json {", "not a JSON file"),
    ('{"hello": 1}', "not a lens file"),
    ('{"model": "pinhole", "size": [640, 480], "camera_matrix": [[1, 0], [0, 1]], "coefficients": [0, 0, 0, 0]}', "camera matrix"),
    ('{"model": "fisheye", "size": [640, 480], "camera_matrix": [[500, 0, 320], [0, 500, 240], [0, 0, 1]], "coefficients": [0.1]}', "4 coefficients"),
    ('{"model": "pinhole", "size": [640, 480], "camera_matrix": [[500, 0, 320], [0, 500, 240], [0, 0, 1]]}', "missing"),
    ('{"a": {"projection_type": "spherical", "width": 10, "height": 10}}', "spherical"),
    ('{"a": {"projection_type": "brown", "width": 10, "height": 10}, "b": {"projection_type": "brown"}}', "2 cameras"),
])
def test_bad_lens_files_are_one_clear_line(tmp_path, content, fragment):
    with pytest.raises(BadInput, match=fragment):
        read_lens(write(tmp_path, "bad.json", content))


# -- the simulator ---------------------------------------------------------------------------------


def test_simulated_lens_puts_a_map_point_where_the_lens_says(texture):
    from mosaic_cli.simulate import parse_lens
    from mosaic_cli.simulate.render import LensGrid, MapPyramid, render_lens

    size = (320, 180)
    lens = parse_lens("-0.2,0.01", size)
    assert lens.K[0, 0] == pytest.approx(900 / 1280 * 320)
    # a map of one bright dot: the frame shows it where the lens images its pinhole pixel
    dot = np.zeros((400, 600, 3), np.uint8)
    cv2.circle(dot, (310, 190), 2, (255, 255, 255), -1)
    map_to_frame = np.array([[1.0, 0, -20], [0, 1.0, -30], [0, 0, 1]])  # map (310, 190) -> pinhole (290, 160): near a corner
    frame = render_lens(MapPyramid(dot), map_to_frame, LensGrid(lens))
    gray = frame[..., 0].astype(np.float64)
    ys, xs = np.nonzero(gray > 20)
    seen = np.array([np.average(xs, weights=gray[ys, xs]), np.average(ys, weights=gray[ys, xs])])
    expected = distort_points(lens, np.array([[290.0, 160.0]]), lens.K)[0]
    assert np.linalg.norm(expected - [290, 160]) > 5  # the lens moves it visibly ...
    assert np.linalg.norm(seen - expected) < 0.5  # ... and the frame shows it there


def test_simulated_fisheye_keeps_the_pinholes_sharpness_at_its_centre(texture):
    """A real fisheye squeezes the ground at its edges only: the simulator picks each pixel's map
    level by the lens's local stretch there, so the frame's centre is as sharp as the pinhole
    frame's (one level for the whole frame, the corners', blurred it), and the squeezed corners
    still do not alias (their detail is no more than the pinhole frame's there)."""
    from mosaic_cli.simulate import parse_lens
    from mosaic_cli.simulate.render import LensGrid, MapPyramid, render_lens, render_view

    size = (320, 180)
    lens = parse_lens("fisheye", size)
    pyramid = MapPyramid(texture)
    map_to_frame = np.array([[0.5, 0, -100], [0, 0.5, -80], [0, 0, 1]])  # the map at half size: detail to spare
    fisheye = cv2.cvtColor(render_lens(pyramid, map_to_frame, LensGrid(lens)), cv2.COLOR_RGB2GRAY).astype(np.float64)
    pinhole = cv2.cvtColor(render_view(pyramid, map_to_frame, size), cv2.COLOR_RGB2GRAY).astype(np.float64)

    def detail(gray: np.ndarray, x0: int, y0: int, side: int = 40) -> float:
        return float(cv2.Laplacian(gray, cv2.CV_64F)[y0 : y0 + side, x0 : x0 + side].std())

    centre = (size[0] // 2 - 20, size[1] // 2 - 20)
    assert detail(fisheye, *centre) > 0.85 * detail(pinhole, *centre)
    # the corner shows 3-4x more ground per pixel: area-averaged, it has no more detail than the pinhole's
    assert detail(fisheye, 0, 0, 24) < 1.5 * detail(pinhole, 0, 0, 24)


@pytest.mark.parametrize("text, fragment", [("-0.3,0.0225", "folds"), ("a,b", "--lens must be"), ("fisheye:1,2,3,4,5", "at most 4"),
                                            ("0.1,f=-3", "focal")])
def test_simulate_lens_syntax(text, fragment):
    from mosaic_cli.simulate import SimulateOptions, parse_lens

    with pytest.raises(BadInput, match=fragment):
        SimulateOptions(size=(1280, 720), lens=parse_lens(text, (1280, 720)))


@pytest.fixture(scope="module")
def wide_flight(tmp_path_factory):
    """A short survey flight at 480x270 through the issue's wide lens (k1 -0.15, ~71 degrees)."""
    from mosaic_cli.simulate import SimulateOptions, parse_lens, simulate_flight

    out = tmp_path_factory.mktemp("lens") / "wide.mp4"
    size = (480, 270)
    simulate_flight(out, None, SimulateOptions(profile="survey", frames=40, size=size, seed=3, lens=parse_lens("-0.15,0.005625", size)),
                    show_progress=False)
    return out


def pair_errors(track_path, gt_path):
    """Each pair's mean error at the frame's corners (px) against the truth, carried into the
    track's own frame (undistorted by the lens it used, if any)."""
    from mosaic_cli.geometry.lens_files import mosaic_lens
    from mosaic_cli.simulate import load_ground_truth

    gt = load_ground_truth(gt_path)
    w, h = gt.size
    true = read_lens(gt_path)
    doc = json.loads(track_path.read_text())
    meta = doc["meta"]["lens"]
    used = mosaic_lens(meta["lens"]).at(gt.size) if meta["applied"] else None
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)

    def to_pinhole(p):
        return undistort_points(true, distort_points(used, p) if used is not None else p, true.K)

    def from_pinhole(p):
        p = distort_points(true, p, true.K)
        return undistort_points(used, p) if used is not None else p

    errors = []
    for H, T in zip(np.array(doc["pairwise"]), gt.pairwise):
        q = np.c_[to_pinhole(corners), np.ones(4)] @ T.T
        q = from_pinhole(q[:, :2] / q[:, 2:])
        a = np.c_[corners, np.ones(4)] @ H.T
        errors.append(np.linalg.norm(a[:, :2] / a[:, 2:] - q, axis=1).mean())
    return np.array(errors)


def test_track_with_the_true_lens_matches_the_pinhole_truth(wide_flight, tmp_path, capsys):
    from conftest import cli_exit

    gt = wide_flight.with_suffix(".gt.json")
    for name, lens in (("none", "none"), ("file", str(gt))):
        assert cli_exit(["track", wide_flight, "-o", tmp_path / f"{name}.json", "-e", "orb", "-q", "--no-overlay-detect", "--lens", lens]) == 0
    none = np.median(pair_errors(tmp_path / "none.json", gt))
    given = np.median(pair_errors(tmp_path / "file.json", gt))
    assert given < 0.6 * none, (given, none)


def test_bad_lens_file_on_the_command_line_is_one_error_line(wide_flight, tmp_path, capsys):
    from conftest import run_cli

    bad = tmp_path / "lens.json"
    bad.write_text('{"model": "fisheye", "size": [480, 270], "camera_matrix": [[300, 0, 240], [0, 300, 135], [0, 0, 1]], "coefficients": [1]}')
    code, err = run_cli(capsys, "track", wide_flight, "-o", tmp_path / "t.json", "-e", "orb", "-q", "--lens", bad)
    assert_one_line_error(code, err, "4 coefficients")
    code, err = run_cli(capsys, "stitch", wide_flight, "-o", tmp_path / "p.png", "-e", "orb", "-q", "--lens", tmp_path / "missing.json")
    assert_one_line_error(code, err, "no such file")
    other = tmp_path / "43.json"
    other.write_text(json.dumps(radial_lens((640, 480), 500, -0.1).to_json()))
    code, err = run_cli(capsys, "stabilize", wide_flight, tmp_path / "s.mp4", "-e", "orb", "-q", "--lens", other)
    assert_one_line_error(code, err, "aspect")


@pytest.mark.parametrize("coefficients", [(-0.3,), (-0.12, -0.09), (-0.48, -0.05), (0.1, -0.05)])
def test_division_model_round_trips_with_one_or_two_coefficients(coefficients):
    from mosaic_cli.geometry.lens import division_lens

    lens = division_lens((640, 360), *coefficients)
    pts = random_pixels(500, (640, 360))
    for P in (None, lens.K):
        back = distort_points(lens, undistort_points(lens, pts, P), P)
        assert np.max(np.abs(back - pts)) < 1e-6
    # the undistorted frame's every pixel sees the source
    mx, my = undistort_maps(lens, (640, 360))
    assert np.all(np.isfinite(mx)) and mx.min() >= -0.5 and mx.max() <= 639.5 and my.min() >= -0.5 and my.max() <= 359.5


@pytest.mark.slow
def test_auto_fits_two_coefficients_to_a_strong_lens_and_a_fisheye():
    """The fit itself, on exact synthetic matches (no video): pairs of views of random ground
    points related by homographies, seen through a strong polynomial lens (k1 -0.30 at 71 degrees)
    and a 120-degree fisheye; the estimate reproduces the corners within 10% (one division
    coefficient: 27% and 19%)."""
    from mosaic_cli.estimators.lens import fit_lens
    from mosaic_cli.geometry.lens import corner_error

    size = (640, 360)
    rng = np.random.default_rng(5)
    for truth in (radial_lens(size, 525.0, -0.30, 0.0225), fisheye_lens(size, 320 / np.radians(60))):
        pairs = []
        for _ in range(8):  # 8 pairs of 200 matches fit within 1% (30 of 400: the same, 10x the time)
            a = random_pixels(200, size, int(rng.integers(1 << 30)))
            shift = rng.uniform(-0.25, 0.25, 2) * size
            H = np.array([[1, 0.01, shift[0]], [-0.01, 1, shift[1]], [1e-5, 0, 1]])
            ua = undistort_points(truth, a, truth.K)
            ub = np.c_[ua, np.ones(len(ua))] @ H.T
            b = distort_points(truth, ub[:, :2] / ub[:, 2:], truth.K)
            inside = np.all((b >= 0) & (b <= np.array(size) - 1), axis=1)
            pairs.append((a[inside], b[inside] + rng.normal(0, 0.1, b[inside].shape)))
        estimate, _, _ = fit_lens(pairs, size)
        assert corner_error(estimate, truth) < 0.1 * corner_displacement(truth), (truth.model, estimate)


def test_auto_refinement_matches_are_exact_through_a_wrong_lens(texture):
    """``auto``'s refinement matches frame i against frame j resampled onto i's pixels through
    the first estimate: the matches it gives hold for the true lens, however far off the lens it
    resampled with (here a division lens for a 120-degree fisheye, 3% or more off at the corners),
    to a few hundredths of a pixel (median 0.04 px), out to the corners."""
    from mosaic_cli.estimators.lens import _aligned_pairs
    from mosaic_cli.geometry.lens import corner_error, division_lens
    from mosaic_cli.simulate.render import LensGrid, MapPyramid, render_lens

    size = (640, 360)
    truth = fisheye_lens(size, 320 / np.radians(60))
    gray = cv2.cvtColor(texture, cv2.COLOR_RGB2GRAY)
    pyramid = MapPyramid(np.repeat(gray[..., None], 3, 2))
    Ti = np.array([[1.0, 0, -500], [0, 1.0, -300], [0, 0, 1]])  # map -> pinhole frame i (camera truth.K)
    Tj = np.array([[0.99, 0.02, -640], [-0.02, 0.99, -330], [0, 0, 1]])
    frames = [render_lens(pyramid, T, LensGrid(truth))[..., 0] for T in (Ti, Tj)]
    H = Tj @ np.linalg.inv(Ti)  # pinhole i -> pinhole j

    def through(points):  # frame i's pixels -> frame j's, by the truth
        q = np.c_[undistort_points(truth, points, truth.K), np.ones(len(points))] @ H.T
        return distort_points(truth, q[:, :2] / q[:, 2:], truth.K)

    a = random_pixels(300, size, 3)
    b = through(a)
    inside = np.all((b >= 0) & (b <= np.array(size) - 1), axis=1)
    wrong = division_lens(size, -0.45, -0.06)
    assert corner_error(wrong, truth) > 0.03 * corner_displacement(truth)
    [(a2, b2)] = _aligned_pairs(frames, [(0, 1)], [(a[inside], b[inside])], wrong)
    err = np.linalg.norm(b2 - through(a2), axis=1)
    assert len(a2) > 200 and np.median(err) < 0.08 and np.percentile(err, 95) < 0.25, (len(a2), np.median(err), np.percentile(err, 95))
    corner = np.linalg.norm(a2 - np.array(size) / 2, axis=1) > 0.8 * np.hypot(*size) / 2
    assert corner.sum() >= 5  # the matches reach the corners


@pytest.mark.slow
def test_auto_recovers_the_lens_and_leaves_a_pinhole_alone(wide_flight, tmp_path):
    from mosaic_cli.estimators.lens import estimate_lens
    from mosaic_cli.geometry.lens import corner_error
    from mosaic_cli.simulate import SimulateOptions, simulate_flight
    from mosaic_cli.video import probe

    truth = read_lens(wide_flight.with_suffix(".gt.json"))
    choice = estimate_lens(probe(wide_flight))
    assert choice.lens is not None
    # the issue's goal: 10% of the corner displacement (one division coefficient reached ~15%)
    assert corner_error(choice.lens, truth) < 0.1 * corner_displacement(truth)
    pinhole = tmp_path / "pinhole.mp4"
    simulate_flight(pinhole, None, SimulateOptions(profile="survey", frames=40, size=(480, 270), seed=3), show_progress=False)
    assert estimate_lens(probe(pinhole)).lens is None


@pytest.mark.slow
def test_auto_finds_a_fisheye_on_a_hovering_shaky_flight(tmp_path):
    """A camera that hovers and shakes moves a few pixels between the samples: `auto` used to ask
    3% of the width of a pair and found no pair at all on such a fisheye flight (a pinhole by
    default, and the output stayed bent).  Its shaky pinhole twin is still left alone."""
    from mosaic_cli.estimators.lens import estimate_lens
    from mosaic_cli.geometry.lens import corner_error
    from mosaic_cli.simulate import SimulateOptions, parse_lens, simulate_flight
    from mosaic_cli.video import probe

    size = (480, 270)
    fisheye, pinhole = tmp_path / "fisheye.mp4", tmp_path / "pinhole.mp4"
    simulate_flight(fisheye, None, SimulateOptions(profile="shaky", frames=60, size=size, seed=4, lens=parse_lens("fisheye", size)),
                    show_progress=False)
    simulate_flight(pinhole, None, SimulateOptions(profile="shaky", frames=60, size=size, seed=4), show_progress=False)
    truth = read_lens(fisheye.with_suffix(".gt.json"))
    choice = estimate_lens(probe(fisheye))
    assert choice.lens is not None, choice.describe()
    assert corner_error(choice.lens, truth) < 0.1 * corner_displacement(truth)
    assert estimate_lens(probe(pinhole)).lens is None
