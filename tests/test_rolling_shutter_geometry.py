"""Row-band motion, the path it samples and the readout, against the simulator's exact rows."""

from __future__ import annotations

import numpy as np
import pytest

from mosaic_cli.geometry import project
from mosaic_cli.geometry.rolling_shutter import (
    band_centres,
    band_corrections,
    band_motion,
    estimate_readout,
    fit_bands,
    row_frame_to_ref,
    similarity_matrix,
)
from mosaic_cli.simulate import RollingShutter, SimulateOptions, plan_simulated_flight

SIZE = (640, 360)


def test_band_motion_of_a_global_similarity_is_that_similarity_in_every_band():
    rng = np.random.default_rng(1)
    src = np.stack([rng.uniform(0, 640, 800), rng.uniform(0, 360, 800)], 1)
    truth = np.array([3.0, -2.0, 0.004, -0.01])
    dst = project(similarity_matrix(truth, SIZE), src)
    got = band_motion(src, dst, SIZE, 12)
    np.testing.assert_allclose(got, np.broadcast_to(truth, (12, 4)), atol=1e-9)


def _true_pair_motion(plan, bands, rng, points=1500, noise=0.05):
    """Each band's motion between consecutive frames, fitted to points moved exactly through
    their own rows (the ground truth's rule), with a little tracking noise."""
    B, M = plan.row_bands, plan.map_to_frame
    w, h = plan.size
    motion = []
    for t in range(len(M) - 1):
        src = np.stack([rng.uniform(0, w, points), rng.uniform(0, h, points)], 1)
        F = row_frame_to_ref(np.linalg.inv(B[t]), src[:, 1], h)
        pm = np.einsum("pij,pj->pi", F, np.c_[src, np.ones(points)])
        pm = pm[:, :2] / pm[:, 2:]
        x = project(M[t + 1], pm)
        for _ in range(3):  # the row it lands on in frame t+1 decides its homography there
            F1 = row_frame_to_ref(np.linalg.inv(B[t + 1]), x[:, 1], h)
            x = project(np.linalg.inv(F1), pm[:, None])[:, 0]  # each point through its own row's inverse
        motion.append(band_motion(src, x + rng.normal(0, noise, x.shape), (w, h), bands))
    return np.array(motion)


@pytest.mark.parametrize("readout,hz,px", [(0.7, 12.0, 5.0), (0.9, 8.0, 5.0)])
def test_corrections_and_readout_from_the_rows_motion(readout, hz, px):
    plan = plan_simulated_flight((2048, 2048), SimulateOptions(frames=60, size=SIZE, seed=2, rolling=RollingShutter(readout, hz, px)))
    rng = np.random.default_rng(0)
    K = 16
    motion = _true_pair_motion(plan, K, rng)
    estimated, costs = estimate_readout(motion, SIZE[1])
    assert abs(estimated - readout) < 0.2 * readout, (estimated, costs)
    C = band_corrections(motion, estimated, SIZE[1])
    wrong, err = [], []
    for t in range(plan.frames):
        for k, yk in enumerate(band_centres(SIZE[1], K)):
            c = np.array([[50.0, yk], [320.0, yk], [590.0, yk]])
            true = project(plan.map_to_frame[t] @ np.linalg.inv(plan.row_bands[t, k]), c)  # band -> mid-time pose
            err.append(true - project(similarity_matrix(C[t, k], SIZE), c))
            wrong.append(true - c)
    rms = lambda a: float(np.sqrt(np.mean(np.sum(np.array(a) ** 2, -1))))  # noqa: E731
    assert rms(wrong) > 0.8  # the rolling shutter moves the bands by about a pixel or more
    assert rms(err) < 0.15 * rms(wrong), (rms(err), rms(wrong))


def test_global_shutter_reads_as_no_readout():
    plan = plan_simulated_flight((2048, 2048), SimulateOptions(profile="shaky", frames=60, size=SIZE, seed=4,
                                                               rolling=RollingShutter(0.0, 12.0, 5.0)))
    motion = _true_pair_motion(plan, 16, np.random.default_rng(1))
    estimated, _ = estimate_readout(motion, SIZE[1])
    assert estimated <= 0.05
    assert np.array_equal(band_corrections(motion, 0.0, SIZE[1]), np.zeros((60, 16, 4)))


def _rolling_pair(rows: np.ndarray, xs: np.ndarray, channels_at) -> tuple[np.ndarray, np.ndarray]:
    """Tracks at (xs, rows) moved each by the similarity of its own row (channels_at(row) -> (4,))."""
    src = np.stack([xs, rows], 1)
    dst = np.array([project(similarity_matrix(channels_at(y), SIZE), p[None])[0] for p, y in zip(src, rows)])
    return src, dst


def test_bands_without_tracks_are_bridged_from_the_nearest_fitted_ones_instead_of_raising():
    """A textureless lower half (water, a uniform field): only the upper rows have tracks."""
    rng = np.random.default_rng(3)
    rows, xs = rng.uniform(0, 0.4 * SIZE[1], 600), rng.uniform(0, SIZE[0], 600)

    def motion_of(y):  # a shift that changes with the row, as under a rolling shutter
        return np.array([2.0 + 0.01 * y, -1.0, 0.0, 0.0])

    src, dst = _rolling_pair(rows, xs, motion_of)
    got, bridged = fit_bands(src, dst, SIZE, 16)
    centres = band_centres(SIZE[1], 16)
    far = centres > 0.4 * SIZE[1] + 2 * SIZE[1] / 16  # bands more than two band heights below the last track
    assert bridged[far].all() and not bridged[centres < 0.3 * SIZE[1]].any()
    assert np.isfinite(got).all()
    last = np.flatnonzero(~bridged).max()  # held flat below the last fitted band
    below = np.arange(16) > last
    assert bridged[below].all() and np.array_equal(got[below], np.broadcast_to(got[last], (int(below.sum()), 4)))
    # The fitted bands read their rows' motion (the Gaussian row weights blur it by a little).
    fitted = ~bridged & (centres < 0.3 * SIZE[1])
    assert np.abs(got[fitted, 0] - (2.0 + 0.01 * centres[fitted])).max() < 0.05


@pytest.mark.parametrize("case", ["one spot", "no tracks", "nan tracks"])
def test_degenerate_tracks_never_raise_and_fall_back_to_the_frame_s_motion(case):
    """Every track on one spot (a single corner tracked many times), none at all, or
    non-numbers from a tracker: no band can tell its rotation from its shift."""
    truth = np.array([1.5, -0.5, 0.0, 0.0])
    n = 0 if case == "no tracks" else 200
    src = np.tile([[320.0, 100.0]], (n, 1))
    dst = src + truth[:2]
    if case == "nan tracks":
        src[::2] = np.nan
    got, bridged = fit_bands(src, dst, SIZE, 16)
    assert bridged.all() and np.isfinite(got).all()
    if n:  # the whole frame's least-squares fit: the shift it saw, no rotation or scale invented
        np.testing.assert_allclose(project(similarity_matrix(got[0], SIZE), src[1:2]), dst[1:2], atol=1e-6)
