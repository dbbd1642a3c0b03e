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
            x = np.array([project(np.linalg.inv(G), q[None])[0] for G, q in zip(F1, pm)])
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
