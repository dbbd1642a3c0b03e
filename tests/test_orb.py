"""ORB estimator: accuracy on known warps, streaming behaviour, graceful failure."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import render, textured_image
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import IdentityEstimator, OrbConfig, OrbEstimator, estimate_stream, make_estimator
from mosaic_cli.geometry import corner_error, four_point_to_homography, frame_corners

HD = (1280, 720)


@pytest.fixture(scope="module")
def ground() -> np.ndarray:
    return textured_image(2000, 1300, seed=3)


def warped_pair(ground, H, size=HD, origin=(400.0, 300.0)):
    """Two views of ``ground``; H maps pixels of the first view to the second, exactly."""
    view0 = np.array([[1, 0, origin[0]], [0, 1, origin[1]], [0, 0, 1.0]])
    return render(ground, view0, size), render(ground, view0 @ np.linalg.inv(H), size)


def known_warps(n, seed, size=HD, spread=30.0):
    """Random homographies that move the frame corners by up to ``spread`` pixels."""
    offsets = np.random.default_rng(seed).uniform(-spread, spread, (n, 4, 2))
    return four_point_to_homography(frame_corners(*size), offsets)


def estimate_pair(estimator, a, b):
    estimator.reset((a.shape[1], a.shape[0]))
    assert estimator.feed(a) == []
    (estimate,) = estimator.feed(b)
    assert estimator.finish() == []
    return estimate


@pytest.mark.parametrize("method, refine", [("usac", "lk"), ("ransac", "lk"), ("usac", "ecc")])
def test_recovers_known_warps_at_hd(ground, method, refine):
    """Working at 320x180, the full-resolution (1280x720) corner error stays below 0.5 px."""
    est = OrbEstimator(320, OrbConfig(method=method, refine=refine))
    errors = []
    for H in known_warps(4, seed=11):
        e = estimate_pair(est, *warped_pair(ground, H), )
        errors.append(corner_error(e.H, H, HD))
        assert e.confidence > 0.5
    assert max(errors) < 0.5, errors


def test_features_alone_are_accurate_to_about_a_working_pixel(ground):
    """Without the polish the feature fit is still within about one pixel at the working
    resolution (4 px at 1280x720), and the polish improves on it: it refines, it does not
    make the estimate."""
    for H in known_warps(3, seed=12):
        pair = warped_pair(ground, H)
        plain = corner_error(estimate_pair(OrbEstimator(320, OrbConfig(refine=None)), *pair).H, H, HD)
        polished = corner_error(estimate_pair(OrbEstimator(320), *pair).H, H, HD)
        assert polished < plain < 4.0


def test_streams_one_estimate_per_new_frame_and_describes_each_frame_once(ground, monkeypatch):
    H = known_warps(1, seed=2, size=(640, 360), spread=10)[0]
    frames = [render(ground, np.array([[1, 0, 300.0], [0, 1, 200.0], [0, 0, 1]]) @ np.linalg.inv(np.linalg.matrix_power(H, k)), (640, 360)) for k in range(5)]
    est = OrbEstimator(320)
    calls = []
    original = est.features_of
    monkeypatch.setattr(est, "features_of", lambda gray: calls.append(gray.shape) or original(gray))
    estimates = list(estimate_stream(est, frames, (640, 360)))
    assert len(estimates) == 4 and len(calls) == 5
    assert all(shape == (180, 320) for shape in calls)
    for e in estimates:
        assert corner_error(e.H, H, (640, 360)) < 0.5
    # a reset starts a new video: no pair across the boundary
    est.reset((640, 360))
    assert est.feed(frames[0]) == []


def flat(value, size=(320, 180)):
    return np.full((size[1], size[0], 3), value, np.uint8)


@pytest.mark.parametrize("name, pair", [
    ("black", (flat(0), flat(0))),
    ("textureless", (flat(128), flat(128))),
    ("smooth gradient", (np.repeat(np.linspace(0, 255, 320, dtype=np.uint8)[None, :, None], 180, 0).repeat(3, 2),) * 2),
    ("texture then black", (textured_image(320, 180, seed=4), flat(0))),
])
def test_failure_is_identity_with_zero_confidence(name, pair):
    for config in (OrbConfig(), OrbConfig(method="ransac", refine=None)):
        e = estimate_pair(OrbEstimator(320, config), *pair)
        assert np.array_equal(e.H, np.eye(3)) and e.confidence == 0.0, name


def test_unrelated_frames_are_failed_pairs_not_invented_motions():
    """Noise and unrelated textures in turn: no homography relates any pair, so every pair is
    reported failed (identity, confidence 0), as stitch and stabilize expect a failure to read."""
    rng = np.random.default_rng(0)
    est = OrbEstimator(320)
    est.reset((320, 180))
    out = []
    for k in range(8):
        frame = textured_image(320, 180, seed=100 + k) if k % 2 else rng.integers(0, 255, (180, 320, 3), dtype=np.uint8)
        out += est.feed(frame)
    assert len(out) == 7
    for e in out:
        assert np.array_equal(e.H, np.eye(3)) and e.confidence == 0.0


def test_one_frame_video_gives_no_pairs():
    assert list(estimate_stream(OrbEstimator(320), [textured_image(320, 180)], (320, 180))) == []


def test_identity_estimator():
    frames = [textured_image(64, 48, seed=k) for k in range(3)]
    out = list(estimate_stream(IdentityEstimator(64), frames, (64, 48)))
    assert len(out) == 2 and all(np.array_equal(e.H, np.eye(3)) and e.confidence == 0.0 for e in out)


def test_make_estimator_validates_names_and_widths():
    assert isinstance(make_estimator("orb"), OrbEstimator)
    assert make_estimator("orb-ransac").config.method == "ransac"
    with pytest.raises(BadInput, match="unknown estimator"):
        make_estimator("sift")
    with pytest.raises(BadInput, match="work-width"):
        make_estimator("orb", work_width=8)
    with pytest.raises(ValueError):
        OrbConfig(method="lmeds")


def test_recovers_known_warps_on_real_aerial_imagery(shared_data):
    """The same < 0.5 px at 1280x720 over a real orthophoto (conifer forest, NEON), when the
    shared data sits beside the repository."""
    import cv2

    path = shared_data / "aerial_stills" / "deepforest_neon_orthophoto" / "2019_YELL_2_541000_4977000_image_crop.png"
    if not path.exists():
        pytest.skip(f"{path.name} is not present")
    photo = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
    # the photo is 1249x1035: view it at 1.6x so a 1280x720 frame (and its warps) fits inside
    ground = cv2.resize(photo, None, fx=1.6, fy=1.6, interpolation=cv2.INTER_CUBIC)
    est = OrbEstimator(320)
    errors = [corner_error(estimate_pair(est, *warped_pair(ground, H, origin=(300.0, 300.0))).H, H, HD)
              for H in known_warps(3, seed=21)]
    assert max(errors) < 0.5, errors
