"""``mosaic stitch`` against exact ground truth: survey flights rendered over a known map, so
every frame's true map -> frame homography is known and any placement can be checked."""

from __future__ import annotations

import dataclasses
import json
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from benchmarks import common
from conftest import run_cli, textured_image
from mosaic_cli.errors import ProcessingError
from mosaic_cli.estimators import Estimator
from mosaic_cli.estimators.orb import OrbConfig, OrbEstimator
from mosaic_cli.geometry import corner_error, frame_corners, normalize, project
from mosaic_cli.simulate import MapPyramid, plan_flight, render_frames, render_view
from mosaic_cli.stitch import RegistrationOptions, StitchOptions, stitch
from mosaic_cli.stitch.compose import ComposeOptions, PlacedImage, compose, tile_count
from mosaic_cli.stitch.features import PairMatch
from mosaic_cli.stitch.keyframes import Keyframe, KeyframeStore
from mosaic_cli.stitch.registration import Link, RegistrationReport, chain_sequence, link_from_match, refine_placements
from mosaic_cli.stitch.spill import SpilledImage
from mosaic_cli.video import VideoWriter

SIZE = (256, 144)
MAP_SIZE = (1024, 1024)


@dataclasses.dataclass
class Flight:
    path: Path
    map_to_frame: np.ndarray  # (N, 3, 3) exact
    map: np.ndarray


@pytest.fixture(scope="module")
def ground() -> np.ndarray:
    return textured_image(*MAP_SIZE, seed=5)


def fly(path: Path, ground: np.ndarray, frames: int = 200, step: int = 4, seed: int = 2, edit=None, fps: float = 30.0) -> Flight:
    """A lawnmower survey (neighbouring lines overlap: ground is revisited), every ``step``-th
    frame of the simulator's, so that small frames still move a few pixels per frame."""
    plan = plan_flight(MAP_SIZE, "survey", frames=frames * step, size=SIZE, seed=seed)
    plan = dataclasses.replace(plan, map_to_frame=plan.map_to_frame[::step], smooth_map_to_frame=plan.smooth_map_to_frame[::step])
    with VideoWriter(path, SIZE, fps, crf=16, preset="veryfast") as writer:
        for k, frame in enumerate(render_frames(ground, plan)):
            writer.write(edit(k, frame) if edit else frame)
    return Flight(path, plan.map_to_frame, ground)


def fast_orb() -> Estimator:
    return OrbEstimator(SIZE[0], OrbConfig(refine=None))


def load_transforms(path: Path) -> tuple[tuple[int, int], list[int], list[np.ndarray]]:
    data = json.loads(Path(path).read_text())
    return tuple(data["canvas_size"]), [f["index"] for f in data["frames"]], [np.array(f["H"]) for f in data["frames"]]


def placement_errors(indices, frame_to_pano, map_to_frame, gap: int) -> np.ndarray:
    """:func:`benchmarks.common.placement_errors` at this file's frame size."""
    return common.placement_errors(indices, frame_to_pano, map_to_frame, SIZE, gap)


def plain_chain(video: Path, indices: list[int]) -> list[np.ndarray]:
    """:func:`benchmarks.common.plain_chain` with ORB's patch and RANSAC's threshold for these small frames."""
    return common.plain_chain(video, indices, features=2000, patch=15, ransac_px=2.0)


def read_rgba(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None, path
    return image


# -- a survey flight stitched once, checked many ways ----------------------------------------


@pytest.fixture(scope="module")
def survey(tmp_path_factory, ground):
    folder = tmp_path_factory.mktemp("survey")
    flight = fly(folder / "survey.mp4", ground)
    pano, transforms = folder / "pano.png", folder / "pano.json"
    result = stitch(flight.path, pano, fast_orb(), transforms=transforms, show_progress=False)
    return flight, pano, transforms, result


@pytest.mark.slow
def test_transforms_place_the_known_map_where_the_panorama_shows_it(survey):
    flight, pano, transforms, result = survey
    canvas, indices, H = load_transforms(transforms)
    rgba = read_rgba(pano)
    assert rgba.shape == (canvas[1], canvas[0], 4)
    assert len(indices) == result.keyframes >= 5 and indices == sorted(indices)
    # Through every used frame, a map point must land on the same panorama pixel.
    map_to_pano = [normalize(H_i @ flight.map_to_frame[i]) for H_i, i in zip(H, indices)]
    centre = np.mean([project(np.linalg.inv(flight.map_to_frame[i]), frame_corners(*SIZE)).mean(axis=0) for i in indices], axis=0)
    landed = np.array([project(A, centre[None])[0] for A in map_to_pano])
    assert np.max(np.linalg.norm(landed - np.median(landed, axis=0), axis=1)) < 2.0
    # And the panorama there shows that map: warp the map by map -> panorama and compare.
    expected = render_view(MapPyramid(flight.map), map_to_pano[len(map_to_pano) // 2], canvas)
    inside = cv2.erode((rgba[..., 3] == 255).astype(np.uint8), np.ones((7, 7), np.uint8), borderValue=0).astype(bool)
    got = cv2.cvtColor(rgba[..., :3], cv2.COLOR_BGR2RGB).astype(np.float32)[inside]
    want = expected.astype(np.float32)[inside]
    assert inside.mean() > 0.4
    assert np.mean(np.abs(got - want)) < 8.0
    assert np.corrcoef(got.ravel(), want.ravel())[0, 1] > 0.95


@pytest.mark.slow
def test_drift_control_beats_plain_chaining(survey):
    flight, _, transforms, result = survey
    _, indices, H = load_transforms(transforms)
    assert result.registration.loops >= 3  # neighbouring survey lines were registered directly
    ours = placement_errors(indices, H, flight.map_to_frame, gap=60)
    chained = placement_errors(indices, plain_chain(flight.path, indices), flight.map_to_frame, gap=60)
    assert len(ours) >= 10
    assert np.median(ours) < 1.0
    assert np.median(ours) <= 0.5 * np.median(chained)


@pytest.mark.slow
def test_alpha_is_zero_exactly_outside_the_covered_ground(survey):
    flight, pano, transforms, _ = survey
    canvas, indices, H = load_transforms(transforms)
    alpha = read_rgba(pano)[..., 3]
    assert set(np.unique(alpha)) <= {0, 255}
    # True footprints (from the exact homographies) of the used frames, on the canvas.
    map_to_pano = normalize(H[0] @ flight.map_to_frame[indices[0]])
    union = np.zeros((canvas[1], canvas[0]), np.uint8)
    for i in indices:
        quad = project(map_to_pano @ np.linalg.inv(flight.map_to_frame[i]), frame_corners(*SIZE))
        cv2.fillConvexPoly(union, np.round(quad * 16).astype(np.int32), 1, shift=4)
    first = np.zeros_like(union)
    cv2.fillConvexPoly(first, np.round(project(H[0], frame_corners(*SIZE)) * 16).astype(np.int32), 1, shift=4)
    kernel = np.ones((7, 7), np.uint8)
    outside = cv2.dilate(union, kernel) == 0
    assert outside.sum() > 1000  # a survey leaves parts of its bounding box unseen
    assert np.all(alpha[outside] == 0)
    inside = cv2.erode(first, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    assert inside.sum() > 10000 and np.all(alpha[inside == 1] == 255)


@pytest.mark.slow
def test_max_size_bounds_the_canvas_and_the_transforms_follow(survey, tmp_path):
    flight, _, _, full = survey
    pano, transforms = tmp_path / "small.jpg", tmp_path / "small.json"
    result = stitch(flight.path, pano, fast_orb(), StitchOptions(canvas=dataclasses.replace(StitchOptions().canvas, max_size=200)),
                    transforms=transforms, show_progress=False)
    canvas, indices, H = load_transforms(transforms)
    # The shrink is said, naming both sizes: the full-size stitch's canvas and this one's.
    from mosaic_cli.commands.stitch import _notices

    native = result.panoramas[0].shrunk_from
    assert native is not None and np.abs(np.subtract(native, full.canvas_size)).max() <= 1  # (the bounds' rounding)
    said = f"{pano}: scaled down from {native[0]}x{native[1]} to {canvas[0]}x{canvas[1]} by --max-size 200"
    assert [line for line in _notices(flight.path, result) if "scaled down" in line] == [said]
    image = read_rgba(pano)
    assert max(canvas) <= 200 and image.shape[:2] == (canvas[1], canvas[0]) and image.ndim == 3
    assert max(canvas) >= 195
    scale = max(canvas) / max(full.canvas_size)
    errors = placement_errors(indices, H, flight.map_to_frame, gap=1)
    assert np.median(errors) < 1.5  # frame <-> frame placement survives the canvas scale
    # Frame -> panorama is the full-size one, scaled.
    ratio = np.linalg.norm(project(H[0], frame_corners(*SIZE))[1] - project(H[0], frame_corners(*SIZE))[0])
    full_H = dict(full.transforms)[indices[0]]
    full_ratio = np.linalg.norm(project(full_H, frame_corners(*SIZE))[1] - project(full_H, frame_corners(*SIZE))[0])
    assert ratio / full_ratio == pytest.approx(scale, rel=0.02)


@pytest.mark.slow
def test_without_drift_control_keyframes_are_only_chained_and_placed_worse(survey, tmp_path):
    flight, _, transforms, _ = survey
    options = StitchOptions(registration=RegistrationOptions(enabled=False))
    result = stitch(flight.path, tmp_path / "p.png", fast_orb(), options, transforms=tmp_path / "t.json", show_progress=False)
    assert result.registration.loops == 0
    _, indices, H = load_transforms(tmp_path / "t.json")
    _, ref_indices, ref_H = load_transforms(transforms)
    assert np.median(placement_errors(indices, H, flight.map_to_frame, 60)) > 1.5 * np.median(
        placement_errors(ref_indices, ref_H, flight.map_to_frame, 60)
    )


# -- keyframe choice and broken chains --------------------------------------------------------

BLURRED = set(range(0, 200)) - set(range(0, 200, 3))
BLACK = {70, 71, 72}
BRIGHT = {120, 121}


def spoil(k: int, frame: np.ndarray) -> np.ndarray:
    if k in BLACK:
        return np.zeros_like(frame)
    if k in BRIGHT:
        return np.full_like(frame, 255)
    if k in BLURRED:
        return cv2.GaussianBlur(frame, (0, 0), 1.5)
    return frame


@pytest.mark.slow
def test_keyframes_skip_blurred_black_and_overexposed_frames_and_bridge_them(tmp_path, ground):
    flight = fly(tmp_path / "spoilt.mp4", ground, edit=spoil)
    result = stitch(flight.path, tmp_path / "p.png", fast_orb(), transforms=tmp_path / "t.json", show_progress=False)
    _, indices, H = load_transforms(tmp_path / "t.json")
    assert not set(indices) & (BLURRED | BLACK | BRIGHT)
    # The estimator fails on the black and white frames; the flight is re-found after them.
    assert indices[-1] > max(BRIGHT)
    assert np.median(placement_errors(indices, H, flight.map_to_frame, 30)) < 1.5
    assert result.keyframes >= 5


class DivergingEstimator(Estimator):
    """A broken estimator: each pairwise homography adds a little perspective, so the chain
    tips over (frames mapped behind the camera) within a hundred frames."""

    name = "diverging"

    def _estimate(self, prev, cur):
        return np.array([[1.0, 0, 1.0], [0, 1.0, 0], [4e-4, 2e-4, 1.0]]), 1.0


def test_a_degenerate_chain_is_refused_with_advice_instead_of_a_huge_canvas(tmp_path, ground):
    flight = fly(tmp_path / "f.mp4", ground, frames=150)
    out = tmp_path / "p.png"
    with pytest.raises(ProcessingError, match="degenerate.*canvas would explode.*--estimator"):
        stitch(flight.path, out, DivergingEstimator(SIZE[0]), show_progress=False)
    assert not out.exists() and list(tmp_path.glob("*.png")) == []


# -- formats, references, errors ---------------------------------------------------------------


@pytest.fixture(scope="module")
def short_clip(tmp_path_factory, ground) -> Path:
    return fly(tmp_path_factory.mktemp("short") / "short.mp4", ground, frames=40).path


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, channels, magic",
    [("p.png", 4, b"\x89PNG"), ("p.jpg", 3, b"\xff\xd8\xff"), ("p.JPEG", 3, b"\xff\xd8\xff"), ("p.tif", 4, b"II*\x00"), ("p.tiff", 4, b"II*\x00")],
)
def test_format_follows_the_extension(short_clip, tmp_path, capsys, name, channels, magic):
    out = tmp_path / name
    code, err = run_cli(capsys, "stitch", short_clip, "-o", out, "-e", "orb", "--work-width", 128, "--no-drift-control", "-q")
    assert code == 0, err
    assert out.read_bytes()[:4].startswith(magic[:3]) and out.read_bytes()[:4] in (magic, magic[:3] + out.read_bytes()[3:4])
    image = read_rgba(out)
    assert (image.shape[2] if image.ndim == 3 else 1) == channels
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]  # no temporary file left


@pytest.mark.slow
def test_reference_first_draws_the_first_keyframe_upright(short_clip, tmp_path, capsys):
    code, err = run_cli(capsys, "stitch", short_clip, "-o", tmp_path / "p.png", "--transforms", tmp_path / "t.json",
                        "--reference", "first", "-e", "orb", "--work-width", 128, "-q")
    assert code == 0, err
    _, indices, H = load_transforms(tmp_path / "t.json")
    A = H[0] / H[0][2, 2]
    assert indices[0] == 0
    assert np.allclose(A[2, :2], 0, atol=1e-9) and np.allclose(A[:2, :2], A[0, 0] * np.eye(2), atol=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize(
    "args, fragment",
    [
        (["-o", "{out}/p.gif"], ".png, .jpg"),
        (["-o", "{out}/p.png", "--reference", "sideways"], "--reference"),
        (["-o", "{out}/p.png", "--reference", "-3"], "--reference"),
        (["-o", "{out}/p.png", "--reference", "5000"], "past the end"),
        (["-o", "{out}/missing/p.png"], "does not exist"),
        (["-o", "{out}/p.png", "--blend", "smudge"], "--blend"),
        (["-o", "{out}/p.png", "--seam", "zip"], "--seam"),
        (["-o", "{out}/p.png", "--max-size", "10"], "--max-size"),
        (["-o", "{out}/p.png", "--overlap", "1.5"], "--overlap"),
        (["-o", "{out}/p.png", "--transforms", "{out}/t.txt"], ".json"),
        (["-o", "{out}/p.png", "--max-loop-pairs", "-1"], "--max-loop-pairs"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_no_file(short_clip, tmp_path, capsys, args, fragment):
    out = tmp_path / "out"
    out.mkdir()
    code, err = run_cli(capsys, "stitch", short_clip, *[a.format(out=out) for a in args], "-q")
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mosaic: error: ") and fragment in lines[0]
    assert list(out.iterdir()) == []


def test_the_library_builds_the_estimator_its_options_name_once_the_input_is_checked(short_clip, tmp_path, monkeypatch):
    from mosaic_cli.errors import BadInput
    from mosaic_cli.stitch import CanvasOptions
    from mosaic_cli.stitch import scan as stitch_scan

    built = []
    real = stitch_scan.plan_estimator

    def spy(name=None, **kwargs):
        built.append((name, kwargs))
        return real(name, **kwargs)

    monkeypatch.setattr(stitch_scan, "plan_estimator", spy)
    late = StitchOptions(estimator="orb", canvas=CanvasOptions(reference="5000"))
    with pytest.raises(BadInput, match="past the end"):
        stitch(short_clip, tmp_path / "p.png", options=late, show_progress=False)
    assert built == []  # refused before the estimator (a learned one loads weights)
    options = StitchOptions(estimator="orb", work_width=128, registration=RegistrationOptions(enabled=False))
    result = stitch(short_clip, tmp_path / "p.png", options=options, show_progress=False)
    assert built == [("orb", {"work_width": 128, "weights": None, "device": "auto"})]
    assert len(result.transforms) >= 2 and (tmp_path / "p.png").stat().st_size > 0


def test_missing_or_unreadable_video_is_one_line_exit_2(tmp_path, capsys):
    (tmp_path / "out").mkdir()
    code, err = run_cli(capsys, "stitch", tmp_path / "nope.mp4", "-o", tmp_path / "out" / "p.png", "-q")
    assert code == 2 and "no such file" in err and len(err.strip().splitlines()) == 1
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"not a video at all" * 100)
    code, err = run_cli(capsys, "stitch", junk, "-o", tmp_path / "out" / "p.png", "-q")
    assert code == 2 and "not a video" in err
    assert list((tmp_path / "out").iterdir()) == []


def test_unwritable_output_folder_is_refused_before_any_work(short_clip, tmp_path, capsys):
    """A folder the user may not write (mode 0500), and for root, whom permission bits do not
    stop (CI runs as root), a folder no one can create files in (/proc/self)."""
    import os

    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        folders = [locked] if not os.access(locked, os.W_OK) else []
        if Path("/proc/self").is_dir():
            folders.append(Path("/proc/self"))
        if not folders:
            pytest.skip("no folder here that this user cannot write")
        for folder in folders:
            code, err = run_cli(capsys, "stitch", short_clip, "-o", folder / "p.png", "-q")
            assert code == 2 and f"output folder {folder} is not writable" in err, err
    finally:
        locked.chmod(0o700)


# -- the stages on their own ------------------------------------------------------------------


def test_joint_refinement_removes_drift_and_ignores_a_wrong_loop_closure():
    rng = np.random.default_rng(0)
    size = (320, 180)
    # True placements (frame -> reference): a row of frames 120 px apart, a second row below.
    truth = []
    for row in range(2):
        for col in range(6):
            t = np.array([[1, 0.01 * col, 120.0 * col], [-0.01 * col, 1, 110.0 * row], [1e-5 * col, 0, 1]])
            truth.append(normalize(t))
    n = len(truth)
    grid = np.array([(x, y) for x in np.linspace(0, size[0] - 1, 8) for y in np.linspace(0, size[1] - 1, 5)])

    def link(a, b, kind, noise=0.2, bias=None):
        H_ab = np.linalg.inv(truth[b]) @ truth[a]
        H_ab = H_ab if bias is None else bias @ H_ab
        return Link(a, b, grid, project(H_ab, grid) + rng.normal(0, noise, grid.shape), kind)

    links = [link(k, k + 1, "sequential") for k in range(n - 1)]
    links += [link(k, k + 6, "loop") for k in range(6)]
    links.append(link(2, 9, "loop", bias=np.array([[1, 0, 40.0], [0, 1, -30.0], [0, 0, 1]])))  # a wrong match
    # Start from a drifted chain: every step is 2 px and 0.6 degrees off.
    drift = np.array([[np.cos(0.01), -np.sin(0.01), 2.0], [np.sin(0.01), np.cos(0.01), 1.0], [0, 0, 1]])
    initial = [truth[0]]
    for k in range(1, n):
        initial.append(normalize(initial[-1] @ np.linalg.inv(np.linalg.inv(truth[k]) @ truth[k - 1]) @ np.linalg.inv(drift)))
    reference = 3
    initial = [normalize(np.linalg.inv(initial[reference]) @ G) for G in initial]
    truth = [normalize(np.linalg.inv(truth[reference]) @ G) for G in truth]
    report = RegistrationReport(links=links)
    refined = refine_placements(initial, report, reference, size, RegistrationOptions())
    before = np.median([corner_error(G, T, size) for G, T in zip(initial, truth)])
    after = np.median([corner_error(G, T, size) for G, T in zip(refined, truth)])
    assert before > 5.0 and after < 0.3
    assert report.loops_dropped == 1 and all(not (l.a == 2 and l.b == 9) for l in report.links)
    assert np.allclose(refined[reference], np.eye(3))


def test_joint_refinement_converges_along_a_flight_s_slow_scale_drift():
    """A line of 40 keyframes from a camera tilted 6 degrees, each registered exactly to the
    next, starting from the scan's affine world (each step's closest affine: the perspective
    dropped, so the frames grow steadily along the line).  The links see that growth as
    hundredths of a pixel per pair; the refinement must still remove it.  scipy's trust region
    with an inexact inner solver left a keyframe 10.6% off in size here (and a mapping
    flight's keyframes -6% to +1% of the truth: docs/measurements/georef.md)."""
    from mosaic_cli.simulate.trajectory import camera_homography
    from mosaic_cli.stitch.keyframes import closest_affine

    size = (320, 180)
    views = [camera_homography(size, 320.0, 150.0 * k, 0.0, 1.0, 0.0, np.radians(6.0), np.radians(2.0)) for k in range(40)]
    reference = 20
    truth = [normalize(views[reference] @ np.linalg.inv(V)) for V in views]  # frame k -> reference
    rng = np.random.default_rng(4)
    links = []
    for k in range(39):
        H = np.linalg.inv(truth[k + 1]) @ truth[k]
        points = rng.uniform([0, 0], size, (200, 2))
        points = points[((project(H, points) >= 0) & (project(H, points) < size)).all(axis=1)][:60]
        links.append(Link(k, k + 1, points, project(H, points), "sequential", 5.0))
    world = [np.eye(3)]
    for k in range(1, 40):
        world.append(world[-1] @ closest_affine(np.linalg.inv(truth[k - 1]) @ truth[k], size))
    start = [normalize(np.linalg.inv(world[reference]) @ G) for G in world]

    def sizes(placements) -> np.ndarray:
        """Each keyframe's area in the reference frame against the truth's."""
        return np.array([cv2.contourArea(project(G, frame_corners(*size)).astype(np.float32))
                         / cv2.contourArea(project(T, frame_corners(*size)).astype(np.float32)) for G, T in zip(placements, truth)])

    assert np.abs(sizes(start) - 1).max() > 0.02  # the affine world drifted
    refined = refine_placements(start, RegistrationReport(links=links), reference, size, RegistrationOptions())
    assert np.abs(sizes(refined) - 1).max() < 1e-3
    assert max(corner_error(G, T, size) for G, T in zip(refined, truth)) < 0.05


def _strip(count: int = 7) -> list[np.ndarray]:
    """Exact placements (frame -> reference) of a strip of overlapping photos."""
    return [
        normalize(np.array([[np.cos(0.02 * k), -np.sin(0.02 * k), 110.0 * k], [np.sin(0.02 * k), np.cos(0.02 * k), 3.0 * k], [0, 0, 1]]))
        for k in range(count)
    ]


def _registration(truth, a, b, inliers, rng, size, bias=np.eye(3)) -> PairMatch:
    """A direct registration a -> b on ``inliers`` correspondences (0.3 px of noise), of the
    exact homography or, with ``bias``, of what a camera sees of ground that is not flat."""
    H = bias @ np.linalg.inv(truth[b]) @ truth[a]
    points = rng.uniform([0, 0], size, (inliers, 2))
    return PairMatch(H, points, project(H, points) + rng.normal(0, 0.3, (inliers, 2)), 0.5)


def test_a_loop_counts_as_its_inliers_so_a_weak_loop_cannot_pull_consecutive_photos_off():
    """Photos over ground with relief: the pairs 2 apart (a longer baseline, more parallax)
    see a slightly different plane than consecutive ones, so no placement satisfies every
    registration.  Consecutive photos overlap most (1000 inliers); the loops over a corner have
    100.  Each link counts as all its inliers (not 60 points each, as before), so the loops
    move the consecutive photos much less from their exact relative placement."""
    size = (320, 240)
    truth = _strip()
    parallax = np.array([[1.0, 0, -3.0], [0, 1.0, 2.0], [0, 0, 1]])
    options = RegistrationOptions()

    def refined_errors(equal_weights: bool) -> np.ndarray:
        rng = np.random.default_rng(0)
        links = [link_from_match(k + 1, k, _registration(truth, k + 1, k, 1000, rng, size), "sequential", options) for k in range(6)]
        links += [link_from_match(k, k + 2, _registration(truth, k, k + 2, 100, rng, size, parallax), "loop", options) for k in range(5)]
        assert links[0].weight == pytest.approx(1000 / options.points_per_pair) and len(links[0].points_a) == options.points_per_pair
        if equal_weights:  # what the refinement did before: every pair 60 points of weight 1
            for link in links:
                link.weight = 1.0
        report = RegistrationReport(links=links)
        refined = refine_placements(list(truth), report, 3, size, options)
        assert report.loops_dropped == 0
        # Where the panorama puts each consecutive photo's pixels in the next, against the truth.
        grid = np.array([(x, y) for x in np.linspace(0, size[0] - 1, 9) for y in np.linspace(0, size[1] - 1, 7)])
        return np.array([
            np.median(np.linalg.norm(project(np.linalg.inv(refined[k + 1]) @ refined[k], grid) - project(np.linalg.inv(truth[k + 1]) @ truth[k], grid), axis=1))
            for k in range(6)
        ])

    weighted, equal = refined_errors(False), refined_errors(True)
    assert np.median(weighted) < 0.9 < np.median(equal)
    assert np.median(weighted) < 0.6 * np.median(equal)


def _parallax_registration(truth, a, b, inliers, rng, size, parallax=1.5) -> PairMatch:
    """A registration a -> b of ground that is not one plane (trees on a field): its homography
    is the ground plane's, exactly, and each inlier lies off it by its height's parallax, up to
    ``parallax`` px along the flight (x), half the points above the plane, half below."""
    H = np.linalg.inv(truth[b]) @ truth[a]
    points = rng.uniform([0, 0], size, (8 * inliers, 2))
    seen = project(H, points)
    points = points[((seen >= 0) & (seen < size)).all(axis=1)][:inliers]
    heights = rng.uniform(-1, 1, len(points))
    return PairMatch(H, points, project(H, points) + parallax * np.outer(heights, [1.0, 0.0]), 0.5)


def test_drift_control_keeps_consecutive_photos_on_their_registrations_over_uneven_ground():
    """Photos of ground with trees: every inlier scatters about the registered homography by
    up to 1.5 px of parallax, so a homography fitted again from a few of them lies off the
    registration.  Every registration here is exact (consecutive ones on 1000 inliers, the
    loops two photos apart on 300), so nothing conflicts and drift control must place each
    photo exactly where its registrations put it: no worse than plain chaining
    (``--no-drift-control``).  The refinement used to take 60 of each pair's matched points
    as they were and fit them again: consecutive photos came out 0.17-0.18 px off (median),
    0.7-1.0 px at worst, with or without loops (issue 15's photo folders); now 0.00."""
    size = (320, 240)
    truth = _strip()
    reference = 3
    options = RegistrationOptions()
    rng = np.random.default_rng(2)
    matches = {(k + 1, k): _parallax_registration(truth, k + 1, k, 1000, rng, size) for k in range(6)}
    loops = {(k, k + 2): _parallax_registration(truth, k, k + 2, 300, rng, size) for k in range(5)}
    grid = np.array([(x, y) for x in np.linspace(0, size[0] - 1, 9) for y in np.linspace(0, size[1] - 1, 7)])

    def consecutive_errors(placements) -> np.ndarray:
        """The worst distance, per consecutive pair, between where the placements and the truth
        put a photo's pixels in the next one."""
        return np.array([
            np.max(np.linalg.norm(project(np.linalg.inv(placements[k + 1]) @ placements[k], grid) - project(np.linalg.inv(truth[k + 1]) @ truth[k], grid), axis=1))
            for k in range(6)
        ])

    # The scan's placements: the registrations chained, each a little off (drift).
    start = [np.eye(3)]
    for k in range(1, 7):
        start.append(start[-1] @ np.linalg.inv(matches[k, k - 1].H) @ np.array([[1, 0, 0.8], [0, 1, -0.5], [0, 0, 1]]))
    to_reference = np.linalg.inv(start[reference])
    start = [normalize(to_reference @ G) for G in start]
    plain = chain_sequence([(a, b, m) for (a, b), m in matches.items()], start, reference)
    for with_loops in (False, True):
        links = [link_from_match(a, b, m, "sequential", options) for (a, b), m in matches.items()]
        if with_loops:
            links += [link_from_match(a, b, m, "loop", options) for (a, b), m in loops.items()]
        report = RegistrationReport(links=links)
        refined = refine_placements(list(start), report, reference, size, options)
        assert report.loops_dropped == 0
        assert consecutive_errors(refined).max() < 0.02
        assert consecutive_errors(refined).max() <= consecutive_errors(plain).max() + 0.02
    # The scan's start was off, so the refinement had to move the photos to get there.
    assert consecutive_errors(start).max() > 0.5


def test_a_weighted_point_counts_as_that_many_copies_of_it():
    """The loss is weighted, not the residuals: a point of weight 3 pulls exactly as three
    copies of it do, and the soft-L1 turn stays at ``loss_scale`` pixels for every link."""
    size = (320, 240)
    truth = _strip(4)
    rng = np.random.default_rng(1)
    matches = [_registration(truth, k + 1, k, 40, rng, size) for k in range(3)]
    loop = _registration(truth, 0, 2, 40, rng, size, np.array([[1, 0, 6.0], [0, 1, -4.0], [0, 0, 1]]))
    weighted = [Link(k + 1, k, m.points_a, m.points_b, "sequential", 3.0) for k, m in enumerate(matches)]
    copied = [Link(k + 1, k, np.tile(m.points_a, (3, 1)), np.tile(m.points_b, (3, 1)), "sequential") for k, m in enumerate(matches)]
    results = []
    for links in (weighted, copied):
        loops = [Link(0, 2, loop.points_a, loop.points_b, "loop")]
        results.append(refine_placements(list(truth), RegistrationReport(links=links + loops), 1, size, RegistrationOptions(outlier_residual=100.0)))
    for a, b in zip(*results):
        assert corner_error(a, b, size) < 1e-3
    # The 7 px loop moved the photos (so the comparison above is not trivially true).
    assert max(corner_error(a, t, size) for a, t in zip(results[0], truth)) > 0.5


def test_keyframe_store_shrinks_held_pixels_as_the_flown_area_grows():
    size = (400, 300)
    store = KeyframeStore(size, decode_scale=1.0, max_size=1000)
    frame = np.zeros((300, 400, 3), np.uint8)
    keyframes = []
    for k in range(40):
        placement = np.array([[1, 0, 300.0 * k], [0, 1, 0], [0, 0, 1]])
        key = Keyframe(k, placement, None, None)
        store.keep(key, frame, project(placement, frame_corners(*size)))
        keyframes.append(key)
        store.shrink(keyframes)
    extent = 300.0 * 39 + 400
    assert store.scale == pytest.approx(KeyframeStore.MARGIN * 1000 / extent, rel=1e-6)
    # Every held image is at most 1/SHRINK_BELOW times the scale the canvas needs.
    for key in keyframes:
        assert key.scale <= store.scale / KeyframeStore.SHRINK_BELOW + 1e-9
        assert key.image.shape[1] == round(size[0] * key.scale)
    held = sum(k.image.size for k in keyframes)
    assert held < 40 * frame.size * 0.1


def test_blending_in_tiles_matches_blending_the_whole_canvas(ground):
    """The blender runs on square tiles to bound its memory; the margins it borrows from the
    neighbouring tiles must make the seams between tiles invisible, also when the cache of
    keyframe pixels is too small to hold one and every tile reads them again."""
    rng = np.random.default_rng(1)
    canvas = (700, 620)
    tiles = []
    for k in range(9):
        x, y = 40 + 190 * (k % 3) + rng.uniform(-10, 10), 30 + 170 * (k // 3) + rng.uniform(-10, 10)
        H = np.array([[1.0, 0.02, x], [-0.02, 1.0, y], [0, 0, 1]])
        gain = 0.85 + 0.3 * rng.random()  # uneven exposure, for the compensator to even out
        view = cv2.warpPerspective(ground, np.linalg.inv(H), (256, 200), flags=cv2.INTER_LINEAR)
        tiles.append((np.clip(view * gain, 0, 255).astype(np.uint8), H))
    results = {}
    for blend in ("multiband", "feather"):
        for tile, cache in ((10**6, 512.0), (64, 1e-6)):  # one tile; 64-px tiles, nothing cached
            placed = [PlacedImage(image.copy(), H) for image, H in tiles]
            options = ComposeOptions(blend=blend, tile=tile, cache_megabytes=cache)
            results[blend, tile] = compose(placed, canvas, options)
            assert all(p.image is None for p in placed)  # pixels dropped once drawn
        whole, parts = results[blend, 10**6].astype(int), results[blend, 64].astype(int)
        assert np.array_equal(whole[..., 3], parts[..., 3])
        assert np.abs(whole - parts).max() <= 2, blend
    assert (results["multiband", 10**6][..., 3] == 255).mean() > 0.6


def test_keyframe_pixels_spilled_to_files_are_the_pixels_held_in_memory(tmp_path):
    size = (400, 300)
    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 256, (300, 400, 3), dtype=np.uint8) for _ in range(12)]
    stores = {"memory": KeyframeStore(size, 1.0, max_size=1200), "files": KeyframeStore(size, 1.0, max_size=1200, spill=tmp_path)}
    held = {}
    for name, store in stores.items():
        keyframes = []
        for k, frame in enumerate(frames):
            placement = np.array([[1, 0, 300.0 * k], [0, 1, 0], [0, 0, 1]])
            key = Keyframe(k, placement, None, None)
            store.keep(key, frame, project(placement, frame_corners(*size)))
            keyframes.append(key)
            store.shrink(keyframes)
        held[name] = keyframes
    assert all(isinstance(k.image, SpilledImage) for k in held["files"])
    assert any(k.scale < 1.0 for k in held["files"])  # some were shrunk, re-written
    for a, b in zip(held["memory"], held["files"]):
        assert a.scale == b.scale and a.image.shape == b.image.shape
        assert np.array_equal(a.image, b.image.load())
    # One file per held image: a shrunk image's old file is gone.
    assert sorted(tmp_path.iterdir()) == sorted(k.image.path for k in held["files"])


def test_spilled_images_compose_exactly_as_in_memory_and_their_files_go(ground, tmp_path):
    tiles = []
    for k in range(6):
        H = np.array([[1.0, 0.01, 30 + 150 * (k % 3)], [-0.01, 1.0, 20 + 140 * (k // 3)], [0, 0, 1]])
        tiles.append((cv2.warpPerspective(ground, np.linalg.inv(H), (220, 180)), H))
    in_memory = compose([PlacedImage(image.copy(), H) for image, H in tiles], (560, 380), ComposeOptions(tile=128))
    spilled = [PlacedImage(SpilledImage(image, tmp_path), H) for image, H in tiles]
    assert len(list(tmp_path.iterdir())) == 6
    from_files = compose(spilled, (560, 380), ComposeOptions(tile=128))
    assert np.array_equal(in_memory, from_files)
    assert list(tmp_path.iterdir()) == []


def test_compose_reports_progress_in_tiles_each_tile_once(ground):
    tiles = []
    for k in range(4):
        H = np.array([[1.0, 0.0, 40 + 200 * (k % 2)], [0.0, 1.0, 30 + 150 * (k // 2)], [0, 0, 1]])
        tiles.append(PlacedImage(cv2.warpPerspective(ground, np.linalg.inv(H), (220, 180)), H))
    steps = []
    options = ComposeOptions(tile=100)
    total = tile_count(tiles, (500, 380), options)
    compose(tiles, (500, 380), options, lambda n=1, status=None: steps.append(n))
    done = [n for n in steps if n]
    assert len(done) > 1  # several tiles, so the bar moves while the canvas is blended
    assert sum(done) == total


@pytest.mark.slow
def test_stitch_spills_keyframes_to_a_temporary_folder_it_always_removes(survey, tmp_path, ground, monkeypatch):
    spill_root = tmp_path / "tmp"
    spill_root.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(spill_root))
    flight, _, transforms, _ = survey
    seen = []
    original = SpilledImage.__init__

    def spy(self, image, folder):
        seen.append(Path(folder))
        original(self, image, folder)

    monkeypatch.setattr(SpilledImage, "__init__", spy)
    stitch(flight.path, tmp_path / "p.png", fast_orb(), transforms=tmp_path / "t.json", show_progress=False)
    assert seen and all(folder.parent == spill_root for folder in seen)
    assert list(spill_root.iterdir()) == []
    # The same panorama as with the pixels in memory.
    stitch(flight.path, tmp_path / "m.png", fast_orb(), StitchOptions(spill=False), show_progress=False)
    assert np.array_equal(read_rgba(tmp_path / "p.png"), read_rgba(tmp_path / "m.png"))
    assert load_transforms(tmp_path / "t.json")[:2] == load_transforms(transforms)[:2]
    # A stitch that fails half way leaves no folder behind either.
    broken = fly(tmp_path / "f.mp4", ground, frames=150)
    with pytest.raises(ProcessingError):
        stitch(broken.path, tmp_path / "d.png", DivergingEstimator(SIZE[0]), show_progress=False)
    assert list(spill_root.iterdir()) == []


class Batching(Estimator):
    """Wraps an estimator and hands its estimates out four frames late, in bursts, as a
    batched (learned) estimator does."""

    name = "batching"

    def __init__(self, inner: Estimator):
        super().__init__(inner.work_width)
        self.inner, self.held = inner, []

    def reset(self, full_size):
        super().reset(full_size)
        self.inner.reset(full_size)
        self.held = []

    def feed(self, frame):
        self.held += self.inner.feed(frame)
        if len(self.held) < 4:
            return []
        out, self.held = self.held, []
        return out

    def finish(self):
        out, self.held = self.held + self.inner.finish(), []
        return out

    def _estimate(self, prev, cur):
        raise AssertionError("not used")


@pytest.mark.slow
def test_an_estimator_that_answers_late_in_batches_gives_the_same_panorama(survey, tmp_path):
    flight, _, transforms, _ = survey
    stitch(flight.path, tmp_path / "p.png", Batching(fast_orb()), transforms=tmp_path / "t.json", show_progress=False)
    canvas, indices, H = load_transforms(tmp_path / "t.json")
    ref_canvas, ref_indices, ref_H = load_transforms(transforms)
    assert (canvas, indices) == (ref_canvas, ref_indices)
    assert np.allclose(np.array(H), np.array(ref_H), atol=1e-6)


@pytest.mark.slow
def test_a_video_with_no_usable_frame_is_refused(tmp_path, capsys):
    with VideoWriter(tmp_path / "black.mp4", SIZE, 30.0) as writer:
        for _ in range(10):
            writer.write(np.zeros((SIZE[1], SIZE[0], 3), np.uint8))
    (tmp_path / "out").mkdir()
    code, err = run_cli(capsys, "stitch", tmp_path / "black.mp4", "-o", tmp_path / "out" / "p.png", "--reference", 5, "-q")
    assert code == 2 and "no frame is usable" in err and len(err.strip().splitlines()) == 1
    assert list((tmp_path / "out").iterdir()) == []


def test_drift_control_starts_from_the_chained_registrations_unless_they_fold_a_keyframe():
    from mosaic_cli.stitch.keyframes import KeyframeOptions
    from mosaic_cli.stitch.pipeline import _start

    size = (320, 180)
    world = [np.eye(3), np.array([[1.0, 0, 100], [0, 1, 0], [0, 0, 1]])]
    chained = [np.eye(3), np.array([[1.0, 0, 100], [0, 1, 0], [1e-4, 0, 1]])]  # the same step, with perspective
    assert _start(world, chained, size, KeyframeOptions()) is chained
    folded = [np.eye(3), np.array([[1.0, 0, 100], [0, 1, 0], [-0.01, 0, 1]])]  # the frame's far side behind the camera
    assert _start(world, folded, size, KeyframeOptions()) is world
