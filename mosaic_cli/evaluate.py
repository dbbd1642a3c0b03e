"""Accuracy of pairwise homographies: the paper's MACE, corner error and failure rate.

MACE (the paper's protocol): landmark annotations ``f1 x1 y1 f2 x2 y2`` (the same ground
point seen in frame f1 at (x1, y1) and in frame f2 at (x2, y2), 0-based frames, f2 - f1 about
30).  The predicted pairwise homographies are chained from f1 to f2, (x1, y1) is mapped through
the chain and compared with (x2, y2); errors are averaged per (f1, f2) pair, then over pairs.
So MACE measures drift accumulated over ~30 frames.  Every number is reported in
1280x720-equivalent pixels (scaled by 1280 / w for frames of width w).

Corner error: per pair, the mean distance between the frame corners mapped by the predicted
and by the true homography (1280x720-equivalent px); failure: a pair whose corner error
exceeds :data:`FAILURE_PX`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.geometry import chain, corner_error, normalize, project

REFERENCE_WIDTH = 1280.0
FAILURE_PX = 10.0
LANDMARK_EVERY = 30


def _scale(size) -> float:
    return REFERENCE_WIDTH / float(size[0])


def landmarks_from_ground_truth(gt, every: int = LANDMARK_EVERY, grid: tuple[int, int] = (4, 3), margin: float = 0.05) -> np.ndarray:
    """Exact landmark annotations (M, 6) ``f1 x1 y1 f2 x2 y2`` from a ground truth.

    For f1 = 0, every, 2*every, ... (while f1 + every is a frame) a ``grid`` (columns, rows) of
    points spread over the central area of frame f1 (the middle 60 % in each direction) is
    mapped to f2 = f1 + every by the true homography; points landing outside frame f2 (less a
    ``margin`` of its size) are left out."""
    w, h = gt.size
    M = np.asarray(gt.map_to_frame, dtype=np.float64)
    xs = np.linspace(0.2 * (w - 1), 0.8 * (w - 1), grid[0])
    ys = np.linspace(0.2 * (h - 1), 0.8 * (h - 1), grid[1])
    pts = np.array([(x, y) for y in ys for x in xs])
    rows = []
    for f1 in range(0, len(M) - every, every):
        f2 = f1 + every
        H = normalize(M[f2] @ np.linalg.inv(M[f1]))
        q = project(H, pts)
        inside = (
            (q[:, 0] >= margin * w) & (q[:, 0] <= (1 - margin) * w - 1) & (q[:, 1] >= margin * h) & (q[:, 1] <= (1 - margin) * h - 1)
        )
        for p, m in zip(pts[inside], q[inside]):
            rows.append((f1, p[0], p[1], f2, m[0], m[1]))
    return np.array(rows, dtype=np.float64).reshape(-1, 6)


def read_annotations(path: str | Path) -> np.ndarray:
    """Landmark annotations (M, 6) from a text file of lines ``f1 x1 y1 f2 x2 y2``
    (whitespace or comma separated; blank lines and ``#`` comments are skipped)."""
    p = Path(path)
    if not p.exists():
        raise BadInput(f"{p}: no such file")
    if p.is_dir():
        raise BadInput(f"{p}: is a folder, not an annotation file")
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise BadInput(f"{p}: cannot read annotations ({exc.__class__.__name__})") from None
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != 6:
            raise BadInput(f"{p}:{number}: expected 6 numbers 'f1 x1 y1 f2 x2 y2', got {len(parts)}")
        try:
            values = [float(v) for v in parts]
        except ValueError:
            raise BadInput(f"{p}:{number}: not a number in {line!r}") from None
        if not all(np.isfinite(values)):
            raise BadInput(f"{p}:{number}: non-finite value")
        if values[0] != int(values[0]) or values[3] != int(values[3]) or values[0] < 0 or values[3] < 0:
            raise BadInput(f"{p}:{number}: frame numbers must be whole numbers >= 0")
        rows.append(values)
    if not rows:
        raise BadInput(f"{p}: no annotations in the file")
    return np.array(rows, dtype=np.float64)


def write_annotations(path: str | Path, rows: np.ndarray) -> None:
    """Write annotations (M, 6) as ``f1 x1 y1 f2 x2 y2`` lines (atomically)."""
    from mosaic_cli.atomic import atomic_path

    rows = np.asarray(rows, dtype=np.float64).reshape(-1, 6)
    lines = ["# f1 x1 y1 f2 x2 y2  (0-based frames, pixel centres, full-resolution pixels)"]
    for f1, x1, y1, f2, x2, y2 in rows:
        lines.append(f"{int(f1)} {x1:.4f} {y1:.4f} {int(f2)} {x2:.4f} {y2:.4f}")
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")


def _clean(pairwise: np.ndarray) -> tuple[np.ndarray, int]:
    """Non-finite or singular estimates count as "no motion" (identity); returns how many."""
    P = np.array(pairwise, dtype=np.float64).reshape(-1, 3, 3)
    bad = ~np.all(np.isfinite(P), axis=(1, 2)) | (np.abs(P[:, 2, 2]) < 1e-12)
    P[bad] = np.eye(3)
    return P, int(bad.sum())


def mace_pairs(pairwise_pred: np.ndarray, annotations: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(pairs (K, 2) of (f1, f2), mean landmark error of each in 1280x720-equivalent px)."""
    P, _ = _clean(pairwise_pred)
    ann = np.asarray(annotations, dtype=np.float64).reshape(-1, 6)
    if len(ann) == 0:
        raise BadInput("no landmark annotations to score")
    n_frames = len(P) + 1
    top = int(max(ann[:, 0].max(), ann[:, 3].max()))
    if top >= n_frames:
        raise BadInput(f"annotations refer to frame {top} but the prediction covers frames 0..{n_frames - 1}")
    keys = ann[:, [0, 3]].astype(np.int64)
    pairs, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    errors = np.zeros(len(pairs))
    for k, (f1, f2) in enumerate(pairs):
        sel = inverse == k
        H = chain(P, int(f1), int(f2))
        q = project(H, ann[sel, 1:3])
        d = np.linalg.norm(q - ann[sel, 4:6], axis=1)
        errors[k] = np.mean(np.where(np.isfinite(d), d, 1e6))
    return pairs, errors * _scale(size)


def mace(pairwise_pred: np.ndarray, annotations: np.ndarray, size: tuple[int, int] = (1280, 720)) -> float:
    """The paper's MACE in 1280x720-equivalent pixels (see the module docstring)."""
    return float(np.mean(mace_pairs(pairwise_pred, annotations, size)[1]))


def corner_errors(pairwise_pred: np.ndarray, pairwise_true: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Per-pair corner error (1280x720-equivalent px) of predictions against the truth."""
    P, _ = _clean(pairwise_pred)
    T = np.asarray(pairwise_true, dtype=np.float64).reshape(-1, 3, 3)
    err = corner_error(P, T, size) * _scale(size)
    return np.where(np.isfinite(err), err, np.inf)


def check_same_video(pairwise_pred: np.ndarray, pred_size: tuple[int, int] | None, gt) -> None:
    """A prediction is scored against a ground truth only when both describe the same video:
    the same frame count and (when the prediction says) the same frame size.  A track of part
    of the flight, or of another clip, would otherwise get a score that means nothing."""
    if pred_size is not None and tuple(pred_size) != tuple(gt.size):
        raise BadInput(f"the prediction is for {pred_size[0]}x{pred_size[1]} frames but the ground truth for "
                       f"{gt.size[0]}x{gt.size[1]}: not the same video")
    frames = len(pairwise_pred) + 1
    if frames != gt.frames:
        raise BadInput(f"the prediction covers {frames} frames but the ground truth {gt.frames}: not the same video "
                       f"(track the whole clip the ground truth came with)")


def evaluate(pairwise_pred: np.ndarray, gt, annotations: np.ndarray | None = None, every: int = LANDMARK_EVERY) -> dict:
    """All metrics of a prediction against a ground truth.

    ``annotations`` default to :func:`landmarks_from_ground_truth` (a pair every ``every``
    frames).  A prediction shorter than the flight (e.g. ``mosaic track --max-frames``) is
    scored on the frames it covers."""
    P = np.asarray(pairwise_pred, dtype=np.float64).reshape(-1, 3, 3)
    T = np.asarray(gt.pairwise, dtype=np.float64)
    if len(P) == 0:
        raise BadInput("the prediction holds no pairwise homographies")
    if len(P) > len(T):
        raise BadInput(f"the prediction has {len(P)} pairwise homographies but the ground truth only {len(T)} ({gt.frames} frames)")
    n = len(P)
    if annotations is None:
        annotations = landmarks_from_ground_truth(gt, every=every)
        annotations = annotations[annotations[:, 3] <= n]
    ann = np.asarray(annotations, dtype=np.float64).reshape(-1, 6)
    cerr = corner_errors(P, T[:n], gt.size)
    _, invalid = _clean(P)
    result = {
        "mace": float(np.mean(mace_pairs(P, ann, gt.size)[1])) if len(ann) else None,
        "corner_error": float(np.median(cerr)),
        "corner_error_mean": float(np.mean(cerr)) if np.all(np.isfinite(cerr)) else float("inf"),
        "failure_rate": float(np.mean(cerr > FAILURE_PX)),
        "pairs": int(n),
        "landmark_pairs": int(len(np.unique(ann[:, [0, 3]], axis=0))) if len(ann) else 0,
        "landmarks": int(len(ann)),
        "invalid": invalid,
        "frames": int(n + 1),
        "units": "1280x720-equivalent px",
    }
    return result


def load_prediction(path: str | Path) -> tuple[np.ndarray, tuple[int, int] | None]:
    """Pairwise predictions (N-1, 3, 3) and frame size (w, h) if known, from a ``mosaic track``
    JSON file or a ``.npy`` array."""
    p = Path(path)
    if not p.exists():
        raise BadInput(f"{p}: no such file")
    if p.is_dir():
        raise BadInput(f"{p}: is a folder, not a prediction file")
    if p.suffix.lower() == ".npy":
        try:
            arr = np.load(p, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise BadInput(f"{p}: not a numpy .npy file ({exc.__class__.__name__})") from None
        if arr.ndim != 3 or arr.shape[1:] != (3, 3):
            raise BadInput(f"{p}: expected an (N-1, 3, 3) array of pairwise homographies, got shape {arr.shape}")
        return arr.astype(np.float64), None
    from mosaic_cli.track import read_track_file

    _, arr, size = read_track_file(p)
    return arr, size


@dataclass
class EvalOptions:
    """What ``mosaic eval`` scores a prediction against."""

    gt: Path | None = None  # a simulated flight's ground truth (<stem>.gt.json)
    annotations: Path | None = None  # landmark annotations, 'f1 x1 y1 f2 x2 y2' per line
    size: tuple[int, int] | None = None  # frame size (w, h) of a .npy prediction scored on annotations
    every: int = LANDMARK_EVERY  # frames between the landmark pairs made from the ground truth

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        if self.gt is None and self.annotations is None:
            raise BadInput("give --gt GROUND_TRUTH.json and/or --annotations ANNOTATIONS.txt")
        if self.every < 1:
            raise BadInput(f"--every must be at least 1 frame, got {self.every}")


def score(prediction: str | Path, options: EvalOptions) -> dict:
    """The metrics of the prediction file ``prediction`` (see :func:`load_prediction`): against
    the ground truth when ``options`` has one (on its annotations if given, else on landmarks
    made from the truth), else MACE on the annotations alone."""
    from mosaic_cli.simulate.groundtruth import load_ground_truth

    pred, pred_size = load_prediction(prediction)
    ann = read_annotations(options.annotations) if options.annotations is not None else None
    if options.gt is not None:
        truth = load_ground_truth(options.gt)
        check_same_video(pred, pred_size, truth)
        metrics = evaluate(pred, truth, ann, every=options.every)
    else:
        size = options.size or pred_size
        if size is None:
            raise BadInput("a .npy prediction scored on annotations needs --size WxH (the video's frame size)")
        _, errors = mace_pairs(pred, ann, size)
        metrics = {"mace": float(errors.mean()), "landmark_pairs": int(len(errors)), "landmarks": int(len(ann)),
                   "pairs": int(len(pred)), "frames": int(len(pred) + 1), "units": "1280x720-equivalent px"}
    metrics["prediction"] = str(prediction)
    return metrics

