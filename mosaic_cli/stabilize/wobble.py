"""Rolling-shutter wobble: how much the shape of the picture changes from frame to frame.

* ``ground_truth_wobble``, exact, for a simulated flight: points along each band's centre row
  are followed to the output (through the band's own warp when the output was corrected per
  row, else the frame's) and compared with where the frame's mid-time pose and the frame's
  warp put them: a rigid frame puts them there exactly.  The per-frame mean of that
  displacement (a shift of the whole frame: jitter, scored by ``metrics.ground_truth_jitter``)
  is taken out; what varies over the rows is the frame's distortion.  A steady distortion (the
  skew of a steady pan) is not wobble: the score is the RMS of its change between consecutive
  output frames, in output pixels.
* ``video_wobble``, from the pixels of any video (vid.stab's output too): corners tracked
  between consecutive frames, each band's median motion less the mean over the bands (the
  row-dependent part of the frame-to-frame motion, which is already the change of the
  distortion), differenced once more in time so that a slow zoom or turn of the path, which
  also varies over the rows, cancels; RMS in full-resolution pixels.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mosaic_cli.geometry import normalize, project
from mosaic_cli.geometry.rolling_shutter import band_centres

COLUMNS = 9  # points along each band's centre row


def ground_truth_wobble(row_bands: np.ndarray, map_to_frame: np.ndarray, size: tuple[int, int],
                        warps: np.ndarray | None = None, band_warps: np.ndarray | None = None) -> float:
    """Residual wobble (output px) of frames whose bands see the map through ``row_bands``
    (N, K, 3, 3), with mid-time poses ``map_to_frame`` (N, 3, 3); ``warps`` (N, 3, 3) input ->
    output (None: the input itself), ``band_warps`` (N, K, 3, 3) the warp of each band's centre
    row when the output was corrected per row (None: ``warps`` for every row)."""
    N, K = row_bands.shape[:2]
    w, h = size
    W = np.broadcast_to(np.eye(3), (N, 3, 3)) if warps is None else normalize(warps)
    E = W[:, None] if band_warps is None else normalize(band_warps)
    xs = np.linspace(0.05 * w, 0.95 * w, COLUMNS)
    residual = np.empty((N, K, COLUMNS, 2))
    for k, yk in enumerate(band_centres(h, K)):
        pts = np.stack([xs, np.full(COLUMNS, yk)], 1)
        on_map = project(np.linalg.inv(row_bands[:, k]), pts)  # (N, C, 2)
        seen = project(np.broadcast_to(E[:, min(k, E.shape[1] - 1)], (N, 3, 3)), pts)
        rigid = project(W @ map_to_frame, on_map)
        residual[:, k] = seen - rigid
    residual -= residual.mean(axis=(1, 2), keepdims=True)
    change = np.diff(residual, axis=0)
    return float(np.sqrt(np.mean(np.sum(change ** 2, axis=-1))))


def band_flow(video: str | Path, bands: int = 16, width: int = 640, margin: float = 0.06) -> tuple[np.ndarray, np.ndarray]:
    """(N-1, K, 2) each band's median motion frame t -> t+1 (full-resolution px, NaN where the
    band has fewer than 5 tracked corners), and (N-1,) the frames' median motion."""
    from mosaic_cli.estimators.rolling import tracked_corners
    from mosaic_cli.video import probe

    info = probe(video)
    w, h = info.source_size
    out, whole = [], []
    for src, dst in tracked_corners(video, width, info):
        inside = (src[:, 0] > margin * w) & (src[:, 0] < (1 - margin) * w) & (src[:, 1] > margin * h) & (src[:, 1] < (1 - margin) * h)
        src, dst = src[inside], dst[inside]
        band = np.clip((src[:, 1] + 0.5) * bands / h, 0, bands - 1).astype(int)
        motion = np.full((bands, 2), np.nan)
        for k in range(bands):
            if np.sum(band == k) >= 5:
                motion[k] = np.median(dst[band == k] - src[band == k], axis=0)
        out.append(motion)
        whole.append(np.median(dst - src, axis=0) if len(src) else np.full(2, np.nan))
    return np.array(out).reshape(-1, bands, 2), np.array(whole).reshape(-1, 2)


def video_wobble(video: str | Path, bands: int = 16, width: int = 640) -> float:
    """Residual wobble of a video from its pixels alone (see the module docstring), px."""
    flow, _ = band_flow(video, bands, width)
    row_part = flow - np.nanmean(flow, axis=1, keepdims=True)
    change = np.diff(row_part, axis=0)
    return float(np.sqrt(np.nanmean(np.sum(change ** 2, axis=-1))))


def ground_truth_band_placement(row_bands: np.ndarray, map_to_frame: np.ndarray, size: tuple[int, int],
                                transforms: list[tuple[int, np.ndarray]], bands: list[np.ndarray] | None = None) -> dict[str, float]:
    """How far a panorama puts each keyframe's row bands from where they belong, panorama px.

    ``transforms``: (frame index, frame -> panorama) per keyframe (``stitch``'s, whose placement
    is the frame's mid-time pose); ``bands``: each keyframe's (K, 3, 3) frame -> panorama of its
    band centre rows when it was drawn band by band (None: its transform for every row).  The
    map -> panorama gauge is fitted (least squares) to the keyframes' mid-time poses, which
    ``transforms``: (frame index, frame -> panorama) per keyframe; ``bands``: each keyframe's
    (K, 3, 3) frame -> panorama of its band centre rows when it was drawn band by band (None:
    its transform for every row).  Points along each band's centre row go to the map through
    the band's true camera; the map -> panorama gauge is the homography that best fits them
    (least squares over all keyframes and bands) to where the panorama drew them, each way of
    drawing given its own best gauge.  Returns the RMS distance of each point from there
    (``rms``) and the same with each keyframe's mean displacement taken out (``shape``: what
    is smeared or doubled between rows rather than a shift of the whole frame)."""
    import cv2

    w, h = size
    xs = np.linspace(0.05 * w, 0.95 * w, COLUMNS)
    K = row_bands.shape[1]
    on_map, drawn = np.empty((len(transforms), K, COLUMNS, 2)), np.empty((len(transforms), K, COLUMNS, 2))
    for j, (i, H) in enumerate(transforms):
        for k, yk in enumerate(band_centres(h, K)):
            pts = np.stack([xs, np.full(COLUMNS, yk)], 1)
            on_map[j, k] = project(np.linalg.inv(row_bands[i, k]), pts)
            drawn[j, k] = project(H if bands is None else bands[j][k], pts)
    gauge, _ = cv2.findHomography(on_map.reshape(-1, 2), drawn.reshape(-1, 2), 0)
    errors = drawn - project(gauge, on_map.reshape(-1, 2)).reshape(drawn.shape)
    shape = errors - errors.mean(axis=(1, 2), keepdims=True)
    return {"rms": float(np.sqrt(np.mean(np.sum(errors ** 2, -1)))), "shape": float(np.sqrt(np.mean(np.sum(shape ** 2, -1))))}
