"""Homography algebra, checked against OpenCV and against exact constructions."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mosaic_cli.geometry import (
    chain,
    corner_error,
    cumulative,
    four_point_to_homography,
    frame_corners,
    homography_to_four_point,
    is_valid,
    normalize,
    project,
    rect_corners,
    resize_matrix,
    to_resolution,
)

SIZE = (320, 180)


def random_homographies(n: int, seed: int = 0, size=SIZE, spread: float = 8.0) -> np.ndarray:
    """Plausible frame-to-frame homographies: the frame corners moved by up to ``spread`` px."""
    rng = np.random.default_rng(seed)
    offsets = rng.uniform(-spread, spread, (n, 4, 2))
    return four_point_to_homography(frame_corners(*size), offsets)


def test_project_matches_opencv():
    H = random_homographies(1, seed=1)[0]
    pts = np.random.default_rng(2).uniform(0, 300, (50, 2))
    ref = cv2.perspectiveTransform(pts[None].astype(np.float64), H)[0]
    np.testing.assert_allclose(project(H, pts), ref, atol=1e-9)
    # batched over homographies
    Hs = random_homographies(3, seed=3)
    out = project(Hs, np.broadcast_to(pts, (3, 50, 2)))
    for k in range(3):
        np.testing.assert_allclose(out[k], cv2.perspectiveTransform(pts[None], Hs[k])[0], atol=1e-9)


def test_normalize_keeps_the_mapping():
    H = random_homographies(1)[0] * 3.7
    assert normalize(H)[2, 2] == pytest.approx(1.0)
    pts = np.array([[10.0, 20.0], [200.0, 100.0]])
    np.testing.assert_allclose(project(normalize(H), pts), project(H, pts))


def test_chain_maps_points_step_by_step():
    pairwise = random_homographies(6)
    pts = np.array([[5.0, 7.0], [160.0, 90.0], [300.0, 170.0]])
    stepped = pts
    for k in range(1, 5):
        stepped = project(pairwise[k], stepped)
    np.testing.assert_allclose(project(chain(pairwise, 1, 5), pts), stepped, atol=1e-9)
    # backwards is the inverse, and the empty chain is the identity
    np.testing.assert_allclose(project(chain(pairwise, 5, 1), stepped), pts, atol=1e-9)
    np.testing.assert_allclose(chain(pairwise, 3, 3), np.eye(3))
    # chains compose: H_[1,5] = H_[3,5] H_[1,3]
    np.testing.assert_allclose(normalize(chain(pairwise, 3, 5) @ chain(pairwise, 1, 3)), chain(pairwise, 1, 5), atol=1e-12)


def test_cumulative_equals_chains_from_zero():
    pairwise = random_homographies(7, seed=4)
    cum = cumulative(pairwise)
    assert cum.shape == (8, 3, 3)
    for t in range(8):
        np.testing.assert_allclose(cum[t], chain(pairwise, 0, t), atol=1e-12)
    assert cumulative(np.zeros((0, 3, 3))).shape == (1, 3, 3)


@pytest.mark.parametrize("interp, src, dst", [
    (cv2.INTER_LINEAR, (40, 30), (100, 90)),   # upscale, non-integer and anisotropic
    (cv2.INTER_LINEAR, (64, 48), (128, 96)),
    (cv2.INTER_AREA, (128, 96), (32, 24)),     # integer downscale by 4
    (cv2.INTER_AREA, (1280, 720), (320, 180)),
])
def test_resize_matrix_is_the_pixel_centre_convention_of_cv2_resize(interp, src, dst):
    """Resize an image whose pixel values are their own x (and y) coordinates: the value at
    each output pixel tells which source position it was sampled from."""
    w, h = src
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    got_x = cv2.resize(xs, dst, interpolation=interp)
    got_y = cv2.resize(ys, dst, interpolation=interp)
    S_inv = np.linalg.inv(resize_matrix(src, dst))
    dy, dx = np.mgrid[0:dst[1], 0:dst[0]].astype(np.float64)
    expect = project(S_inv, np.stack([dx, dy], axis=-1).reshape(-1, 2)).reshape(dst[1], dst[0], 2)
    # away from the border, where cv2 clamps
    inner = (expect[..., 0] >= 0) & (expect[..., 0] <= w - 1) & (expect[..., 1] >= 0) & (expect[..., 1] <= h - 1)
    np.testing.assert_allclose(got_x[inner], expect[..., 0][inner], atol=1e-3)
    np.testing.assert_allclose(got_y[inner], expect[..., 1][inner], atol=1e-3)


def test_to_resolution_agrees_with_warping_at_both_resolutions():
    """Warping a full-res image with the converted matrix, then downscaling, equals
    downscaling first and warping with the small-resolution matrix.  A strong zoom makes the
    pixel-centre offsets matter: ignoring them (H_full = diag(4,4,1) H diag(1/4,1/4,1))
    triples the error."""
    small, full = (80, 45), (320, 180)
    ys, xs = np.mgrid[0:180, 0:320].astype(np.float32)
    base = np.sin(xs / 9.0) * np.cos(ys / 11.0) + 0.5 * np.sin((xs + ys) / 13.0)
    H_small = np.array([[1.6, 0.1, -30], [-0.1, 1.6, -20], [0, 0, 1.0]])
    b = cv2.warpPerspective(cv2.resize(base, small, interpolation=cv2.INTER_AREA), H_small, small)
    inner = (slice(8, -8), slice(8, -8))

    def mismatch(H_full):
        a = cv2.resize(cv2.warpPerspective(base, H_full, full), small, interpolation=cv2.INTER_AREA)
        return np.abs(a[inner] - b[inner]).mean()

    naive = normalize(np.diag([4.0, 4.0, 1.0]) @ H_small @ np.diag([0.25, 0.25, 1.0]))
    assert mismatch(to_resolution(H_small, small, full)) < 0.025 < mismatch(naive)
    # round trip, batched
    Hs = random_homographies(4, seed=6, size=small)
    np.testing.assert_allclose(to_resolution(to_resolution(Hs, small, full), full, small), normalize(Hs), atol=1e-10)


def test_to_resolution_of_a_translation():
    """A 1 px shift at 320 wide is exactly a 4 px shift at 1280, whatever the pixel convention."""
    T = np.array([[1, 0, 1.0], [0, 1, -2.0], [0, 0, 1]])
    np.testing.assert_allclose(to_resolution(T, (320, 180), (1280, 720)), [[1, 0, 4], [0, 1, -8], [0, 0, 1]], atol=1e-12)
    # a scaling about the image centre stays a scaling about the (new) image centre
    c = np.array([159.5, 89.5])
    Z = np.array([[1.1, 0, -0.1 * c[0]], [0, 1.1, -0.1 * c[1]], [0, 0, 1]])
    Z_full = to_resolution(Z, (320, 180), (1280, 720))
    np.testing.assert_allclose(project(Z_full, np.array([[639.5, 359.5]])), [[639.5, 359.5]], atol=1e-9)


def test_four_point_round_trip_and_opencv():
    corners = rect_corners(96, 26, 128, 128)
    offsets = np.random.default_rng(1).uniform(-20, 20, (5, 4, 2))
    H = four_point_to_homography(corners, offsets)
    assert H.shape == (5, 3, 3)
    np.testing.assert_allclose(homography_to_four_point(H, corners), offsets, atol=1e-9)
    for k in range(5):
        ref = cv2.getPerspectiveTransform(corners.astype(np.float32), (corners + offsets[k]).astype(np.float32))
        assert corner_error(H[k], ref, (320, 180)) < 1e-3  # OpenCV solves in float32
    np.testing.assert_allclose(four_point_to_homography(corners, np.zeros((4, 2))), np.eye(3), atol=1e-12)


def test_corner_error_values():
    T = np.array([[1, 0, 3.0], [0, 1, 4.0], [0, 0, 1]])
    assert corner_error(np.eye(3), np.eye(3), SIZE) == pytest.approx(0.0)
    assert corner_error(T, np.eye(3), SIZE) == pytest.approx(5.0)
    # moving one corner by 8 px moves the mean by 2
    offsets = np.zeros((4, 2))
    offsets[2] = [0, 8]
    H = four_point_to_homography(frame_corners(*SIZE), offsets)
    assert corner_error(H, np.eye(3), SIZE) == pytest.approx(2.0)
    assert corner_error(np.stack([T, np.eye(3)]), np.eye(3), SIZE).tolist() == pytest.approx([5.0, 0.0])


def test_is_valid_accepts_plausible_motion():
    assert is_valid(np.eye(3), SIZE)
    assert all(is_valid(H, SIZE) for H in random_homographies(20, spread=15))
    assert is_valid(np.eye(3) * 5, SIZE)  # scale of the matrix is irrelevant


@pytest.mark.parametrize("name, H", [
    ("nan", np.full((3, 3), np.nan)),
    ("inf", np.array([[1, 0, np.inf], [0, 1, 0], [0, 0, 1.0]])),
    ("singular", np.array([[1, 2, 0], [2, 4, 0], [0, 0, 1.0]])),
    ("zero h33", np.array([[1, 0, 0], [0, 1, 0], [0, 0, 0.0]])),
    ("mirror", np.diag([-1.0, 1.0, 1.0])),
    ("collapse", np.diag([0.1, 0.1, 1.0])),
    ("blow-up", np.diag([3.0, 3.0, 1.0])),
    ("horizon inside the frame", np.array([[1, 0, 0], [0, 1, 0], [-0.005, 0, 1.0]])),
    ("wrong shape", np.eye(2)),
])
def test_is_valid_rejects_degenerate(name, H):
    assert not is_valid(H, SIZE), name


def test_is_valid_bounds():
    T = np.array([[1, 0, 30.0], [0, 1, 0], [0, 0, 1]])
    assert is_valid(T, SIZE) and not is_valid(T, SIZE, max_corner_shift=20.0)
    zoom = np.diag([1.8, 1.8, 1.0])
    assert is_valid(zoom, SIZE) and not is_valid(zoom, SIZE, max_area_ratio=2.0)
    # a bow-tie (two corners swapped) is not a view of a plane
    c = frame_corners(*SIZE)
    bowtie = cv2.getPerspectiveTransform(c.astype(np.float32), c[[1, 0, 2, 3]].astype(np.float32))
    assert not is_valid(bowtie, SIZE)
