"""Options that had no test of their own: stitch's --seam, --exposure, --blend none and --start,
and eval --every.  Compositing options are checked on two exactly placed views of one ground,
so that where each output pixel comes from is known."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import cli_exit, textured_image
from mosaic_cli.evaluate import landmarks_from_ground_truth
from mosaic_cli.simulate import plan_flight, procedural_map, write_flight
from mosaic_cli.stitch.compose import ComposeOptions, PlacedImage, compose

VIEW = (256, 160)  # w, h of each view
SHIFT = 96  # view B starts this many canvas px right of view A: 160 px of overlap
CANVAS = (VIEW[0] + SHIFT, VIEW[1])


@pytest.fixture(scope="module")
def views() -> tuple[np.ndarray, np.ndarray]:
    """Views A and B of one ground, B brighter by 50 levels (an exposure step)."""
    ground = textured_image(*CANVAS, seed=7)
    a = ground[:, : VIEW[0]].copy()
    b = np.clip(ground[:, SHIFT:].astype(int) + 50, 0, 255).astype(np.uint8)
    return a, b


def panorama(views, **options) -> np.ndarray:
    a, b = views
    shift = np.array([[1.0, 0, SHIFT], [0, 1, 0], [0, 0, 1]])
    placed = [PlacedImage(a.copy(), np.eye(3)), PlacedImage(b.copy(), shift)]
    return compose(placed, CANVAS, ComposeOptions(**options))


def overlap_sources(views, pano: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Masks over the overlap (canvas columns SHIFT..VIEW[0]) of the pixels equal to view A's
    and to view B's (within 2 levels)."""
    a, b = views
    out = pano[:, SHIFT : VIEW[0], :3].astype(int)
    from_a = np.abs(out - a[:, SHIFT:].astype(int)).max(-1) <= 2
    from_b = np.abs(out - b[:, : VIEW[0] - SHIFT].astype(int)).max(-1) <= 2
    return from_a, from_b


@pytest.mark.parametrize("seam", ["dp", "graphcut", "voronoi"])
def test_each_seam_finder_cuts_the_overlap_between_the_views(views, seam):
    a, b = views
    pano = panorama(views, seam=seam, blend="none", exposure="none")
    assert (pano[..., 3] == 255).all()
    from_a, from_b = overlap_sources(views, pano)
    assert (from_a | from_b).mean() > 0.99  # without blending each overlap pixel is one view's
    # each view's own part is its own, untouched
    assert np.array_equal(pano[:, :SHIFT, :3], a[:, :SHIFT]) and np.array_equal(pano[:, VIEW[0]:, :3], b[:, VIEW[0] - SHIFT:])
    if seam == "voronoi":  # the cut halfway between the two views' centres
        middle = (VIEW[0] - SHIFT) // 2
        assert from_a[:, : middle - 4].mean() > 0.99 and from_b[:, middle + 4 :].mean() > 0.99


def test_no_seam_finder_lets_the_view_drawn_last_cover_the_overlap(views):
    from_a, from_b = overlap_sources(views, panorama(views, seam="none", blend="none", exposure="none"))
    assert from_b.mean() > 0.99 and from_a.mean() < 0.05


def test_blend_none_leaves_a_hard_cut_that_blending_softens(views):
    from_a, from_b = overlap_sources(views, panorama(views, blend="none", exposure="none"))
    assert (from_a | from_b).mean() > 0.99
    from_a, from_b = overlap_sources(views, panorama(views, blend="multiband", exposure="none"))
    assert (from_a | from_b).mean() < 0.97  # pixels along the seam mix the two views


@pytest.mark.parametrize("exposure, at_most", [("gain", 0.5), ("gain-blocks", 0.95)])
def test_exposure_compensation_evens_out_the_brighter_view(views, exposure, at_most):
    """The brightness step between A's and B's own parts of the panorama (50 levels without
    compensation) shrinks when the compensator is on: one gain per view evens it out, gains per
    block mostly where the views overlap (the parts compared here lie outside the overlap)."""
    def step(pano: np.ndarray) -> float:
        gray = pano[..., :3].astype(float).mean(-1)
        left, right = gray[:, :SHIFT - 8], gray[:, VIEW[0] + 8 :]
        ground = textured_image(*CANVAS, seed=7).astype(float).mean(-1)
        return (right - ground[:, VIEW[0] + 8 :]).mean() - (left - ground[:, : SHIFT - 8]).mean()

    plain = step(panorama(views, exposure="none"))
    assert plain == pytest.approx(50, abs=3)
    assert abs(step(panorama(views, exposure=exposure))) < at_most * plain


# --- commands --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """A 40-frame 256x144 simulated flight with its ground truth."""
    folder = tmp_path_factory.mktemp("options")
    rgb = procedural_map((1024, 1024), seed=3)
    plan = plan_flight((1024, 1024), "paper", frames=40, size=(256, 144), seed=3)
    video = folder / "f.mp4"
    gt = write_flight(video, rgb, plan, preset="veryfast", show_progress=False)
    return video, gt


def test_stitch_start_skips_the_first_frames(flight, tmp_path):
    video, _ = flight
    transforms = tmp_path / "t.json"
    args = ["stitch", video, "-o", tmp_path / "p.png", "--transforms", transforms, "--work-width", 128,
            "--no-drift-control", "-e", "orb", "-q"]
    assert cli_exit([*args, "--start", "12"]) == 0
    indices = [int(f["index"]) for f in json.loads(transforms.read_text())["frames"]]
    assert min(indices) >= 12 and indices  # frame numbers still count from the video's start


def test_eval_every_sets_the_landmark_spacing(flight, tmp_path):
    video, gt = flight
    gt_path = video.with_name("f.gt.json")
    out = tmp_path / "m.json"
    for every in (10, 30):
        assert cli_exit(["eval", gt_path, "--gt", gt_path, "--every", str(every), "--json", out, "-q"]) == 0
        metrics = json.loads(out.read_text())
        expected = landmarks_from_ground_truth(gt, every=every)
        assert metrics["landmarks"] == len(expected)
        assert metrics["landmark_pairs"] == len(np.unique(expected[:, [0, 3]], axis=0))
        assert metrics["mace"] < 1e-6  # the truth scored against itself


@pytest.mark.slow
def test_learned_estimator_options_of_every_type_are_read_or_refused_in_one_line():
    """Numbers with a fraction (spoilt-ratio) are read as numbers, like the whole ones."""
    from mosaic_cli.errors import BadInput
    from mosaic_cli.estimators import make_estimator

    est = make_estimator("lstm:spoilt-ratio=0.75:carry-limit=4:carry=none", device="cpu")
    assert (est.config.spoilt_ratio, est.config.carry_limit, est.config.carry) == (0.75, 4, "none")
    with pytest.raises(BadInput, match="spoilt-ratio must be a number"):
        make_estimator("lstm:spoilt-ratio=high", device="cpu")
    with pytest.raises(BadInput, match="spoilt-ratio must be in"):
        make_estimator("lstm:spoilt-ratio=1.5", device="cpu")
