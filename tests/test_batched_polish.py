"""The learned estimator's polish and correlation check batched in torch (estimators/batched.py,
``-e lstm:polish-with=torch``; the default on a GPU), on the CPU device against OpenCV:

- its pyramid and derivatives are OpenCV's to the grey level, and its Lucas-Kanade tracks
  ``cv2.calcOpticalFlowPyrLK``'s (the same status, tracks within a thousandth of a px) on
  textured images with known subpixel shifts, as far from the truth;
- its robust refit finds a known homography through noisy tracks with outliers, as
  ``cv2.findHomography(RANSAC)`` does, and its inliers are the true ones;
- its correlation check is ``correlation.detail_zncc`` and its last check ``refine``'s;
- on simulated flights (a paper one, and one with exposure drift, noise and blur and bursts of
  spoilt frames whose pairs the batched polish hands to OpenCV) the estimates are OpenCV's
  polish's within 0.05 working px (median corner difference), by the same paths, as accurate;
- the CPU default never runs it; on a GPU (marked cuda) it runs by default and agrees with
  the CPU device's.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from conftest import textured_image
from mosaic_cli.estimators import batched, make_estimator
from mosaic_cli.estimators.correlation import detail_zncc, fine_detail
from mosaic_cli.estimators.refine import CornerConfig, _close_and_valid, points_to_track
from mosaic_cli.geometry import corner_error

pytestmark = pytest.mark.usefixtures("one_torch_thread")

WORK = (320, 180)
LK_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)


def gray_texture(width: int, height: int, seed: int) -> np.ndarray:
    return cv2.cvtColor(textured_image(width, height, seed=seed), cv2.COLOR_RGB2GRAY)


def shifted_pairs(count: int, seed: int) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """``count`` working-size (prev, cur) pairs of one texture, cur moved by a known subpixel
    shift, and each pair's shift."""
    rng = np.random.default_rng(seed)
    ground = gray_texture(900, 600, seed)
    prevs, curs, shifts = [], [], []
    for _ in range(count):
        shift = rng.uniform(-3, 3, 2)
        x0, y0 = rng.uniform(100, 400), rng.uniform(100, 300)
        at = np.array([[1, 0, x0], [0, 1, y0]])
        moved = at - np.array([[0, 0, shift[0]], [0, 0, shift[1]]])
        prevs.append(cv2.warpAffine(ground, at, WORK, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP))
        curs.append(cv2.warpAffine(ground, moved, WORK, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP))
        shifts.append(shift)
    return prevs, curs, shifts


def padded(arrays: list[np.ndarray]) -> torch.Tensor:
    out = np.zeros((len(arrays), max(len(a) for a in arrays), 2), np.float32)
    for i, a in enumerate(arrays):
        out[i, : len(a)] = a
    return torch.from_numpy(out)


def test_the_pyramid_and_the_derivatives_are_opencvs():
    for w, h in ((320, 180), (161, 91), (41, 23)):
        image = gray_texture(w, h, seed=w)
        assert np.array_equal(batched.pyr_down(torch.from_numpy(image)[None])[0].numpy(), cv2.pyrDown(image))
        d = batched.scharr(torch.from_numpy(image)[None])[0].numpy()
        assert np.array_equal(d[0], cv2.Scharr(image, cv2.CV_16S, 1, 0, borderType=cv2.BORDER_REFLECT_101))
        assert np.array_equal(d[1], cv2.Scharr(image, cv2.CV_16S, 0, 1, borderType=cv2.BORDER_REFLECT_101))
    assert batched.pyramid_levels(WORK, 11, 1) == 1
    assert batched.pyramid_levels(WORK, 31, 4) == 2  # OpenCV stops before a level under the window: 40x23


@pytest.mark.slow
@pytest.mark.parametrize("window, levels", [(11, 1), (31, 4)])
def test_the_tracks_are_opencvs(window, levels):
    prevs, curs, shifts = shifted_pairs(4, seed=window)
    rng = np.random.default_rng(1)
    points = [points_to_track(p, CornerConfig(max_points=200)) for p in prevs]
    points[0] = np.vstack([points[0], [[2.0, 3.0], [318.5, 177.0]]]).astype(np.float32)  # near the border
    guesses = [(p + s + rng.normal(0, 1.0, p.shape)).astype(np.float32) for p, s in zip(points, shifts)]
    guesses[0][-1] = (400.0, 400.0)  # starts outside the frame: lost
    tracked, status = batched.track(torch.from_numpy(np.stack(prevs)), torch.from_numpy(np.stack(curs)), padded(points),
                                    padded(guesses), window, levels)
    gaps, ours, theirs, agree = [], [], [], []
    for b, (pts, guess, shift) in enumerate(zip(points, guesses, shifts)):
        cv_tracks, cv_status, _ = cv2.calcOpticalFlowPyrLK(prevs[b], curs[b], pts.reshape(-1, 1, 2), guess.reshape(-1, 1, 2).copy(),
                                                           winSize=(window, window), maxLevel=levels, criteria=LK_CRITERIA,
                                                           flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        cv_ok, ok = cv_status.ravel() == 1, status[b, : len(pts)].numpy()
        agree.append(cv_ok == ok)
        both = cv_ok & ok
        mine, cv_tracks = tracked[b, : len(pts)].numpy()[both], cv_tracks.reshape(-1, 2)[both]
        gaps.append(np.linalg.norm(mine - cv_tracks, axis=1))
        ours.append(np.linalg.norm(mine - (pts[both] + shift), axis=1))
        theirs.append(np.linalg.norm(cv_tracks - (pts[both] + shift), axis=1))
    assert not status[0, len(points[0]) - 1]  # lost, as OpenCV loses it
    assert np.concatenate(agree).mean() >= 0.99
    gap = np.concatenate(gaps)
    assert np.median(gap) < 1e-4 and np.percentile(gap, 99) < 1e-3
    assert np.median(np.concatenate(ours)) < 0.1  # tracks of a known shift
    assert abs(np.median(np.concatenate(ours)) - np.median(np.concatenate(theirs))) < 1e-3


def test_the_refit_finds_a_known_homography_through_outliers():
    rng = np.random.default_rng(3)
    B, N = 6, 150
    truth = np.stack([np.array([[1.0 + rng.normal(0, 0.01), rng.normal(0, 0.02), rng.uniform(-5, 5)],
                                [rng.normal(0, 0.02), 1.0 + rng.normal(0, 0.01), rng.uniform(-5, 5)],
                                [rng.normal(0, 2e-5), rng.normal(0, 2e-5), 1.0]]) for _ in range(B)])
    src = rng.uniform([0, 0], WORK, (B, N, 2)).astype(np.float32)
    dst = np.stack([cv2.perspectiveTransform(s[None], H)[0] for s, H in zip(src, truth)]) + rng.normal(0, 0.08, (B, N, 2))
    outlier = rng.random((B, N)) < 0.25
    dst[outlier] += rng.uniform(2, 10, (outlier.sum(), 2)) * rng.choice([-1, 1], (outlier.sum(), 2))
    dst = dst.astype(np.float32)
    ok = np.ones((B, N), bool)
    ok[:, -10:] = False  # not asked: never an inlier
    H, inliers = batched.fit_homography(torch.from_numpy(src), torch.from_numpy(dst), torch.from_numpy(ok), 0.5)
    H, inliers = H.numpy(), inliers.numpy()
    assert not inliers[:, -10:].any()
    for b in range(B):
        cv_H, _ = cv2.findHomography(src[b][ok[b]], dst[b][ok[b]], cv2.RANSAC, 0.5, maxIters=300, confidence=0.999)
        assert corner_error(H[b], truth[b], WORK) < 0.05
        assert corner_error(H[b], cv_H, WORK) < 0.05
        assert np.mean(inliers[b][ok[b]] == ~outlier[b][ok[b]]) > 0.95


@pytest.fixture(scope="module")
def pair_frames():
    """Two working frames of the ``flight`` fixture's kind: a known warp between them."""
    ground = gray_texture(1000, 700, seed=11)
    to_map = np.array([[1, 0, 300.0], [0, 1, 200.0], [0, 0, 1]])
    motion = np.array([[0.998, 0.03, 4.2], [-0.03, 0.998, -2.7], [1e-5, -2e-5, 1.0]])
    prev = cv2.warpPerspective(ground, to_map, WORK, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    cur = cv2.warpPerspective(ground, to_map @ np.linalg.inv(motion), WORK, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    other = cv2.warpPerspective(gray_texture(1000, 700, seed=12), to_map, WORK, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    return prev, cur, other, motion


@pytest.mark.parametrize("masked", [False, True])
def test_the_correlation_check_is_detail_zncc(pair_frames, masked):
    prev, cur, other, motion = pair_frames
    positions = np.array([[96, 26], [0, 0], [192, 52]])
    mask = None
    if masked:
        mask = np.full(WORK[::-1], 255, np.uint8)
        mask[10:60, 200:300] = 0
    usable = np.ones(WORK[::-1], np.float32) if mask is None else (mask > 0).astype(np.float32)
    cases = [(prev, cur, motion), (prev, cur, motion @ np.array([[1, 0, 1.5], [0, 1, 0], [0, 0, 1]])), (prev, other, motion),
             (prev, cur, np.array([[1, 0, 250.0], [0, 1, 0], [0, 0, 1]]))]  # off the frame: too few pixels, 0
    want = [detail_zncc(fine_detail(a), fine_detail(b), H, positions, 128, usable, mask) for a, b, H in cases]
    got = batched.detail_zncc(batched.fine_detail(torch.from_numpy(np.stack([a for a, _, _ in cases]))),
                              batched.fine_detail(torch.from_numpy(np.stack([b for _, b, _ in cases]))),
                              torch.from_numpy(np.stack([H for _, _, H in cases])), torch.from_numpy(positions), 128,
                              torch.from_numpy(usable), None if mask is None else torch.from_numpy(mask))
    assert want[0] > 0.9 and want[2] < 0.1 and want[3] == 0.0  # registered, unrelated, outside: the cases differ
    np.testing.assert_allclose(got.numpy(), want, atol=1e-4)
    np.testing.assert_allclose(batched.fine_detail(torch.from_numpy(prev)[None])[0].numpy(), fine_detail(prev), atol=1e-4)


def test_the_last_check_is_refines():
    rng = np.random.default_rng(5)
    seeds, polished = [], []
    for _ in range(300):
        seed = np.eye(3) + np.diag([1, 1, 0]) * rng.normal(0, 0.02, (3, 3)) + np.array([[0, 0, 1], [0, 0, 1], [0, 0, 0]]) * rng.normal(0, 5, (3, 3))
        jitter = rng.normal(0, [[0.005, 0.005, 1.5], [0.005, 0.005, 1.5], [3e-5, 3e-5, 0]])
        polished.append(seed + jitter * rng.choice([0.2, 1, 5, 300]))
        seeds.append(seed)
    polished[0] = np.diag([-1.0, 1, 1])  # a mirror
    polished[1] = np.full((3, 3), np.nan)
    want = [_close_and_valid(p, s, WORK[::-1], 3.0) for p, s in zip(polished, seeds)]
    got = batched.settled(torch.from_numpy(np.array(polished)), torch.from_numpy(np.array(seeds)), WORK, 3.0).numpy()
    assert 0.2 < np.mean(want) < 0.9  # both kinds are tried
    assert list(got) == want


def estimates(spec: str, frames: list[np.ndarray], device: str = "cpu"):
    est = make_estimator(spec, device=device)
    est.reset((frames[0].shape[1], frames[0].shape[0]))
    out = []
    for f in frames:
        out += est.feed(f)
    return out + est.finish(), est


@pytest.fixture(scope="module")
def flights():
    """A paper flight and a degraded one (exposure drift, noise, blur, and bursts of frames
    without a motion cue), 640x360 over the procedural map, with their true pairwise motion."""
    from mosaic_cli.simulate import SimulateOptions, load_map, plan_simulated_flight, render_frames
    from mosaic_cli.simulate.bursts import BurstSpec

    out = {}
    ground = load_map(None, seed=3)  # one map for both (seed 3: the map the session has made for other tests)
    for profile, seed, bursts in (("paper", 4, None), ("hard", 9, BurstSpec(("glare", "blur", "dark")))):
        options = SimulateOptions(profile=profile, frames=40, size=(640, 360), seed=seed, bursts=bursts)  # 3 chunks of pairs
        plan = plan_simulated_flight((ground.shape[1], ground.shape[0]), options)
        frames = [cv2.cvtColor(f, cv2.COLOR_RGB2BGR) for f in render_frames(ground, plan)]
        out[profile] = frames, plan.pairwise
    return out


@pytest.mark.slow
def test_on_flights_the_batched_polish_is_opencvs(flights, monkeypatch):
    calls = {"polish": 0}
    polish = batched.polish

    def counted(*args, **kwargs):
        calls["polish"] += 1
        return polish(*args, **kwargs)

    monkeypatch.setattr(batched, "polish", counted)
    for profile, (frames, truth) in flights.items():
        before = calls["polish"]
        opencv, est = estimates("lstm", frames)
        assert calls["polish"] == before  # the CPU default: OpenCV alone, as before
        torch_, est_t = estimates("lstm:polish-with=torch", frames)
        assert calls["polish"] >= before + 3  # chunks of 16 pairs
        scale = frames[0].shape[1] / est.work_size[0]
        gap = np.array([corner_error(a.H, b.H, (640, 360)) for a, b in zip(opencv, torch_)]) / scale  # working px
        same_path = np.mean([a.path == b.path for a, b in zip(opencv, torch_)])
        assert np.median(gap) <= 0.05, profile
        assert same_path >= 0.995, profile
        err = [np.mean([corner_error(e.H, t, (640, 360)) for e, t in zip(run, truth) if e.path == "learned"]) for run in (opencv, torch_)]
        assert err[1] <= 1.1 * err[0] + 0.02, (profile, err)
    assert est_t.path_counts["carried"] > 0 and est_t.path_counts == est.path_counts  # the spoilt pairs handed to OpenCV


def test_the_option_reads_as_written():
    assert make_estimator("lstm:polish-with=torch", device="cpu")._batched
    assert not make_estimator("lstm", device="cpu")._batched
    assert not make_estimator("lstm:polish-with=opencv", device="cpu")._batched
    assert not make_estimator("lstm:polish-with=torch:refine=ecc", device="cpu")._batched  # only the LK polish is batched


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
def test_on_the_gpu_it_runs_by_default_and_agrees_with_the_cpu_device(flights):
    prevs, curs, shifts = shifted_pairs(3, seed=2)
    points = padded([points_to_track(p, CornerConfig(max_points=200)) for p in prevs])
    guess = points + torch.from_numpy(np.array(shifts, np.float32))[:, None]
    args = (torch.from_numpy(np.stack(prevs)), torch.from_numpy(np.stack(curs)), points, guess, 11, 1)
    cpu_tracks, cpu_status = batched.track(*args)
    gpu_tracks, gpu_status = batched.track(*(a.cuda() if isinstance(a, torch.Tensor) else a for a in args))
    assert torch.equal(cpu_status, gpu_status.cpu())
    assert (cpu_tracks - gpu_tracks.cpu()).abs().max() < 1e-3
    frames, _ = flights["paper"]
    assert make_estimator("lstm", device="cuda")._batched
    cpu, _ = estimates("lstm:polish-with=torch:precision=fp32", frames)
    gpu, _ = estimates("lstm", frames, device="cuda")
    gap = [corner_error(a.H, b.H, (640, 360)) / 2 for a, b in zip(cpu, gpu)]
    assert np.median(gap) <= 0.05
    assert np.mean([a.path == b.path for a, b in zip(cpu, gpu)]) >= 0.995
