"""Homography algebra: chaining, resolution changes, the DLT, 4-corner parametrisation, errors, validity.

All functions are pure and accept numpy arrays; leading batch dimensions are allowed where noted.
See :mod:`mosaic_cli.geometry` for the pixel and direction conventions.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = [
    "normalize",
    "project",
    "chain",
    "cumulative",
    "resize_matrix",
    "to_resolution",
    "rect_corners",
    "frame_corners",
    "weighted_dlt",
    "four_point_to_homography",
    "homography_to_four_point",
    "corner_error",
    "is_valid",
    "IDENTITY",
]

IDENTITY = np.eye(3)


def normalize(H: np.ndarray) -> np.ndarray:
    """Scale ``H`` (..., 3, 3) so that H[..., 2, 2] == 1."""
    H = np.asarray(H, dtype=np.float64)
    return H / H[..., 2:3, 2:3]


def project(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map points (..., N, 2) through homographies (..., 3, 3); returns (..., N, 2)."""
    H = np.asarray(H, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    homog = np.concatenate([points, np.ones(points.shape[:-1] + (1,))], axis=-1)
    mapped = homog @ np.swapaxes(H, -1, -2)
    return mapped[..., :2] / mapped[..., 2:3]


def chain(pairwise: Sequence[np.ndarray], t: int, s: int) -> np.ndarray:
    """H_[t,s]: frame t -> frame s from ``pairwise[k]`` (frame k -> k+1). s < t gives the inverse chain."""
    if s == t:
        return np.eye(3)
    if s < t:
        return normalize(np.linalg.inv(chain(pairwise, s, t)))
    H = np.eye(3)
    for k in range(t, s):
        H = np.asarray(pairwise[k], dtype=np.float64) @ H
        H = H / H[2, 2]
    return H


def cumulative(pairwise: Sequence[np.ndarray]) -> np.ndarray:
    """H_[0,t] for t = 0..N-1 as an (N, 3, 3) array, given N-1 pairwise matrices."""
    out = np.empty((len(pairwise) + 1, 3, 3))
    out[0] = np.eye(3)
    for k, H in enumerate(pairwise):
        out[k + 1] = normalize(np.asarray(H, dtype=np.float64) @ out[k])
    return out


def resize_matrix(src_size: tuple[float, float], dst_size: tuple[float, float]) -> np.ndarray:
    """The matrix that maps pixel coordinates of an image of ``src_size`` (w, h) to the same
    point in that image resized to ``dst_size``, with pixel-centre convention:
    x_dst = (x_src + 0.5) * dst_w / src_w - 0.5 (as cv2.resize samples)."""
    sx = dst_size[0] / src_size[0]
    sy = dst_size[1] / src_size[1]
    return np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])


def to_resolution(H: np.ndarray, src_size: tuple[float, float], dst_size: tuple[float, float]) -> np.ndarray:
    """Re-express a frame-to-frame homography (..., 3, 3) given for images of ``src_size``
    as one for the same frames at ``dst_size``: H_dst = S @ H_src @ S^-1."""
    S = resize_matrix(src_size, dst_size)
    return normalize(S @ np.asarray(H, dtype=np.float64) @ np.linalg.inv(S))


def rect_corners(x: float, y: float, w: float, h: float) -> np.ndarray:
    """Corners of an axis-aligned rectangle, in the order TL, TR, BR, BL, as a (4, 2) array."""
    return np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]], dtype=np.float64)


def frame_corners(w: float, h: float) -> np.ndarray:
    """The outer corners of a w x h image (pixel-centre convention): TL, TR, BR, BL."""
    return rect_corners(-0.5, -0.5, w, h)


def weighted_dlt(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None, conditioned: bool = False) -> np.ndarray:
    """The direct linear transform: the homography (..., 3, 3), H[2, 2] = 1, mapping ``src``
    (..., N, 2) onto ``dst`` (..., N, 2), N >= 4, that minimises the algebraic error, each
    correspondence's squared error weighted by ``weights`` (..., N) (None: all 1); through 4
    points in general position, exact.  Batched over leading dimensions.

    Each point set is first conditioned as OpenCV's ``findHomography`` conditions it (moved to its
    weighted centroid, each axis scaled by its weighted mean absolute deviation from it) and the
    fit taken back; ``conditioned``: the points are already centred and of order one (the
    caller's own normalisation) and are fitted as they are.  The fit is the right singular
    vector of the weighted system's smallest singular value.  The torch twin, batched on a
    device, is :func:`mosaic_cli.geometry.tensor.weighted_dlt`."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    src, dst = np.broadcast_arrays(src, dst)
    weights = np.ones(src.shape[:-1]) if weights is None else np.broadcast_to(np.asarray(weights, dtype=np.float64), src.shape[:-1])
    if not conditioned:
        (cs, ss), (cd, sd) = _conditioning(src, weights), _conditioning(dst, weights)
        H = weighted_dlt((src - cs) * ss, (dst - cd) * sd, weights, conditioned=True)
        to_src = np.zeros(H.shape)  # conditioned src <- src
        to_src[..., 0, 0], to_src[..., 1, 1], to_src[..., 2, 2] = ss[..., 0, 0], ss[..., 0, 1], 1.0
        to_src[..., :2, 2] = -cs[..., 0, :] * ss[..., 0, :]
        from_dst = np.zeros(H.shape)  # dst <- conditioned dst
        from_dst[..., 0, 0], from_dst[..., 1, 1], from_dst[..., 2, 2] = 1.0 / sd[..., 0, 0], 1.0 / sd[..., 0, 1], 1.0
        from_dst[..., :2, 2] = cd[..., 0, :]
        return normalize(from_dst @ H @ to_src)
    n = src.shape[-2]
    batch = src.shape[:-2]
    x, y = src[..., 0], src[..., 1]
    u, v = dst[..., 0], dst[..., 1]
    ones = np.ones_like(x)
    A = np.zeros(batch + (2 * n, 9))
    A[..., 0::2, 0:3] = np.stack([x, y, ones], -1)
    A[..., 0::2, 6:9] = -np.stack([u * x, u * y, u], -1)
    A[..., 1::2, 3:6] = np.stack([x, y, ones], -1)
    A[..., 1::2, 6:9] = -np.stack([v * x, v * y, v], -1)
    A *= np.repeat(np.sqrt(weights), 2, axis=-1)[..., None]
    H = np.linalg.svd(A)[2][..., -1, :].reshape(batch + (3, 3))
    return H / H[..., 2:3, 2:3]


def _conditioning(points: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The weighted centroid (..., 1, 2) of ``points`` (..., N, 2) and the per-axis scale (..., 1, 2)
    that makes their weighted mean absolute deviation from it 1 (OpenCV's conditioning)."""
    w = weights[..., None]
    total = w.sum(-2, keepdims=True)
    centre = (points * w).sum(-2, keepdims=True) / total
    return centre, total / (np.abs(points - centre) * w).sum(-2, keepdims=True)


def four_point_to_homography(corners: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """The homography mapping ``corners`` (..., 4, 2) to ``corners + offsets``, batched over
    leading dimensions: the DLT (:func:`weighted_dlt`) through the 4 correspondences."""
    src = np.asarray(corners, dtype=np.float64)
    dst = src + np.asarray(offsets, dtype=np.float64)
    return weighted_dlt(src, dst)


def homography_to_four_point(H: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Offsets (..., 4, 2) of ``corners`` under ``H``: project(H, corners) - corners."""
    return project(H, corners) - np.asarray(corners, dtype=np.float64)


def corner_error(H_est: np.ndarray, H_true: np.ndarray, size: tuple[float, float]) -> np.ndarray:
    """Mean L2 distance (pixels) between the frame corners mapped by ``H_est`` and by ``H_true``.

    ``size`` is the (w, h) of the source frame; batched over leading dimensions.
    """
    c = frame_corners(*size)
    return np.linalg.norm(project(H_est, c) - project(H_true, c), axis=-1).mean(axis=-1)


def is_valid(
    H: np.ndarray,
    size: tuple[float, float],
    max_area_ratio: float = 4.0,
    max_corner_shift: float | None = None,
) -> bool:
    """A plausible frame-to-frame homography: finite, keeps the frame in front of the camera
    (positive projective depth at every corner), maps it to a convex, same-orientation
    quadrilateral, and changes its area by less than ``max_area_ratio``.  With
    ``max_corner_shift`` (pixels) the corners may not move further than that either."""
    H = np.asarray(H, dtype=np.float64)
    if H.shape != (3, 3) or not np.all(np.isfinite(H)) or abs(H[2, 2]) < 1e-12:
        return False
    H = H / H[2, 2]
    c = frame_corners(*size)
    w_den = c @ H[2, :2] + H[2, 2]
    if np.any(w_den <= 1e-6):
        return False
    q = project(H, c)
    if not np.all(np.isfinite(q)):
        return False
    cross = _turns(q)
    # Convex, and turning the same way as the source frame: a mirror image is no camera motion.
    if not np.all(np.sign(cross) == np.sign(_turns(c))):
        return False
    area_src = float(size[0] * size[1])
    after = _following(q)
    area_dst = 0.5 * abs(np.sum(q[:, 0] * after[:, 1] - after[:, 0] * q[:, 1]))
    if not (1.0 / max_area_ratio < area_dst / area_src < max_area_ratio):
        return False
    if max_corner_shift is not None and np.max(np.linalg.norm(q - c, axis=-1)) > max_corner_shift:
        return False
    return True


def _following(points: np.ndarray) -> np.ndarray:
    """Each vertex's successor around a closed polygon (np.roll(points, -1, axis=0), without its
    overhead: is_valid runs twice a frame pair in the learned estimator)."""
    return np.concatenate((points[1:], points[:1]))


def _turns(quad: np.ndarray) -> np.ndarray:
    """z of the cross product of consecutive edges of a closed polygon (4, 2)."""
    edges = _following(quad) - quad
    nxt = _following(edges)
    return edges[:, 0] * nxt[:, 1] - edges[:, 1] * nxt[:, 0]
