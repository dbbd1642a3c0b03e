"""The default correction, ``tilt``: a similarity, plus the camera's pitch and roll shake where
the estimates show it.  On a path with pitch and roll shake it leaves clearly less shake than a
similarity; on one without, it is the similarity's plan (the estimates' perspective noise kept
out, where ``homography`` turns it into wobble); planned as the pairs arrive it is the whole
clip's plan.

Truth: camera paths built here (shaky_path's pan and in-plane shake, plus a rotation of the
camera about its centre, K R K^-1), their exact pairwise motions with noise added at the frame
corners as estimates have it, the jitter measured by test_stabilize's moving average; end to
end (slow), simulated flights with and without pitch and roll shake and the metrics module."""

from __future__ import annotations

import numpy as np
import pytest
from test_stabilize import FPS, SIZE, high_frequency, outside_by, pairwise_of, shaky_path

from mosaic_cli.geometry import four_point_to_homography, frame_corners
from mosaic_cli.stabilize.crop import output_warps
from mosaic_cli.stabilize.metrics import cropping_ratio, distortion
from mosaic_cli.stabilize.path import MODELS, camera_motion, fit_model, motion_model, perspective_support, to_normalized
from mosaic_cli.stabilize.pipeline import StabilizeOptions
from mosaic_cli.stabilize.smoothing import GaussianSmoother, L1Smoother


def _rotation(pitch: float, roll: float) -> np.ndarray:
    cp, sp, cr, sr = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    return np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]]) @ np.array([[cr, 0, sr], [0, 1, 0], [-sr, 0, cr]])


def tilt_shaky_path(n: int, seed: int = 0, tilt_deg: float = 0.6, size=SIZE):
    """shaky_path's (shaken, smooth) with the camera also turning about its centre by a 3-8 Hz
    pitch and roll of up to ``tilt_deg`` (focal length: the frame width)."""
    shaken, smooth = shaky_path(n, seed=seed, size=size)
    if tilt_deg == 0:
        return shaken, smooth
    rng = np.random.default_rng(seed + 100)
    t = np.arange(n) / FPS

    def shake():
        f, phase = rng.uniform(3, 8, 3), rng.uniform(0, 2 * np.pi, 3)
        return np.radians(tilt_deg) * np.sin(2 * np.pi * f[:, None] * t + phase[:, None]).mean(axis=0)

    w, h = size
    K = np.array([[w, 0, (w - 1) / 2], [0, w, (h - 1) / 2], [0, 0, 1.0]])
    pitch, roll = shake(), shake()
    return np.stack([K @ _rotation(pitch[k], roll[k]) @ np.linalg.inv(K) @ shaken[k] for k in range(n)]), smooth


def estimated(pairwise: np.ndarray, noise_px: float = 0.1, seed: int = 0, size=SIZE) -> np.ndarray:
    """The pairwise homographies as an estimator gives them: each frame corner's image off by
    Gaussian noise of ``noise_px`` (noise in every entry, the perspective ones included)."""
    rng = np.random.default_rng(seed)
    corners = np.broadcast_to(frame_corners(*size), (len(pairwise), 4, 2))
    moved = np.einsum("nij,npj->npi", pairwise, np.concatenate([corners, np.ones((len(pairwise), 4, 1))], axis=-1))
    moved = moved[..., :2] / moved[..., 2:]
    return four_point_to_homography(corners, moved - corners + rng.normal(0, noise_px, moved.shape))


def plan(pairwise: np.ndarray, model: str, smoother=None, crop=None) -> tuple[np.ndarray, np.ndarray]:
    """(warps, views) of the L1 path (several windows) planned from ``pairwise`` with ``model``."""
    smoother = smoother or L1Smoother(window=60, overlap=20)
    views = smoother.smooth(camera_motion(pairwise, SIZE, MODELS[model]), SIZE, MODELS[model], crop)
    return output_warps(views, SIZE), views


def test_tilt_is_the_default_and_fits_similarity_plus_perspective_exactly():
    assert StabilizeOptions().model == "tilt"
    model = motion_model("tilt")
    truth = model.matrices(np.array([[1.01, 0.02, 0.03, -0.02, 0.004, -0.003], [0.99, -0.01, 0.0, 0.05, -0.002, 0.001]]))
    np.testing.assert_allclose(fit_model(truth, model), truth, atol=1e-12)
    sheared = truth.copy()
    sheared[:, 0, 1] += 0.01  # no shear in the model: it fits the rest
    fitted = fit_model(sheared, model)
    np.testing.assert_allclose(fitted[:, 2, :2], truth[:, 2, :2], atol=1e-3)
    assert np.allclose(fitted[:, 0, 0], fitted[:, 1, 1]) and np.allclose(fitted[:, 0, 1], -fitted[:, 1, 0])


def test_support_tells_pitch_and_roll_shake_from_noise():
    shaken, _ = tilt_shaky_path(150, seed=3)
    motion = np.linalg.inv(to_normalized(estimated(pairwise_of(shaken), seed=3), SIZE))
    assert perspective_support(motion[:119]) == 1.0
    plain, _ = shaky_path(150, seed=3)
    for seed in range(4):  # estimates' noise in the perspective terms, whatever the shake
        motion = np.linalg.inv(to_normalized(estimated(pairwise_of(plain), seed=seed), SIZE))
        assert perspective_support(motion[:119]) == 0.0
    # Perspective terms moving with the shift: as a camera turning makes them (g = c x, h = c y,
    # c < 0), believed; the other way (the sign of an estimator's own shift-perspective
    # trade-off), not.
    shift = motion[:, :2, 2]
    shake = shift - np.stack([np.convolve(np.pad(x, 4, mode="edge"), np.ones(9) / 9, mode="valid") for x in shift.T], 1)
    for c, support in ((-0.25, 1.0), (0.25, 0.0)):
        moved = motion.copy()
        moved[:, 2, :2] = c * shake
        assert perspective_support(moved[:119]) == support
    assert perspective_support(motion[:10]) == 0.0  # too few motions to tell


@pytest.mark.slow
def test_tilt_takes_out_pitch_and_roll_shake_that_a_similarity_leaves():
    shaken, smooth = tilt_shaky_path(120, seed=1)  # 4 s: three windows of the L1 path, the ratios of 6 s
    pairwise = estimated(pairwise_of(shaken), seed=1)
    before = high_frequency(shaken, smooth)
    jitter, warps = {}, {}
    for model in ("similarity", "tilt", "homography"):
        warps[model], _ = plan(pairwise, model)
        jitter[model] = high_frequency(shaken, smooth, warps[model])
        assert outside_by(warps[model]).max() < 0.01, model  # the crop stays inside every frame
        assert 0.85 < cropping_ratio(warps[model], SIZE) < 1.0
    assert jitter["tilt"] < 0.6 * jitter["similarity"], jitter
    assert jitter["tilt"] < 0.15 * before, (before, jitter)
    assert distortion(warps["tilt"], SIZE) > 0.99  # no stretch: a similarity and a keystone


def test_without_pitch_and_roll_shake_tilt_is_the_similaritys_plan():
    shaken, smooth = shaky_path(120, seed=2)
    pairwise = estimated(pairwise_of(shaken), seed=2)
    sim_warps, sim_views = plan(pairwise, "similarity")
    tilt_warps, tilt_views = plan(pairwise, "tilt")
    np.testing.assert_allclose(tilt_views, sim_views, atol=1e-9)
    assert np.all(tilt_views[:, 2, :2] == 0)  # not a keystone, so the renderer's affine warp
    # (homography would have turned the estimates' perspective noise into wobble)
    hom_warps, _ = plan(pairwise, "homography")
    assert high_frequency(shaken, smooth, hom_warps) > 1.1 * high_frequency(shaken, smooth, sim_warps)


@pytest.mark.parametrize("crop", [None, 0.9])
def test_tilt_planned_as_pairs_arrive_is_the_whole_clips(crop):
    # pitch and roll shake in the first half only: windows with and without support, and the seams
    # between (windows of 60 frames, not the default 120: the same four windows in half the frames)
    shaken, _ = tilt_shaky_path(150, seed=5)
    plain, _ = shaky_path(150, seed=5)
    pairwise = estimated(np.concatenate([pairwise_of(shaken)[:75], pairwise_of(plain)[75:]]), seed=5)
    model = motion_model("tilt")
    motion = np.concatenate([camera_motion(H[None], SIZE, model) for H in pairwise])
    smoother = L1Smoother(window=60, overlap=20)
    whole = smoother.smooth(motion, SIZE, model, crop)
    assert np.abs(whole[:50, 2, :2]).max() > 1e-4  # the tilt shake was taken out where it was
    rng = np.random.default_rng(2)
    planner = smoother.planner(SIZE, model, crop)
    cuts = np.sort(rng.choice(np.arange(1, len(motion)), size=12, replace=False))
    views = np.concatenate([planner.push(chunk) for chunk in np.split(motion, cuts)] + [planner.finish()])
    np.testing.assert_array_equal(views, whole)


def test_gaussian_smoother_takes_the_tilt_shake_out_too():
    shaken, smooth = tilt_shaky_path(180, seed=6)
    pairwise = estimated(pairwise_of(shaken), seed=6)
    sim = high_frequency(shaken, smooth, plan(pairwise, "similarity", GaussianSmoother(radius=15))[0])
    tilt = high_frequency(shaken, smooth, plan(pairwise, "tilt", GaussianSmoother(radius=15))[0])
    assert tilt < 0.7 * sim, (sim, tilt)


# --- end to end on simulated flights --------------------------------------------------------------


def _simulated(tmp_path, profile: str, seed: int):
    from conftest import simulated
    from mosaic_cli.simulate import load_ground_truth

    video = simulated(tmp_path / f"{profile}.mp4", "-p", profile, "-n", "150", "--size", "640x360", "--seed", str(seed))
    return video, load_ground_truth(video.with_suffix(".gt.json"))


@pytest.mark.slow
@pytest.mark.parametrize("profile", ["shaky-tilt", "shaky"])
def test_simulated_flight_default_against_similarity(tmp_path, profile):
    from mosaic_cli.estimators import OrbEstimator
    from mosaic_cli.stabilize.metrics import ground_truth_jitter
    from mosaic_cli.track import track_video

    video, gt = _simulated(tmp_path, profile, seed=4)
    track = track_video(video, OrbEstimator(640), show_progress=False)
    size = gt.size
    base = ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, size, gt.fps)
    ratio, warps = {}, {}
    for name in ("similarity", "tilt"):
        model = motion_model(name)
        views = L1Smoother().smooth(camera_motion(track.pairwise, size, model, track.confidence), size, model, None)
        warps[name] = output_warps(views, size)
        ratio[name] = ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, size, gt.fps, warps[name]) / base
    if profile == "shaky-tilt":
        assert ratio["tilt"] < 0.6 * ratio["similarity"], ratio
    else:
        assert ratio["tilt"] == pytest.approx(ratio["similarity"], rel=0.05), ratio
    assert cropping_ratio(warps["tilt"], size) > cropping_ratio(warps["similarity"], size) - 0.005
    assert distortion(warps["tilt"], size) > 0.99
