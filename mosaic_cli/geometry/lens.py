"""Camera lenses: OpenCV's two camera models and what mosaic does with them.

* ``pinhole``: the pinhole with radial and tangential distortion, OpenCV's coefficients
  (k1, k2, p1, p2[, k3[, k4, k5, k6]]) (4, 5 or 8 of them).
* ``fisheye``: OpenCV's equidistant fisheye (``cv2.fisheye``), coefficients k1..k4.
* ``division``: the division model that ``--lens auto`` estimates, with one or two
  coefficients: a pixel at normalised radius r (the camera matrix's focal length as the unit) is
  undistorted to radius r / (1 + l1 r^2 + l2 r^4) (Fitzgibbon 2001; one coefficient: in closed
  form both ways, barrel lenses up to fisheyes never fold back inside the frame; two: the second
  term bends the corners, which one term cannot do for a strong polynomial lens or a fisheye,
  and the way back is a dense table of the radius, polished by Newton's method).

A :class:`Lens` holds its camera matrix at a stated calibration size; :meth:`Lens.at` scales it
to a video's size (OpenCV pixel centres, as :func:`mosaic_cli.geometry.resize_matrix`).

Undistorting maps a frame to a pinhole view of the same size through a *new* camera matrix
(:func:`undistorted_camera`), chosen so that every output pixel sees the source frame (no black
corners ever enter the estimator, the stitcher or the renderer): OpenCV's
``getOptimalNewCameraMatrix`` with alpha = 0, and for a fisheye
``cv2.fisheye.estimateNewCameraMatrixForUndistortRectify`` with balance = 0.  A barrel lens
(k1 < 0) keeps its field of view along the frame's axes; what the crop loses is the stretched
corners.  Keeping every source pixel (alpha = 1) would leave curved black borders that a
panorama would have to mask.

Pure functions: no I/O (the file readers are :mod:`mosaic_cli.geometry.lens_files`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from mosaic_cli.geometry.homography import resize_matrix

MODELS = ("pinhole", "fisheye", "division")
# The iterative undistortion's stopping rule: OpenCV's default (5 iterations) leaves pixels of
# error at the corners of a strong lens; this one is exact to well under 1e-3 px.
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass(frozen=True)
class Lens:
    """A camera: ``model`` (pinhole or fisheye), the calibration ``size`` (w, h), the camera
    matrix (3x3, as a tuple of rows, pixels at ``size``) and the distortion ``coefficients``
    (OpenCV's order).  Frozen and hashable: the maps are cached per lens and size."""

    model: str
    size: tuple[int, int]
    camera_matrix: tuple[tuple[float, ...], ...]
    coefficients: tuple[float, ...]

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"lens model {self.model!r}: pinhole or fisheye")
        if self.model == "division" and len(self.coefficients) not in (1, 2):
            raise ValueError("a division-model lens has one or two coefficients (l1[, l2])")
        K = np.asarray(self.camera_matrix, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError("camera matrix: 3x3, finite, with positive focal lengths")
        n = len(self.coefficients)
        if self.model == "fisheye" and n != 4:
            raise ValueError(f"a fisheye lens has 4 coefficients (k1..k4), not {n}")
        if self.model == "pinhole" and n not in (4, 5, 8):
            raise ValueError(f"a pinhole lens has 4, 5 or 8 coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]), not {n}")
        if not all(np.isfinite(self.coefficients)):
            raise ValueError("lens coefficients must be finite")
        if len(self.size) != 2 or min(self.size) < 1:
            raise ValueError("lens size: (w, h), positive")

    @staticmethod
    def make(model: str, size: tuple[int, int] | list, K: np.ndarray | list, coefficients: np.ndarray | list | tuple) -> Lens:
        """A lens from arrays (any sequence types)."""
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"camera matrix: 3x3, not {'x'.join(map(str, K.shape))}")
        return Lens(str(model), (int(size[0]), int(size[1])), tuple(tuple(float(v) for v in row) for row in K),
                    tuple(float(c) for c in np.asarray(coefficients, dtype=np.float64).ravel()))

    @property
    def K(self) -> np.ndarray:
        return np.array(self.camera_matrix, dtype=np.float64)

    @property
    def D(self) -> np.ndarray:
        return np.array(self.coefficients, dtype=np.float64)

    def at(self, size: tuple[int, int]) -> Lens:
        """The same lens for frames of ``size`` (w, h): the camera matrix rescaled.  A frame of
        another aspect is a crop, not a scaling, of the calibrated one: ValueError."""
        size = (int(size[0]), int(size[1]))
        if size == self.size:
            return self
        if abs(size[0] * self.size[1] - size[1] * self.size[0]) > 0.01 * size[0] * self.size[1]:
            raise ValueError(f"the lens was calibrated at {self.size[0]}x{self.size[1]}, another aspect than {size[0]}x{size[1]}")
        return Lens.make(self.model, size, resize_matrix(self.size, size) @ self.K, self.coefficients)

    def is_identity(self) -> bool:
        """No distortion at all: undistorting would only resample."""
        return not any(self.coefficients)

    def to_json(self) -> dict:
        """mosaic's lens file (docs/guide/stitch.md, "Lenses")."""
        return {"model": self.model, "size": list(self.size), "camera_matrix": [list(r) for r in self.camera_matrix],
                "coefficients": list(self.coefficients)}


def radial_lens(size: tuple[int, int], focal: float, k1: float, k2: float = 0.0) -> Lens:
    """A pinhole lens with radial coefficients only, its principal point at the frame's centre."""
    w, h = size
    return Lens.make("pinhole", size, [[focal, 0, (w - 1) / 2], [0, focal, (h - 1) / 2], [0, 0, 1]], [k1, k2, 0.0, 0.0, 0.0])


def fisheye_lens(size: tuple[int, int], focal: float, k: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)) -> Lens:
    """An equidistant fisheye lens, its principal point at the frame's centre."""
    w, h = size
    k = tuple(k) + (0.0,) * (4 - len(k))
    return Lens.make("fisheye", size, [[focal, 0, (w - 1) / 2], [0, focal, (h - 1) / 2], [0, 0, 1]], k[:4])


def check_lens_covers(lens: Lens) -> None:
    """ValueError when the lens folds back inside its frame (its distortion stops growing with
    the radius before the corners: a radial polynomial pushed past its range), where no
    undistortion is defined."""
    w, h = lens.size
    edge = np.concatenate([np.stack([np.linspace(0, w - 1, 33), np.full(33, y)], 1) for y in (0, h - 1)]
                          + [np.stack([np.full(19, x), np.linspace(0, h - 1, 19)], 1) for x in (0, w - 1)])
    back = distort_points(lens, undistort_points(lens, edge, lens.K), lens.K)
    if not np.all(np.isfinite(back)) or np.max(np.abs(back - edge)) > 0.01:
        raise ValueError("the lens's distortion folds back before the frame's edge (no pinhole view of its corners): "
                         "a smaller coefficient or a longer focal length")


def undistorted_camera(lens: Lens) -> np.ndarray:
    """The new camera matrix (3x3) of the undistorted frame at ``lens.size``: every output pixel
    sees the source (see the module doc)."""
    return _new_camera(lens).copy()


@functools.lru_cache(maxsize=32)
def _new_camera(lens: Lens) -> np.ndarray:
    if lens.model == "division":
        return _division_crop(lens)
    if lens.model == "fisheye":
        P = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(lens.K, lens.D, lens.size, np.eye(3), balance=0.0)
    else:
        # OpenCV's alpha = 0 fits x and y each with its own focal length (the undistorted view
        # would be stretched); the larger of its two zooms, applied to both, keeps square pixels
        # and still leaves no pixel off the source.
        crop, _ = cv2.getOptimalNewCameraMatrix(lens.K, lens.D, lens.size, 0.0, lens.size)
        K = lens.K
        zoom = max(crop[0, 0] / K[0, 0], crop[1, 1] / K[1, 1])
        P = K.copy()
        P[0, 0], P[1, 1], P[0, 1] = K[0, 0] * zoom, K[1, 1] * zoom, K[0, 1] * zoom
    return np.asarray(P, dtype=np.float64)


def undistort_points(lens: Lens, points: np.ndarray, P: np.ndarray | None = None) -> np.ndarray:
    """Distorted pixels (N, 2) -> their pinhole pixels (N, 2) under the camera ``P`` (default
    :func:`undistorted_camera`; ``lens.K``: the same scale at the centre)."""
    # (contiguous: cv2.fisheye.undistortPoints reads a strided view, e.g. every k-th match, as garbage)
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 1, 2))
    if len(pts) == 0:
        return np.zeros((0, 2))
    P = undistorted_camera(lens) if P is None else np.asarray(P, dtype=np.float64)
    if lens.model == "division":
        return _division_undistort(lens, pts.reshape(-1, 2), P)
    if lens.model == "fisheye":
        out = cv2.fisheye.undistortPoints(pts, lens.K, lens.D, R=np.eye(3), P=P, criteria=_CRITERIA)
    else:
        out = cv2.undistortPoints(pts, lens.K, lens.D, R=None, P=P, criteria=_CRITERIA)
    return out.reshape(-1, 2)


def distort_points(lens: Lens, points: np.ndarray, P: np.ndarray | None = None) -> np.ndarray:
    """Pinhole pixels (N, 2) under the camera ``P`` (default :func:`undistorted_camera`) -> where
    the lens images them (N, 2)."""
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 2))
    if len(pts) == 0:
        return np.zeros((0, 2))
    P = undistorted_camera(lens) if P is None else np.asarray(P, dtype=np.float64)
    homog = np.concatenate([pts, np.ones((len(pts), 1))], 1) @ np.linalg.inv(P).T
    normal = homog[:, :2] / homog[:, 2:3]
    if lens.model == "division":
        return _division_distort(lens, normal)
    if lens.model == "fisheye":
        out = cv2.fisheye.distortPoints(normal.reshape(-1, 1, 2), lens.K, lens.D)
    else:
        rays = np.concatenate([normal, np.ones((len(normal), 1))], 1).reshape(-1, 1, 3)
        out, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), lens.K, lens.D)
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


def undistort_maps(lens: Lens, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap``'s (map_x, map_y) (h, w) float32 that undistort a frame of ``size``: for each
    pixel of the undistorted frame (camera ``undistorted_camera(lens.at(size))``), the distorted
    pixel it shows.  Cached per lens and size: read-only arrays."""
    return _maps(lens, (int(size[0]), int(size[1])))


@functools.lru_cache(maxsize=16)
def _maps(lens: Lens, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    at = lens.at(size)
    P = _new_camera(at)
    if at.model == "division":
        w, h = size
        xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        src = distort_points(at, np.stack([xs.ravel(), ys.ravel()], 1), P)
        mx, my = (np.ascontiguousarray(src[:, k].reshape(h, w), dtype=np.float32) for k in (0, 1))
    elif at.model == "fisheye":
        mx, my = cv2.fisheye.initUndistortRectifyMap(at.K, at.D, np.eye(3), P, size, cv2.CV_32FC1)
    else:
        mx, my = cv2.initUndistortRectifyMap(at.K, at.D, None, P, size, cv2.CV_32FC1)
    mx.setflags(write=False)
    my.setflags(write=False)
    return mx, my


def distorted_grid(lens: Lens, P: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """For each pixel of a distorted frame at ``lens.size``, the pinhole pixel it shows under
    the camera ``P`` (default ``lens.K``): (x, y), each (h, w) float64.  What the simulator
    renders a lens with (the inverse of :func:`undistort_maps`)."""
    w, h = lens.size
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    u = undistort_points(lens, np.stack([xs.ravel(), ys.ravel()], 1), lens.K if P is None else P)
    return u[:, 0].reshape(h, w), u[:, 1].reshape(h, w)


def corner_displacement(lens: Lens) -> float:
    """How far the lens moves the frame's corners, pixels at ``lens.size``: the largest distance,
    over the four corners, between a corner and its pinhole pixel at the same scale at the
    centre (camera ``lens.K``).  How estimated coefficients are scored against the truth."""
    w, h = lens.size
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], dtype=np.float64)
    return float(np.max(np.linalg.norm(undistort_points(lens, corners, lens.K) - corners, axis=1)))


def corner_error(estimate: Lens, truth: Lens) -> float:
    """The largest distance, over the four corners, between where ``estimate`` and ``truth``
    put a corner's pinhole pixel (camera of each lens's own K, at ``truth.size``), pixels."""
    w, h = truth.size
    est = estimate.at(truth.size)
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], dtype=np.float64)
    a = undistort_points(est, corners, est.K)
    b = undistort_points(truth, corners, truth.K)
    return float(np.max(np.linalg.norm(a - b, axis=1)))


def remap_frame(frame: np.ndarray, lens: Lens) -> np.ndarray:
    """A frame (h, w) or (h, w, C) undistorted at its own size (one ``cv2.remap``, bilinear; the
    rare output pixel just off the source repeats its edge)."""
    h, w = frame.shape[:2]
    mx, my = undistort_maps(lens, (w, h))
    return cv2.remap(frame, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


# ``stabilize --keep-lens``: the render's warps composed with the lens.  Where the undistorted
# output of the table's footprint has no image (past a polynomial's range, a division model's
# NaN), the table reads this: far off any frame, so that the sample is the border's.
OFF_FRAME = -1.0e5
TABLE_POINTS = 500_000  # the distortion table's entries at most (its step grows past that: ~0.5 s to build)


def distortion_table(lens: Lens, size: tuple[int, int]) -> tuple[np.ndarray, tuple[float, float], float]:
    """:func:`distort_points` of ``lens.at(size)`` (camera :func:`undistorted_camera`, as the
    frames were undistorted) tabulated over the undistorted coordinates of the frame's whole
    footprint, distorted corners included (which the undistorted frame crops), as the
    displacement it adds: (table (Hb, Wb, 2) float32, origin (x0, y0), step), entry (i, j) the
    distorted pixel less the undistorted point (x0 + j step, y0 + i step).  A point past the
    footprint's largest radius (a polynomial lens folds back there) or with no image reads
    :data:`OFF_FRAME`.  Read it with :func:`distort_by_table`: a bilinear look-up in place of the
    lens's own (iterative, for a division model) distortion.  Cached per lens and size:
    read-only."""
    return _table(lens, (int(size[0]), int(size[1])))


@functools.lru_cache(maxsize=4)
def _table(lens: Lens, size: tuple[int, int]) -> tuple[np.ndarray, tuple[float, float], float]:
    at = lens.at(size)
    P = _new_camera(at)
    w, h = size
    # the footprint: the distorted frame's outer pixel edges and a grid inside, undistorted (a
    # polynomial lens pushed past its turn puts the corners' undistorted points inside others)
    xs, ys = np.linspace(-0.5, w - 0.5, 257), np.linspace(-0.5, h - 0.5, 145)
    edge = np.concatenate([np.stack([xs, np.full_like(xs, y)], 1) for y in (-0.5, h - 0.5)]
                          + [np.stack([np.full_like(ys, x), ys], 1) for x in (-0.5, w - 0.5)]
                          + [np.stack([g.ravel() for g in np.meshgrid(xs[::8], ys[::8])], 1)])
    outline = undistort_points(at, edge, P)
    outline = outline[np.all(np.isfinite(outline), axis=1)]
    lo, hi = outline.min(0), outline.max(0)
    # (no further than a few frames out: a fisheye near 180 degrees runs off to infinity)
    centre = P[:2, 2]
    reach = 4.0 * np.array([w, h], dtype=np.float64)
    lo, hi = np.maximum(lo, centre - reach), np.minimum(hi, centre + reach)
    area = float(np.prod(hi - lo + 1.0))
    step = max(1.0, float(np.ceil(np.sqrt(area / TABLE_POINTS))))
    lo, hi = np.floor(lo) - 2 * step, np.ceil(hi) + 2 * step
    gx = np.arange(lo[0], hi[0] + step, step)
    gy = np.arange(lo[1], hi[1] + step, step)
    X, Y = np.meshgrid(gx, gy)
    pts = np.stack([X.ravel(), Y.ravel()], 1)
    with np.errstate(invalid="ignore"):
        out = distort_points(at, pts, P) - pts

    def radius(p: np.ndarray) -> np.ndarray:
        return np.hypot((p[:, 0] - P[0, 2]) / P[0, 0], (p[:, 1] - P[1, 2]) / P[1, 1])

    # past the outline's largest normalised radius (a small margin kept): no image
    far = radius(pts) > 1.01 * float(radius(outline).max()) + 2.0 * step / min(P[0, 0], P[1, 1])
    out[far | ~np.all(np.isfinite(out), axis=1)] = OFF_FRAME
    table = np.ascontiguousarray(out.reshape(len(gy), len(gx), 2), dtype=np.float32)
    table.setflags(write=False)
    return table, (float(lo[0]), float(lo[1])), step


def distort_by_table(table: np.ndarray, origin: tuple[float, float], step: float,
                     x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distorted pixels (x', y') (same shape, float32) of undistorted points (x, y), their
    displacement read off :func:`distortion_table`'s ``table`` (``cv2.remap``, bilinear; off the
    table: :data:`OFF_FRAME`).  OpenCV rounds the look-up's position to 1/32 of the step: an error
    of the displacement's slope times 1/64 of the step at most, 0.024 px for a k1 -0.30 lens and
    0.047 px for a 120-degree fisheye at 1280x720 (steps of 2 and 3 px; 8 ms a 1280x720 frame's
    maps where a float64 look-up took 33), about what the frame's own remap rounds to (1/32 px)."""
    x = np.asarray(x, dtype=np.float32)
    y = np.asarray(y, dtype=np.float32)
    rows = x.reshape(x.shape if x.ndim == 2 else (1, -1))  # (cv2.remap takes 2-D maps)
    mx = (rows - np.float32(origin[0])) / np.float32(step)
    my = (y.reshape(rows.shape) - np.float32(origin[1])) / np.float32(step)
    shift = cv2.remap(table, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=(OFF_FRAME, OFF_FRAME))
    return x + shift[..., 0].reshape(x.shape), y + shift[..., 1].reshape(x.shape)


def undistort_mask(use: np.ndarray, lens: Lens) -> np.ndarray:
    """A use mask (h, w) uint8 (255 = use) drawn in the distorted frame's pixels, in the
    undistorted frame's (the maps :func:`remap_frame` undistorts its frames with), still 0/255:
    a pixel is usable only where every distorted pixel its bilinear sample reads is, so that no
    masked pixel's edge slips out by a rounding (nearest would move an edge by up to half a
    pixel either way)."""
    h, w = use.shape[:2]
    mx, my = undistort_maps(lens, (w, h))
    touched = cv2.remap(use, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.where(touched >= 255, 255, 0).astype(np.uint8)


@dataclass(frozen=True)
class Undistortion:
    """What ``--lens`` sets on an input's frames (``estimators.lens.LensChoice.image_filter``,
    handed to each reader of the input as its ``lens``): each image
    undistorted by ``lens`` (:func:`remap_frame`), and a ``--mask`` drawn in the distorted frame's
    pixels carried into the undistorted frame's (:meth:`mask`)."""

    lens: Lens

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        return remap_frame(frame, self.lens)

    def mask(self, use: np.ndarray) -> np.ndarray:
        return undistort_mask(use, self.lens)


def frame_to_undistorted(lens: Lens, size: tuple[int, int]) -> np.ndarray:
    """The matrix (3x3) from the pinhole frame of camera ``lens.at(size).K`` to the undistorted
    frame's pixels (camera ``undistorted_camera``): how a homography between pinhole frames at
    the lens's own K (a simulator's truth) reads in the undistorted frames."""
    at = lens.at(size)
    return _new_camera(at) @ np.linalg.inv(at.K)


def division_lens(size: tuple[int, int], lam: float, lam2: float | None = None) -> Lens:
    """A division-model lens centred on the frame, its unit radius the half diagonal (so that the
    coefficients read the same at any frame size: r / (1 + lam + lam2) at the corners); ``lam2``
    None: the one-coefficient model."""
    w, h = size
    unit = 0.5 * float(np.hypot(w, h))
    coefficients = [lam] if lam2 is None else [lam, lam2]
    return Lens.make("division", size, [[unit, 0, (w - 1) / 2], [0, unit, (h - 1) / 2], [0, 0, 1]], coefficients)


def division_denominator(coefficients: tuple[float, ...] | list[float], r2: np.ndarray) -> np.ndarray:
    """1 + l1 r^2 (+ l2 r^4) at the squared normalised radii ``r2``."""
    out = 1.0 + coefficients[0] * r2
    if len(coefficients) > 1:
        out = out + coefficients[1] * r2 * r2
    return out


def _division_undistort(lens: Lens, pts: np.ndarray, P: np.ndarray) -> np.ndarray:
    K = lens.K
    n = (pts - K[:2, 2]) / np.diag(K)[:2]
    r2 = np.sum(n * n, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = n / division_denominator(lens.coefficients, r2)
    return u * np.diag(P)[:2] + P[:2, 2]


def _division_distort(lens: Lens, normal: np.ndarray) -> np.ndarray:
    """Normalised pinhole points (N, 2) -> distorted pixels.  One coefficient: r_d solves
    lam r_u r_d^2 - r_d + r_u = 0, the root that tends to r_u as lam -> 0; two: the radius read
    off a dense table of r_u(r_d) over its increasing range and polished by two Newton steps.
    NaN where there is none (past the range where the lens's radius grows)."""
    ru = np.linalg.norm(normal, axis=1, keepdims=True)
    K = lens.K
    if len(lens.coefficients) == 1:
        lam = lens.coefficients[0]
        with np.errstate(invalid="ignore", divide="ignore"):
            disc = np.sqrt(1.0 - 4.0 * lam * ru * ru)
            # 2 r_u / (1 + sqrt(.)): the stable form of (1 - sqrt(.)) / (2 lam r_u)
            ratio = np.where(ru > 0, 2.0 / (1.0 + disc), 1.0)
        return normal * ratio * np.diag(K)[:2] + K[:2, 2]
    grid_d, grid_u = _division_table(lens.coefficients)
    rd = np.interp(ru.ravel(), grid_u, grid_d, right=np.nan)
    l1, l2 = lens.coefficients
    with np.errstate(invalid="ignore", divide="ignore"):
        for _ in range(2):
            d2 = rd * rd
            den = 1.0 + l1 * d2 + l2 * d2 * d2
            f = rd / den - ru.ravel()
            df = (1.0 - l1 * d2 - 3.0 * l2 * d2 * d2) / (den * den)
            rd = rd - f / df
        ratio = np.where(ru.ravel() > 0, rd / np.where(ru.ravel() > 0, ru.ravel(), 1.0), 1.0)[:, None]
    return normal * ratio * np.diag(K)[:2] + K[:2, 2]


@functools.lru_cache(maxsize=64)
def _division_table(coefficients: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(r_d, r_u) sampled densely from the centre out over the range where r_u grows with r_d
    and the denominator stays positive (at most 4 units: past any frame's corners)."""
    rd = np.linspace(0.0, 4.0, 16001)
    den = division_denominator(coefficients, rd * rd)
    with np.errstate(invalid="ignore", divide="ignore"):
        ru = rd / den
    ok = (den > 0) & np.isfinite(ru)
    ok[1:] &= np.diff(ru) > 0
    end = int(np.argmin(ok)) if not ok.all() else len(rd)
    return rd[:max(end, 2)], ru[:max(end, 2)]


def _division_crop(lens: Lens) -> np.ndarray:
    """The undistorted camera of a division lens: its own K zoomed (square pixels, same centre)
    as little as keeps every output pixel on the source, found by bisection on the zoom (what
    alpha = 0 does for OpenCV's models)."""
    w, h = lens.size
    edge = np.concatenate([np.stack([np.linspace(0, w - 1, 65), np.full(65, y)], 1) for y in (0, h - 1)]
                          + [np.stack([np.full(37, x), np.linspace(0, h - 1, 37)], 1) for x in (0, w - 1)])
    K = lens.K

    def fits(zoom: float) -> bool:
        P = K.copy()
        P[0, 0], P[1, 1] = K[0, 0] * zoom, K[1, 1] * zoom
        homog = np.concatenate([edge, np.ones((len(edge), 1))], 1) @ np.linalg.inv(P).T
        src = _division_distort(lens, homog[:, :2])
        return bool(np.all(np.isfinite(src)) and np.all(src >= -0.5) and np.all(src[:, 0] <= w - 0.5) and np.all(src[:, 1] <= h - 0.5))

    lo, hi = 0.05, 20.0  # zoomed out too far: off the source; zoomed in this far: always on it
    for _ in range(60):
        mid = np.sqrt(lo * hi)
        lo, hi = (lo, mid) if fits(mid) else (mid, hi)
    P = K.copy()
    P[0, 0], P[1, 1] = K[0, 0] * hi, K[1, 1] * hi
    return P
