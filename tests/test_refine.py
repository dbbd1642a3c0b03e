"""The polish seeded by a coarse estimate (estimators/refine.py) and its use in the learned
estimator: a deliberately wrong "network" is corrected to sub-pixel accuracy on a known warp,
the network's estimate is kept where the polish cannot work, and frames without texture give
the identity with confidence 0, never NaN."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from conftest import render, textured_image
from mosaic_cli.estimators import estimate_stream
from mosaic_cli.estimators.learned import LearnedConfig, LearnedEstimator, WorkFrame, patch_positions
from mosaic_cli.estimators.refine import CornerConfig, PolishConfig, align_pixels, band_pass, points_to_track, track_points
from mosaic_cli.geometry import corner_error, four_point_to_homography, frame_corners, project, rect_corners, to_resolution
from mosaic_cli.model import HomographyNet, NetConfig

pytestmark = pytest.mark.usefixtures("one_torch_thread")

FULL, WORK = (640, 360), (320, 180)


@pytest.fixture(scope="module")
def ground() -> np.ndarray:
    return textured_image(1400, 1000, seed=5)


def true_motion(seed: int = 0) -> np.ndarray:
    """A frame t -> t+1 homography at full resolution: a few px of translation, a little rotation,
    zoom and perspective (random corner offsets of up to 8 px)."""
    offsets = np.random.default_rng(seed).uniform(-8, 8, (4, 2)) + np.array([6.0, -3.0])
    return four_point_to_homography(frame_corners(*FULL), offsets)


def flight(ground, H: np.ndarray, n: int = 6, size=FULL) -> list[np.ndarray]:
    """n frames whose pairwise homography (frame t -> t+1) is exactly ``H``."""
    origin = np.array([[1, 0, 350.0], [0, 1, 300.0], [0, 0, 1.0]])
    step = np.linalg.inv(H)
    return [render(ground, origin @ np.linalg.matrix_power(step, t), size) for t in range(n)]


def gray_work(frame):
    return cv2.resize(cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY), WORK, interpolation=cv2.INTER_AREA)


def perturbed(H_work: np.ndarray, px: float, seed: int = 1) -> np.ndarray:
    """``H_work`` with its frame corners moved by ``px`` working pixels in random directions."""
    corners = frame_corners(*WORK)
    angles = np.random.default_rng(seed).uniform(0, 2 * np.pi, 4)
    moved = project(H_work, corners) + px * np.stack([np.cos(angles), np.sin(angles)], -1)
    return four_point_to_homography(corners, moved - corners)


# --- the polish itself -------------------------------------------------------------------


@pytest.mark.parametrize("polisher", ["lk", "ecc"])
def test_polish_recovers_a_known_warp_from_a_perturbed_seed(ground, polisher):
    H_full = true_motion()
    prev, cur = (gray_work(f) for f in flight(ground, H_full, n=2))
    H_true = to_resolution(H_full, FULL, WORK)
    config = PolishConfig(levels=2, max_shift=4.0)
    for px in (1.0, 2.5):
        seed = perturbed(H_true, px)
        assert corner_error(seed, H_true, WORK) > 0.9 * px
        if polisher == "lk":
            result = track_points(prev, cur, seed, points_to_track(prev, CornerConfig()), config)
        else:
            result = align_pixels(prev, cur, seed, config)
        assert result.refined and 0.5 < result.score <= 1.0
        assert corner_error(result.H, H_true, WORK) < 0.05, (px, corner_error(result.H, H_true, WORK))


def test_polish_keeps_the_seed_without_texture():
    flat = np.full(WORK[::-1], 128, np.uint8)
    assert len(points_to_track(flat, CornerConfig())) == 0
    # a smooth gradient (no corners at all) with a little noise, as a badly exposed sky would be
    gradient = np.tile(np.linspace(60, 190, WORK[0]), (WORK[1], 1))
    noisy = [np.clip(gradient + np.random.default_rng(s).normal(0, 0.7, gradient.shape), 0, 255).astype(np.uint8) for s in (0, 1)]
    assert len(points_to_track(noisy[0], CornerConfig())) == 0
    seed = perturbed(np.eye(3), 1.5)
    for prev, cur in ((flat, flat), tuple(noisy)):
        lk = track_points(prev, cur, seed, points_to_track(prev, CornerConfig()), PolishConfig())
        assert not lk.refined and lk.score == 0 and lk.H is seed
        ecc = align_pixels(prev, cur, seed, PolishConfig())
        assert not ecc.refined and np.array_equal(ecc.H, seed)


def test_polish_refuses_to_wander(ground):
    """A seed further from the truth than max_shift: the polish may find the truth, but it is
    not trusted to, and the seed comes back unchanged."""
    H_full = true_motion(3)
    prev, cur = (gray_work(f) for f in flight(ground, H_full, n=2))
    H_true = to_resolution(H_full, FULL, WORK)
    seed = perturbed(H_true, 3.0)
    result = track_points(prev, cur, seed, points_to_track(prev, CornerConfig()), PolishConfig(levels=2, max_shift=1.0))
    assert not result.refined and result.H is seed


# --- seeded by a network -------------------------------------------------------------------


class OracleNet(nn.Module):
    """Stands in for a trained net: outputs the true corner offsets of each patch plus a fixed,
    deliberate error (``bias``, working px), like a network that is roughly right."""

    def __init__(self, H_work: np.ndarray, positions: np.ndarray, bias: np.ndarray):
        super().__init__()
        self.config = SimpleNamespace(patch=128, head="cnn")
        self.head = "cnn"
        corners = np.stack([rect_corners(x - 0.5, y - 0.5, 128, 128) for x, y in positions])
        offsets = project(H_work, corners) - corners + bias
        self.offsets = torch.tensor(offsets, dtype=torch.float32)  # (M, 4, 2)
        self.dummy = nn.Parameter(torch.zeros(1))

    def features(self, pairs):
        return torch.zeros(len(pairs), 1)

    def step(self, features, state=None):  # features (M, n, 1)
        M, n = features.shape[:2]
        return self.offsets[:, None].expand(M, n, 4, 2).clone(), None


def oracle_estimator(H_full, bias, **config):
    config.setdefault("fallback", "none")  # the learned path alone: these tests are about its polish
    H_work = to_resolution(H_full, FULL, WORK)
    cfg = LearnedConfig(**config)
    positions = patch_positions(WORK, 128, cfg.patches)
    net = OracleNet(H_work, positions, bias)
    return LearnedEstimator(net, {"variant": "oracle", "work_size": WORK}, "cpu", cfg)


def run(estimator, frames):
    out = list(estimate_stream(estimator, frames, FULL))
    return np.array([e.H for e in out]), np.array([e.confidence for e in out])


@pytest.mark.parametrize("refine", ["lk", "ecc"])
def test_network_estimate_polished_to_subpixel(ground, refine):
    H_full = true_motion(1)
    frames = flight(ground, H_full)
    bias = np.array([[2.2, -1.4], [1.9, -1.2], [2.4, -1.6], [2.0, -1.0]])  # about 2.5 working px off (5 px full)
    raw, raw_conf = run(oracle_estimator(H_full, bias, refine=None, chunk=3), frames)
    polished, conf = run(oracle_estimator(H_full, bias, refine=refine, chunk=3), frames)
    raw_err, err = corner_error(raw, H_full, FULL), corner_error(polished, H_full, FULL)
    assert raw_err.min() > 3.0  # the network alone is off by several full-resolution px
    assert err.max() < 0.3, err  # the polish brings every pair well under a pixel (0.1-0.2 px measured)
    assert conf.min() > 0.5 and conf.min() > raw_conf.max()  # registered pairs are trusted more


def spoiled(frame: np.ndarray, seed: int) -> np.ndarray:
    """A fast flight's frame: blurred along the motion, with sensor noise (sigma 6 gray levels)."""
    kernel = np.zeros((1, 9), np.float32)
    kernel[0, :] = 1 / 9
    blurred = cv2.filter2D(frame.astype(np.float32), -1, kernel)
    noise = np.random.default_rng(seed).normal(0, 6, frame.shape)
    return np.clip(blurred + noise, 0, 255).astype(np.uint8)


def test_a_far_seed_on_degraded_frames_is_found_by_the_wide_polish_then_placed_by_the_fine_one(ground):
    """A network 6-8 working px off (as on fast flights over ground unlike its training sites),
    on blurred, noisy frames: the cheap polish's leash is too short, the wide one finds the
    basin, and the cheap one seeded by it places the pair as precisely as from a close seed."""
    H_full = true_motion(5)
    frames = [spoiled(f, k) for k, f in enumerate(flight(ground, H_full, n=4))]
    far = np.array([[7.0, -4.0], [6.0, -3.5], [7.5, -4.5], [6.5, -3.0]])
    close = far / 10
    no_wide, no_wide_conf = run(oracle_estimator(H_full, far, polish_wide=None), frames)
    assert corner_error(no_wide, H_full, FULL).min() > 5 and no_wide_conf.max() < 0.3  # unconfirmed, several px off
    cascade, conf = run(oracle_estimator(H_full, far), frames)
    reference, _ = run(oracle_estimator(H_full, close), frames)
    err, ref_err = corner_error(cascade, H_full, FULL), corner_error(reference, H_full, FULL)
    assert err.max() < 0.5, err
    assert err.max() < ref_err.max() + 0.1, (err, ref_err)  # as precise as from a close seed
    assert conf.min() > 0.3


def test_band_passed_agreement_ranks_registrations_of_a_degraded_pair(ground):
    """What chooses between the wide polish and ORB: on blurred, noisy frames the correlation of
    the band-passed frames falls as a registration moves away from the truth."""
    H_full = true_motion(6)
    frames = [spoiled(f, k) for k, f in enumerate(flight(ground, H_full, n=2))]
    estimator = oracle_estimator(H_full, np.zeros((4, 2)))
    estimator.reset(FULL)
    prev, cur = (WorkFrame(estimator.prepared(f)) for f in frames)
    for f in (prev, cur):
        estimator._read_frame(f)
    H_true = to_resolution(H_full, FULL, WORK)
    scores = [estimator._agreement(prev, cur, perturbed(H_true, px)) for px in (0.0, 1.5, 4.0)]
    assert scores[0] > scores[1] > scores[2], scores
    assert scores[0] > 0.8


def test_a_pair_only_the_wide_polish_placed_is_contested_by_the_fallback(ground):
    """The cheap polish never succeeds here, so every pair is the wide polish's alone: ORB then
    registers it too, and the better-agreeing registration is kept; every pair is right either way."""
    H_full = true_motion(7)
    frames = [spoiled(f, k) for k, f in enumerate(flight(ground, H_full, n=5))]
    far = np.array([[6.0, -4.0], [6.5, -3.5], [7.0, -4.5], [6.0, -3.0]])
    never = PolishConfig(min_inliers=100000)
    estimator = oracle_estimator(H_full, far, fallback="orb", polish=never)
    asked, register = [], estimator._fallback.register
    estimator._fallback.register = lambda *a: asked.append(1) or register(*a)
    H, conf = run(estimator, frames)
    assert len(asked) == 4  # ORB was asked about every pair the wide polish placed alone
    assert corner_error(H, H_full, FULL).max() < 1.0
    assert estimator.path_counts["failed"] == 0 and sum(estimator.path_counts.values()) == 4
    alone = oracle_estimator(H_full, far, fallback="none", polish=never)
    run(alone, frames)
    assert alone.path_counts == {"learned": 4, "fallback": 0, "carried": 0, "failed": 0}


def test_network_estimate_kept_when_the_polish_cannot_confirm_it(ground):
    """When the polish fails (here: it is never allowed to succeed), the output is exactly the
    network's own estimate, with a discounted confidence."""
    H_full = true_motion(2)
    frames = flight(ground, H_full)
    bias = np.full((4, 2), 0.7)
    raw, raw_conf = run(oracle_estimator(H_full, bias, refine=None), frames)
    never = PolishConfig(min_inliers=100000)
    kept, conf = run(oracle_estimator(H_full, bias, refine="lk", polish=never, polish_wide=never), frames)
    np.testing.assert_allclose(kept, raw, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(conf, 0.5 * raw_conf, rtol=1e-9)


# --- robustness: frames with nothing to register -------------------------------------------


def degraded(kind: str, texture: np.ndarray) -> np.ndarray:
    if kind == "black":
        return np.zeros_like(texture)
    if kind == "over-exposed":
        return np.full_like(texture, 255)
    if kind == "blurred":
        return cv2.GaussianBlur(texture, (0, 0), 12)
    if kind == "textureless":
        noise = np.random.default_rng(0).normal(0, 0.6, texture.shape)
        return np.clip(140 + noise, 0, 255).astype(np.uint8)
    raise ValueError(kind)


@pytest.mark.parametrize("kind", ["black", "over-exposed", "blurred", "textureless"])
@pytest.mark.parametrize("refine", ["lk", None])
@pytest.mark.parametrize("carry", ["none", "velocity"])
def test_frames_without_texture_are_carried_or_failed_never_wild(ground, kind, refine, carry):
    """A real (randomly initialised) network and the full pipeline: a pair that involves a frame
    with nothing to register is never NaN or a wild matrix: with ``carry=none`` it is the
    identity with confidence 0 (failed); by default it is placed by the last confirmed motion,
    at the carried confidence, and counted as carried.  The good pairs around it are unaffected."""
    torch.manual_seed(0)
    net = HomographyNet(NetConfig(head="cnn"))
    good = flight(ground, true_motion(4), n=4)
    frames = good[:2] + [degraded(kind, good[2]), degraded(kind, good[2])] + good[2:]
    config = LearnedConfig(refine=refine, chunk=4, carry=carry)
    estimator = LearnedEstimator(net, {"variant": "base", "work_size": WORK}, "cpu", config)
    H, conf = run(estimator, frames)
    assert H.shape == (5, 3, 3) and np.all(np.isfinite(H)) and np.all(np.isfinite(conf))
    assert conf[0] > config.carry_confidence and conf[4] > config.carry_confidence
    for k in (1, 2, 3):  # every pair with a degraded frame
        if carry == "none":
            np.testing.assert_array_equal(H[k], np.eye(3))
            assert conf[k] == 0
        else:
            np.testing.assert_allclose(H[k], H[0], atol=1e-9)
            assert conf[k] == config.carry_confidence
    assert estimator.path_counts["carried" if carry != "none" else "failed"] == 3


def test_wide_polish_rescues_a_far_off_network(ground):
    """A network 6 working px off is out of reach of the cheap first polish (1 level, 3 px
    leash); the wide retry (3 levels, 8 px) brings it to sub-pixel accuracy."""
    H_full = true_motion(5)
    frames = flight(ground, H_full, n=3)
    bias = np.array([[5.0, -3.5], [4.6, -3.2], [5.3, -3.8], [4.8, -3.0]])
    narrow, _ = run(oracle_estimator(H_full, bias, polish_wide=None), frames)
    wide, conf = run(oracle_estimator(H_full, bias), frames)
    assert corner_error(narrow, H_full, FULL).min() > 8.0
    assert corner_error(wide, H_full, FULL).max() < 0.3 and conf.min() > 0.5


@pytest.mark.parametrize("size", [(320, 180), (321, 181)])
def test_band_pass_matches_the_full_resolution_difference_of_gaussians(ground, size):
    """The coarse base is blurred at half size; the band it leaves must be the plain DoG's, to
    within a gray level, up to the frame's borders."""
    gray = cv2.cvtColor(cv2.resize(ground, size, interpolation=cv2.INTER_AREA), cv2.COLOR_RGB2GRAY)
    fine, coarse, gain = 1.5, 6.0, 3.0
    smooth = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), fine)
    base = cv2.GaussianBlur(smooth, (0, 0), float(np.sqrt(coarse**2 - fine**2)))
    expected = np.clip(np.rint(128 + gain * (smooth - base)), 0, 255)
    got = band_pass(gray, fine, coarse, gain)
    assert got.shape == gray.shape and got.dtype == np.uint8
    diff = np.abs(got.astype(np.float64) - expected)
    assert np.percentile(diff, 99) <= 1.0 and diff.max() <= 3.0
    assert diff.mean() < 0.5
    assert np.std(got.astype(np.float64)) > 5  # the band carries the texture, not a flat 128


def test_the_carried_motion_stops_after_its_limit_and_never_starts_before_a_confirmed_pair(ground):
    """A video that goes black for longer than ``carry-limit`` pairs: the first pairs into the dark
    take the carried motion, the rest fail (identity, confidence 0); a video that starts black
    has no motion to carry."""
    torch.manual_seed(0)
    net = HomographyNet(NetConfig(head="cnn"))
    good = flight(ground, true_motion(4), n=4)
    black = np.zeros_like(good[0])
    config = LearnedConfig(refine="lk", chunk=4, carry_limit=3)
    estimator = LearnedEstimator(net, {"variant": "base", "work_size": WORK}, "cpu", config)
    H, conf = run(estimator, good[:2] + [black] * 6)  # pairs: 1 good, 6 into or within the dark
    assert conf[0] > config.carry_confidence
    assert list(conf[1:4]) == [config.carry_confidence] * 3 and np.all(conf[4:] == 0)
    assert estimator.path_counts["carried"] == 3 and estimator.path_counts["failed"] == 3
    estimator = LearnedEstimator(net, {"variant": "base", "work_size": WORK}, "cpu", config)
    H, conf = run(estimator, [black] * 3 + good[:2])
    assert np.all(conf[:3] == 0) and estimator.path_counts["carried"] == 0
