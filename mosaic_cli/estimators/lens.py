"""``--lens auto|none|FILE``: which lens a video is undistorted with, and ``auto``'s estimate.

``auto`` fits a radial lens to the video itself.  A homography maps one pinhole view of flat
ground onto another exactly; through a lens it cannot, and the misfit grows toward the corners
and with the motion between the two frames.  So: frames sampled across the video (decoded small,
once), sub-pixel matches between samples 1, 2, 4 and 8 apart (pairs that moved by 1-60% of the
width, at most :data:`MAX_PAIRS`), and the lens whose undistortion lets each pair's homography fit
its matches best (:func:`_residual`: the mean error, measured back in the distorted frame).  The
search: one coefficient of the division model (:func:`~mosaic_cli.geometry.lens.division_lens`,
radius r -> r / (1 + l1 r^2), r in half diagonals, centred; a bounded 1-D search), and where that
finds a lens, two coefficients of two families from there (Nelder-Mead): the division model's
(l1, l2), which follows a fisheye, and OpenCV's radial polynomial (k1, k2 at the half diagonal),
which is a wide-angle lens's own model, and for a barrel lens OpenCV's equidistant fisheye (its
focal length and k1); the best fit is kept.  Where a lens is found, a refinement
(:func:`_aligned_pairs`): each pair matched again between frame i and frame j resampled onto i's
pixels through that lens (patches that look alike out to the corners, where LK between the raw
frames was biased by the lens's stretch: a true fisheye's own residual read 0.42 px there, and the
division fit beside it 12 px off at the corners of 1280x720), and the three families fitted again
to those matches (corner errors of 0.05 px for k1 -0.30 and 0.24 px for a 120-degree fisheye at
1280x720; ``python -m benchmarks lens``).  The lens is applied only where
the residual improves on no lens by :data:`MIN_GAIN` or more and the lens moves the corners by more
than :data:`MIN_CORNER_PX`; otherwise the video is taken as a pinhole's (and the two-coefficient
search is not run).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.geometry.lens import (
    Lens,
    Undistortion,
    corner_displacement,
    distort_points,
    division_lens,
    fisheye_lens,
    radial_lens,
    undistort_points,
)
from mosaic_cli.geometry.lens_files import read_lens
from mosaic_cli.video import VideoInfo
from mosaic_cli.video.decode import frames_at
from mosaic_cli.video.lens_filter import ImageFilter

SAMPLES = 24  # frames decoded for `auto`
# px: the matches' resolution (a video narrower than this: its own).  At 640 a k1 -0.30 lens at
# 1280x720 came out 4.2 px off at the corners (px at 1280, the sample's noise scaled up 2x), at
# 1280 0.1 px, for about the same time (the fit's cost is the matches', not the pixels').
SAMPLE_WIDTH = 1280
GAPS = (1, 2, 4, 8)  # pairs of samples this far apart
MIN_GAIN = 0.15  # the median residual must fall by this fraction over lambda = 0 ...
MIN_CORNER_PX = 0.5  # ... and the lens move the corners this far (px of the sample width) to be applied
CAP = 0.015  # a match's error counts up to this fraction of the width
LAMBDA_RANGE = (-0.7, 0.3)  # the search: a strong fisheye (corners 3.3x further out) to a mild pincushion
LAMBDA2_RANGE = (-0.4, 0.4)  # the second coefficient's (the corners' bend)
K_RANGE, K2_RANGE = (-0.6, 0.6), (-0.4, 0.4)  # OpenCV's k1, k2 (unit: the half diagonal)
# OpenCV's equidistant fisheye: its focal length (unit: the half diagonal; 0.75: the corners 76
# degrees off the axis) and k1
FISHEYE_F_RANGE, FISHEYE_K_RANGE = (0.75, 4.0), (-0.3, 0.3)
REFINE_WINDOW = 15  # px: the refinement's LK window (its frames aligned: displacements of a pixel or two)
REFINE_STEP = 8  # px: the refinement's resampling grid
MAX_PAIRS, MAX_MATCHES = 40, 300  # the fit's sample
# A pair's median shift at least this share of the width.  A hovering, shaky camera moves a few
# pixels between samples; at 3% a shaky fisheye flight of 90 frames gave no pair at all (and was
# left distorted), at 1% 36 pairs and the lens (docs/guide/stabilize.md).
MIN_SHIFT = 0.01


@dataclass
class LensChoice:
    """What ``--lens`` resolved to: the lens the frames are undistorted with (None: as they
    are), how it was chosen, and for ``auto`` the evidence (residuals in px at
    :data:`SAMPLE_WIDTH`, pairs used, seconds)."""

    lens: Lens | None
    source: str  # "none", "file" or "auto"
    estimate: Lens | None = None  # auto: the fitted lens, applied or not
    residual_none: float = 0.0
    residual_fit: float = 0.0
    pairs: int = 0
    seconds: float = 0.0
    info: VideoInfo | None = None  # the video's probe where choosing needed one: the run reuses it

    def describe(self) -> str:
        """The final line's part: what was estimated and whether it was applied."""
        if self.source == "file":
            assert self.lens is not None
            return f"lens: {self.lens.model} from the file, frames undistorted"
        if self.source == "none":
            return "lens: none"
        if self.estimate is None:
            return f"lens: auto, too few matched pairs ({self.pairs}) to tell: taken as a pinhole"
        c = self.estimate.coefficients
        if self.estimate.model == "division":
            what = f"division lambda {c[0]:+.3f}" + (f", {c[1]:+.3f}" if len(c) > 1 else "")
        elif self.estimate.model == "fisheye":
            unit = 0.5 * float(np.hypot(*self.estimate.size))
            what = f"fisheye f {self.estimate.K[0, 0] / unit:.3f}, k1 {c[0]:+.3f} (unit: the half diagonal)"
        else:
            what = f"radial k1 {c[0]:+.3f}, k2 {c[1]:+.3f} (unit: the half diagonal)"
        px = corner_displacement(self.estimate)
        said = (f"lens: auto, {what} (corners moved {px:.0f} px), residual "
                f"{self.residual_none:.2f} -> {self.residual_fit:.2f} px over {self.pairs} pairs")
        return said + (", frames undistorted" if self.lens is not None else ": a pinhole, left alone")

    @property
    def image_filter(self) -> ImageFilter | None:
        """The filter the input's frames are decoded through: the lens's undistortion (each
        image (h, w) or (h, w, C) -> one of the same size), None where no lens is applied."""
        return None if self.lens is None else Undistortion(self.lens)

    def to_meta(self) -> dict:
        doc: dict = {"source": self.source, "applied": self.lens is not None}
        if self.lens is not None:
            doc["lens"] = self.lens.to_json()
        if self.source == "auto":
            doc.update(pairs=self.pairs, residual_none_px=self.residual_none, residual_fit_px=self.residual_fit, seconds=self.seconds)
            if self.estimate is not None:
                doc["estimate"] = self.estimate.to_json()
        return doc


def parse_lens_option(value: str | None) -> str | Path:
    """``--lens``: "auto", "none" or an existing FILE (read later, at the video's size)."""
    if value is None or value.strip().lower() in ("", "none"):
        return "none"
    if value.strip().lower() == "auto":
        return "auto"
    path = Path(value)
    if not path.is_file():
        raise BadInput(f"--lens must be auto, none or a lens file (mosaic, Gyroflow or OpenSfM JSON): no such file {value}")
    return path


def resolve_lens(value: str | None, video: str | Path, info: VideoInfo | None) -> LensChoice:
    """The lens ``--lens value`` asks for, for the video ``video`` (its probe ``info``).  A FILE is
    read and checked against the video's size; ``auto`` is estimated (:func:`estimate_lens`)."""
    spec = parse_lens_option(value)
    if spec == "none":
        return LensChoice(None, "none")
    if info is None:
        raise BadInput("--lens needs a video file or an image folder, not a live input")
    if spec == "auto":
        return estimate_lens(info)
    lens = read_lens(spec)
    try:
        lens.at(info.source_size)
    except ValueError as exc:
        raise BadInput(f"--lens {spec}: {exc}") from None
    return LensChoice(lens, "file")


def estimate_lens(info: VideoInfo, samples: int = SAMPLES) -> LensChoice:
    """``--lens auto`` (see the module doc)."""
    clock = time.perf_counter()
    total = info.frame_count or 0
    n = min(samples, total) if total else samples
    indices = sorted({int(round(v)) for v in np.linspace(0, max(total - 1, 0), n)}) if total else list(range(n))
    width = min(SAMPLE_WIDTH, info.source_size[0])
    frames = [cv2.cvtColor(np.asarray(f), cv2.COLOR_RGB2GRAY) for f in frames_at(info, indices, width)]
    if len(frames) < 2:
        return LensChoice(None, "auto", seconds=time.perf_counter() - clock)
    h, w = frames[0].shape
    found: list[tuple[int, int]] = []
    pairs = _matched_pairs(frames, w, found)
    if len(pairs) < 3:
        return LensChoice(None, "auto", pairs=len(pairs), seconds=time.perf_counter() - clock)
    estimate, none, fit = fit_lens(pairs, (w, h))
    applied = fit < (1.0 - MIN_GAIN) * none and corner_displacement(estimate) > MIN_CORNER_PX
    if applied:
        # the refinement: each pair matched again between frame i and frame j carried onto i's
        # pixels through the estimate (near-identical patches: no bias from the lens stretching
        # the one view against the other), and the lens fitted to those matches
        again = _aligned_pairs(frames, found, pairs, estimate)
        if len(again) >= 3:
            estimate, none, fit = fit_lens(again, (w, h))
            applied = fit < (1.0 - MIN_GAIN) * none and corner_displacement(estimate) > MIN_CORNER_PX
    return LensChoice(estimate if applied else None, "auto", estimate, none, fit, len(pairs), time.perf_counter() - clock)


def fit_lens(pairs: list[tuple[np.ndarray, np.ndarray]], size: tuple[int, int]) -> tuple[Lens, float, float]:
    """The lens fitted to matched pairs (a, b) of frames of ``size``: (the estimate, the
    residual with no lens, the residual with it) (px, :func:`_residual`)."""
    w, h = size
    pairs = _thinned(pairs)
    from scipy.optimize import minimize, minimize_scalar

    def cost1(lam: float) -> float:
        return _residual(division_lens((w, h), lam), pairs)

    def bounded(make, ranges):
        def cost(x: np.ndarray) -> float:
            if any(not lo <= v <= hi for v, (lo, hi) in zip(x, ranges)):
                return float("inf")
            return _residual(make(*(float(v) for v in x)), pairs)
        return cost

    def division2(l1: float, l2: float) -> Lens:
        return division_lens((w, h), l1, l2)

    def polynomial(k1: float, k2: float) -> Lens:
        return radial_lens((w, h), 0.5 * float(np.hypot(w, h)), k1, k2)

    def fisheye(f: float, k1: float) -> Lens:
        return fisheye_lens((w, h), f * 0.5 * float(np.hypot(w, h)), (k1,))

    # one division coefficient first (a bounded 1-D search); where that finds a lens, two
    # coefficients of each family from there (Nelder-Mead): the division model's (l1, l2) and
    # OpenCV's radial polynomial (k1, k2; k1 ~ l1 near the centre, halved until the polynomial
    # covers the frame), the better fit kept
    one = minimize_scalar(cost1, bounds=LAMBDA_RANGE, method="bounded", options={"xatol": 1e-4})
    none = cost1(0.0)
    fit, estimate = float(one.fun), division_lens((w, h), float(one.x))
    if fit < (1.0 - MIN_GAIN) * none:
        l1 = float(one.x)
        # the fisheye's focal length from l1: near the centre r_u ~ r_d (1 + (r_d / f)^2 / 3)
        f0 = float(np.clip(1.0 / np.sqrt(max(-3.0 * l1, 1e-6)), *FISHEYE_F_RANGE))
        families = [(division2, (LAMBDA_RANGE, LAMBDA2_RANGE), (l1, 0.0)), (polynomial, (K_RANGE, K2_RANGE), (l1, 0.0))]
        if l1 < 0:
            families.append((fisheye, (FISHEYE_F_RANGE, FISHEYE_K_RANGE), (f0, 0.0)))
        for make, ranges, start in families:
            cost = bounded(make, ranges)
            while make is not fisheye and not np.isfinite(cost(np.array(start))) and abs(start[0]) > 0.01:
                start = (0.5 * start[0], start[1])
            simplex = [start, (start[0] + 0.03, start[1]), (start[0], start[1] + 0.03)]
            res = minimize(cost, np.array(start), method="Nelder-Mead",
                           options={"initial_simplex": simplex, "xatol": 2e-4, "fatol": 1e-4, "maxfev": 60})
            if np.isfinite(res.fun) and res.fun < fit:
                fit, estimate = float(res.fun), make(float(res.x[0]), float(res.x[1]))
    return estimate, none, fit


def _thinned(pairs: list[tuple[np.ndarray, np.ndarray]]) -> list[tuple[np.ndarray, np.ndarray]]:
    """At most :data:`MAX_PAIRS` pairs (spread over the list) of at most :data:`MAX_MATCHES`
    matches each (every k-th): the fit's cost grows with both, its precision hardly."""
    if len(pairs) > MAX_PAIRS:
        pairs = [pairs[int(k)] for k in np.linspace(0, len(pairs) - 1, MAX_PAIRS).round()]
    out = []
    for a, b in pairs:
        step = max(1, int(np.ceil(len(a) / MAX_MATCHES)))
        out.append((a[::step], b[::step]))
    return out


def _matched_pairs(frames: list[np.ndarray], width: int, found: list[tuple[int, int]] | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """ORB matches (a (M, 2), b (M, 2)) between samples ``GAPS`` apart that moved 1-60% of the
    width, gross outliers dropped by a loose homography (a lens's misfit is well under its
    threshold, a wrong match is not).  The candidates are tried in an order spread over the
    video and the gaps, until :data:`MAX_PAIRS` pairs are found (matching is most of ``auto``'s
    time)."""
    orb = cv2.ORB_create(nfeatures=1500, fastThreshold=10)
    feats = [orb.detectAndCompute(f, None) for f in frames]
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    corners: dict[int, np.ndarray | None] = {}
    pairs: list[tuple[np.ndarray, np.ndarray]] = []
    candidates = [(i, gap) for gap in GAPS for i in range(len(frames) - gap)]
    # a bit-reversal order: every prefix spread over the whole list
    bits = max(1, int(np.ceil(np.log2(max(len(candidates), 2)))))
    order = sorted(range(len(candidates)), key=lambda k: int(format(k, f"0{bits}b")[::-1], 2))
    for i, gap in (candidates[k] for k in order):
        if len(pairs) >= MAX_PAIRS:
            break
        (ka, da), (kb, db) = feats[i], feats[i + gap]
        if da is None or db is None or len(ka) < 50 or len(kb) < 50:
            continue
        m = matcher.match(da, db)
        if len(m) < 50:
            continue
        a = np.array([ka[x.queryIdx].pt for x in m], dtype=np.float64)
        b = np.array([kb[x.trainIdx].pt for x in m], dtype=np.float64)
        H, inl = cv2.findHomography(a, b, cv2.RANSAC, 0.03 * width)
        if H is None or inl.sum() < 40:
            continue
        keep = inl.ravel().astype(bool)
        shift = float(np.median(np.linalg.norm(a[keep] - b[keep], axis=1)))
        if not MIN_SHIFT * width <= shift <= 0.6 * width:
            continue
        # ORB's keypoints sit on its pyramid's coarse grid: the lens's misfit (a fraction of
        # a pixel away from the corners) needs sub-pixel matches, which LK gives, started
        # from ORB's homography and checked forward and back.
        if i not in corners:
            corners[i] = cv2.goodFeaturesToTrack(frames[i], 1200, 0.005, 6)
        p0 = corners[i]
        if p0 is None:
            continue
        guess = cv2.perspectiveTransform(p0.astype(np.float32), H)
        lk = {"winSize": (21, 21), "maxLevel": 2, "criteria": (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 0.01)}
        p1, ok, _ = cv2.calcOpticalFlowPyrLK(frames[i], frames[i + gap], p0.astype(np.float32), guess.copy(),
                                             flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        back, ok2, _ = cv2.calcOpticalFlowPyrLK(frames[i + gap], frames[i], p1, p0.astype(np.float32).copy(),
                                                flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        good = (ok.ravel() == 1) & (ok2.ravel() == 1) & (np.linalg.norm((back - p0).reshape(-1, 2), axis=1) < 0.3)
        a2, b2 = p0.reshape(-1, 2)[good].astype(np.float64), p1.reshape(-1, 2)[good].astype(np.float64)
        if len(a2) < 40:
            continue
        # gross outliers out (a lens's misfit stays well under the threshold)
        H2, inl2 = cv2.findHomography(a2, b2, cv2.RANSAC, 0.02 * width)
        if H2 is None or inl2.sum() < 40:
            continue
        keep = inl2.ravel().astype(bool)
        pairs.append((a2[keep], b2[keep]))
        if found is not None:
            found.append((i, i + gap))
    return pairs


def _aligned_pairs(frames: list[np.ndarray], found: list[tuple[int, int]], pairs: list[tuple[np.ndarray, np.ndarray]],
                   lens: Lens) -> list[tuple[np.ndarray, np.ndarray]]:
    """The pairs (frames ``found`` (i, j)) matched again through ``lens``: frame j resampled onto
    frame i's pixels (each pixel undistorted, carried by the pair's homography between the
    undistorted views, distorted back into j), so that a patch of i and its match look alike
    wherever they sit in either frame; sub-pixel LK between i and that view (checked forward and
    back), each match carried back into j's pixels by the same chain.  The chain is only a
    resampling: the matches are exact for any lens; the closer the lens, the better the patches
    agree.  A pair whose homography the lens cannot give keeps no matches (dropped)."""
    h, w = frames[0].shape
    K = lens.K
    # the chain on a coarse grid (every REFINE_STEP px), bilinear in between: a smooth resampling
    # (the matches read the same interpolated map the view was drawn with)
    gx, gy = np.linspace(0, w - 1, int(np.ceil((w - 1) / REFINE_STEP)) + 1), np.linspace(0, h - 1, int(np.ceil((h - 1) / REFINE_STEP)) + 1)
    cx, cy = np.meshgrid(gx, gy)
    grid = undistort_points(lens, np.stack([cx.ravel(), cy.ravel()], 1), K)
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pixels = np.stack([xs.ravel(), ys.ravel()], 1)
    lk = {"winSize": (REFINE_WINDOW, REFINE_WINDOW), "maxLevel": 1, "criteria": (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.003)}
    corners: dict[int, np.ndarray | None] = {}
    out = []
    for (i, j), (a, b) in zip(found, pairs):
        ua, ub = undistort_points(lens, a, K), undistort_points(lens, b, K)
        H, _ = cv2.findHomography(ua, ub, cv2.RANSAC, 1.0)
        if H is None:
            continue
        with np.errstate(invalid="ignore", divide="ignore"):
            q = np.concatenate([grid, np.ones((len(grid), 1))], 1) @ H.T
            coarse = distort_points(lens, q[:, :2] / q[:, 2:3], K)
        coarse = np.where(np.isfinite(coarse), coarse, -1e5).reshape(len(gy), len(gx), 2)
        src = _bilinear(coarse, pixels, (w, h)).astype(np.float32)
        mx, my = src[:, 0].reshape(h, w), src[:, 1].reshape(h, w)
        view = cv2.remap(frames[j], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        seen = ((mx >= 1) & (mx <= w - 2) & (my >= 1) & (my <= h - 2)).astype(np.uint8) * 255
        seen = cv2.erode(seen, np.ones((REFINE_WINDOW, REFINE_WINDOW), np.uint8))
        if i not in corners:
            corners[i] = cv2.goodFeaturesToTrack(frames[i], 2000, 0.005, 6)
        p0 = corners[i]
        if p0 is None:
            continue
        p0 = p0.reshape(-1, 2)
        p0 = p0[seen[p0[:, 1].astype(int), p0[:, 0].astype(int)] > 0].reshape(-1, 1, 2).astype(np.float32)
        if len(p0) < 40:
            continue
        p1, ok, _ = cv2.calcOpticalFlowPyrLK(frames[i], view, p0, p0.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        back, ok2, _ = cv2.calcOpticalFlowPyrLK(view, frames[i], p1, p0.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        good = (ok.ravel() == 1) & (ok2.ravel() == 1) & (np.linalg.norm((back - p0).reshape(-1, 2), axis=1) < 0.1)
        a2, p1 = p0.reshape(-1, 2)[good].astype(np.float64), p1.reshape(-1, 2)[good].astype(np.float64)
        b2 = _bilinear(coarse, p1, (w, h))
        inside = np.all(np.isfinite(b2), 1) & np.all((b2 >= 0) & (b2 <= np.array([w - 1, h - 1])), 1)
        if inside.sum() >= 40:
            out.append((a2[inside], b2[inside]))
    return out


def _bilinear(coarse: np.ndarray, points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Values (N, C) at pixel ``points`` (N, 2) of ``coarse`` (gh, gw, C), a grid spread evenly
    over a frame of ``size`` (its first and last rows and columns on the frame's edges)."""
    w, h = size
    gh, gw = coarse.shape[:2]
    x = np.clip(points[:, 0] * (gw - 1) / (w - 1), 0, gw - 1.000001)
    y = np.clip(points[:, 1] * (gh - 1) / (h - 1), 0, gh - 1.000001)
    x0, y0 = x.astype(int), y.astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((coarse[y0, x0] * (1 - fx) + coarse[y0, x0 + 1] * fx) * (1 - fy)
            + (coarse[y0 + 1, x0] * (1 - fx) + coarse[y0 + 1, x0 + 1] * fx) * fy)


def _residual(lens: Lens, pairs: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """Mean over the pairs of the mean reprojection error (px of the sample, each error capped at
    :data:`CAP` of the width) of each pair's homography fitted to its undistorted matches, the
    error measured where the lens puts the prediction back in the distorted frame.  Measured in
    the distorted frame, not the undistorted one: undistorting stretches a barrel lens's corners,
    which would weigh their matches' noise up and pull the fit toward a weaker lens.  The fit is
    deterministic (least squares, refitted once without the matches beyond three times the
    median error), so that the search over the coefficients sees a smooth cost.  A mean, not a
    median: the lens's misfit lives in the frame's outer parts, which a median overlooks."""
    errors = []
    K = lens.K
    cap = CAP * lens.size[0]
    if lens.model == "pinhole" and not _covers(lens):
        return float("inf")
    for a, b in pairs:
        ua, ub = undistort_points(lens, a, K), undistort_points(lens, b, K)
        if not (np.all(np.isfinite(ua)) and np.all(np.isfinite(ub))):
            return float("inf")
        keep = np.ones(len(a), dtype=bool)
        err = None
        for _ in range(2):
            H, _ = cv2.findHomography(ua[keep], ub[keep], 0)
            if H is None:
                break
            proj = np.concatenate([ua, np.ones((len(ua), 1))], 1) @ H.T
            with np.errstate(invalid="ignore", divide="ignore"):
                back = distort_points(lens, proj[:, :2] / proj[:, 2:3], K)
            err = np.linalg.norm(back - b, axis=1)
            err = np.where(np.isfinite(err), err, cap)
            keep = err < max(3.0 * float(np.median(err)), 1e-3)
            if keep.sum() < 8:
                break
        if err is not None:
            errors.append(float(np.mean(np.minimum(err, cap))))
    return float(np.mean(errors)) if errors else float("inf")


def _covers(lens: Lens) -> bool:
    from mosaic_cli.geometry.lens import check_lens_covers

    try:
        check_lens_covers(lens)
    except ValueError:
        return False
    return True


def choose_lens(value: str | None, video: str | Path, info: VideoInfo | None = None, live: bool = False) -> LensChoice:
    """``--lens value`` resolved for ``video`` (probed here if ``info`` is None and a lens is
    asked for); its :attr:`~LensChoice.image_filter` is handed to every reader of ``video``, so
    that the estimator, the stitcher and the renderer all see the pinhole view, undistorted once
    where the frames are decoded.  ``live``: ``video`` is a live source (a stream, standard
    input), read once and never probed: a lens FILE undistorts each frame as it arrives (its size
    checked against the stream's once it is known: LiveStream), ``auto`` is refused (it reads
    samples spread over a whole file)."""
    if live:
        spec = parse_lens_option(value)
        if spec == "auto":
            raise BadInput("--lens auto reads frames spread over a whole video file: with a live input, pass a lens FILE (or none)")
        return LensChoice(None, "none") if spec == "none" else LensChoice(read_lens(spec), "file")
    if parse_lens_option(value) != "none" and info is None:
        from mosaic_cli.video import probe

        info = probe(video)
    return dataclasses.replace(resolve_lens(value, video, info), info=info)
