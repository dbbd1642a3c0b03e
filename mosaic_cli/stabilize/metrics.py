"""How good is a stabilisation?  Scores from exact warps, from ground truth, or from videos.

* Cropping ratio and distortion (Liu et al., "Bundled camera paths", SIGGRAPH 2013): for each
  frame, the warp input -> output; cropping is 1 / its scale (the share of the input's width
  still shown), averaged over frames; distortion the ratio of the smaller to the larger
  singular value of its linear part (1 = no anisotropic stretch), the worst frame.  The linear
  part is the warp's Jacobian at the frame centre, which also covers homographies.
* Residual jitter: the high-frequency part of the path of the frame corners, root mean
  square in pixels.  The path's slow part (the flight itself) is a Gaussian-weighted local
  quadratic fit (sigma ``HIGHPASS_SECONDS``): exact for steady acceleration, so a drone that
  speeds up or turns is not counted as shaking (a plain Gaussian mean would count 0.3 px of
  it on the simulated flights); its gain is 0.94 at 0.5 Hz, 0.5 at 1 Hz and below 0.015 from
  2 Hz up.  What is left is the shake a viewer sees.
  ``ground_truth_jitter`` measures it against a simulated flight's known jitter-free path,
  ``pairwise_jitter`` from the frame-to-frame homographies of any video (no ground truth).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mosaic_cli.geometry import frame_corners, normalize, project
from mosaic_cli.stabilize.path import gaussian_weights, neighbour_mean
from mosaic_cli.video.lens_filter import ImageFilter

HIGHPASS_SECONDS = 0.3  # sigma of the low-pass removed: half gain at 1 Hz, below the 3-8 Hz of shake


def warp_jacobian(warps: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(N, 2, 2): the derivative of each warp (N, 3, 3) at the centre of a frame of ``size``."""
    W = normalize(warps)
    centre = np.array([(size[0] - 1) / 2.0, (size[1] - 1) / 2.0])
    mapped = project(W, centre[None])[..., 0, :]  # (N, 2)
    denom = W[..., 2, :2] @ centre + W[..., 2, 2]  # (N,)
    # d/dx (A x + t) / (p.x + 1) = (A - y p^T) / (p.x + 1), y the mapped point.
    return (W[..., :2, :2] - mapped[..., :, None] * W[..., 2, None, :2]) / denom[..., None, None]


def frame_cropping(warps: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(N,) each frame's cropping: 1 / the scale of its warp input -> output (N, 3, 3) at the
    frame centre (the share of the input's width still shown; 1 = no zoom)."""
    J = warp_jacobian(warps, size)
    return 1.0 / np.sqrt(np.abs(np.linalg.det(J)))


def cropping_ratio(warps: np.ndarray, size: tuple[int, int]) -> float:
    """Liu et al.'s cropping ratio: the mean over frames of :func:`frame_cropping`."""
    return float(np.mean(frame_cropping(warps, size)))


def distortion(warps: np.ndarray, size: tuple[int, int]) -> float:
    """Liu et al.'s distortion score: the worst frame's ratio of singular values of the warp."""
    s = np.linalg.svd(warp_jacobian(warps, size), compute_uv=False)
    return float(np.min(s[..., 1] / s[..., 0]))


def _trimmed_rms(residual: np.ndarray, trim: int) -> float:
    """RMS length of (N, P, 2) residuals, leaving out ``trim`` frames at each end when the
    clip is long enough (the low-pass is least trustworthy there)."""
    if len(residual) > 4 * trim:
        residual = residual[trim:len(residual) - trim]
    return float(np.sqrt(np.mean(np.sum(residual ** 2, axis=-1))))


def lowpass_weights(fps: float, seconds: float = HIGHPASS_SECONDS) -> np.ndarray:
    """Symmetric weights (2r + 1,) that give the value at the centre of a Gaussian-weighted
    (sigma = ``seconds``) least-squares quadratic through a sequence: exact for quadratics."""
    sigma = max(1.0, seconds * fps)
    radius = int(np.ceil(3 * sigma))
    k = np.arange(-radius, radius + 1, dtype=np.float64)
    g = gaussian_weights(radius, sigma)
    X = np.vander(k, 3, increasing=True)
    return np.linalg.solve(X.T @ (g[:, None] * X), np.eye(3)[0]) @ X.T * g


def pairwise_jitter(pairwise: np.ndarray, size: tuple[int, int], fps: float, seconds: float = HIGHPASS_SECONDS) -> float:
    """Residual jitter (pixels) of a video from its frame-to-frame homographies (N-1, 3, 3),
    frame t -> t+1: how far each frame's corners lie from the low-pass (local quadratic) of
    where its neighbours' corners are, in the frame's own pixels."""
    if len(pairwise) < 2:
        return 0.0
    weights = lowpass_weights(fps, seconds)
    corners = frame_corners(*size)
    back = np.linalg.inv(normalize(pairwise))
    mean = neighbour_mean(back, corners, weights)
    return _trimmed_rms(corners - mean, len(weights) // 2)


def ground_truth_jitter(map_to_frame: np.ndarray, smooth_map_to_frame: np.ndarray, size: tuple[int, int], fps: float,
                        warps: np.ndarray | None = None, seconds: float = HIGHPASS_SECONDS) -> float:
    """Residual jitter (pixels of the input) of the output path against the known smooth one.

    With ``warps`` (input -> output, N x 3 x 3) it is the output's; without, the input's.
    The output frame's outline is followed in the coordinates of the jitter-free camera
    (map -> smooth frame), where the intended flight no longer moves it; what the high-pass
    leaves of that outline's motion is shake the stabiliser did not remove (or added)."""
    from scipy.ndimage import convolve1d
    M = normalize(map_to_frame)
    G = normalize(smooth_map_to_frame)
    W = np.broadcast_to(np.eye(3), M.shape) if warps is None else normalize(warps)
    outline = project(G @ np.linalg.inv(W @ M), frame_corners(*size))  # (N, 4, 2)
    weights = lowpass_weights(fps, seconds)
    low = convolve1d(outline, weights, axis=0, mode="nearest")
    return _trimmed_rms(outline - low, len(weights) // 2)


# The ruler for scores from pixels: mosaic's ORB with its sub-pixel polish, finer than the
# stabiliser's own tracking (measured on shaky flights: 0.05-0.09 px high-frequency error of
# the chained path, against 0.07-0.4 px at 320 px wide with 500 features).
RULER_WIDTH = 960
RULER_FEATURES = 1000


def ruler():
    from mosaic_cli.estimators import OrbEstimator
    from mosaic_cli.estimators.orb import OrbConfig

    return OrbEstimator(RULER_WIDTH, OrbConfig(n_features=RULER_FEATURES))


def track_pairwise(video: str | Path) -> tuple[np.ndarray, tuple[int, int], float]:
    """Frame-to-frame homographies of a video, measured with :func:`ruler` (full-res pixels)."""
    from mosaic_cli.track import track_video

    result = track_video(video, ruler(), show_progress=False)
    return result.pairwise, result.info.source_size, result.info.fps


def matched_warps(input_video: str | Path, output_video: str | Path, step: int = 1,
                  lens: ImageFilter | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Estimate the warp input frame t -> output frame t from the pixels, for every ``step``-th
    frame; returns (frame indices, warps in full-resolution pixels).  Frames that do not match
    are left out.  ``lens``: the input's frames through this filter (``--lens``: the input as
    the stabiliser saw it, undistorted); the output is read as written.

    Two rounds: the first fit brings the output back onto the input, where a zoom or rotation no
    longer spoils the sub-pixel polish; the second measures what is left."""
    import cv2

    from mosaic_cli.geometry import to_resolution
    from mosaic_cli.video import open_video

    estimator = ruler()

    def fit(a: np.ndarray, b: np.ndarray, full: tuple[int, int]) -> np.ndarray | None:
        estimator.reset(full)
        estimator.feed(a)
        (estimate,) = estimator.feed(b)
        return estimate.H if estimate.confidence > 0 else None

    indices, warps = [], []
    with open_video(input_video, width=RULER_WIDTH, gray=True, lens=lens) as src, \
            open_video(output_video, width=RULER_WIDTH, gray=True) as dst:
        full = src.info.source_size
        if dst.info.source_size != full:
            raise ValueError("input and output differ in size")
        for t, (a, b) in enumerate(zip(src, dst)):
            if t % step:
                continue
            first = fit(a, b, full)
            if first is None:
                continue
            work = (a.shape[1], a.shape[0])
            back = cv2.warpPerspective(b, to_resolution(first, full, work), work, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
            rest = fit(a, back, full)
            indices.append(t)
            warps.append(first if rest is None else normalize(first @ rest))
    return np.array(indices, dtype=int), np.array(warps).reshape(-1, 3, 3)
