"""``--plot FILE.png``: what stabilize and track computed, drawn over time (matplotlib, optional).

The data plotted are computed by plain functions (``camera_path_series``, ``crop_series``),
tested on their own; the drawing only lays them out.  matplotlib is the ``plot`` extra: a run
that asks for a plot without it is refused before any work.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput, install_hint

INSTALL = install_hint("plot")


def check_plot_request(path: str | Path | None) -> None:
    """``--plot FILE.png``: a writable .png, and matplotlib installed; before any long work."""
    if path is None:
        return
    from mosaic_cli.atomic import check_writable

    if Path(path).suffix.lower() != ".png":
        raise BadInput(f"--plot {path} must end in .png")
    check_writable(path)
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise BadInput(f"--plot needs matplotlib, which is not installed: {INSTALL}") from None


@dataclass
class PathSeries:
    """A camera path per axis, one value per frame: translation x, y (frame widths, heights),
    rotation (degrees) and scale (1: as the first frame)."""

    x: np.ndarray
    y: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray


def path_series(path: np.ndarray) -> PathSeries:
    """(N, 3, 3) frame -> first-frame transforms (normalised coordinates) as per-axis series."""
    path = np.asarray(path, float)
    a, b = path[:, 0, 0], path[:, 1, 0]
    return PathSeries(path[:, 0, 2], path[:, 1, 2], np.degrees(np.arctan2(b, a)), np.hypot(a, b))


def camera_path_series(motion: np.ndarray, views: np.ndarray) -> tuple[PathSeries, PathSeries]:
    """The camera path before and after stabilisation.  ``motion`` (N-1, 3, 3): F_{t+1}, frame
    t+1 -> frame t (stabilize.path.camera_motion); ``views`` (N, 3, 3): each output frame's view
    in its input frame (the smoother's answer).  Before: C_t = F_1 ... F_t, frame t -> frame 0;
    after: C_t V_t, the path the output follows."""
    chain = [np.eye(3)]
    for F in np.asarray(motion, float):
        chain.append(chain[-1] @ F)
    before = np.array(chain)
    after = before @ np.asarray(views, float)
    return path_series(before), path_series(after)


@dataclass
class CropSeries:
    """The crop window of each output frame in its input frame: the share of the input's
    width it keeps and its centre (input pixels)."""

    kept: np.ndarray
    centre_x: np.ndarray
    centre_y: np.ndarray


def crop_series(warps: np.ndarray, size: tuple[int, int]) -> CropSeries:
    """``warps`` (N, 3, 3): input -> output pixels (StabilizeResult.warps)."""
    w, h = size
    corners = np.array([[0, 0, 1], [w, 0, 1], [w, h, 1], [0, h, 1]], float).T
    window = np.linalg.inv(np.asarray(warps, float)) @ corners  # output frame's corners in the input
    window = window[:, :2] / window[:, 2:]
    x, y = window[:, 0], window[:, 1]
    area = 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1))  # shoelace
    return CropSeries(np.sqrt(area / (w * h)), x.mean(axis=1), y.mean(axis=1))


def _figure(rows: int):
    import matplotlib

    matplotlib.use("Agg")  # files only: no display needed, none opened
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(rows, 1, figsize=(9, max(3.5, 2.2 * rows)), sharex=True, squeeze=False)
    return figure, axes[:, 0]


def _save(figure, path: str | Path) -> None:
    import matplotlib.pyplot as plt

    from mosaic_cli.atomic import atomic_path

    figure.tight_layout()
    with atomic_path(path) as tmp:
        figure.savefig(tmp, format="png", dpi=100)
    plt.close(figure)


def write_stabilize_plot(path: str | Path, before: PathSeries, after: PathSeries, crop: CropSeries, fps: float) -> None:
    """The camera path before and after, per axis, and the crop window, over time (seconds)."""
    figure, axes = _figure(5)
    t = np.arange(len(before.x)) / (fps or 1.0)
    for ax, name, label in zip(axes, ("x", "y", "rotation", "scale"),
                               ("x (frame widths)", "y (frame heights)", "rotation (deg)", "scale")):
        ax.plot(t, getattr(before, name), color="0.6", label="before")
        ax.plot(t, getattr(after, name), color="tab:blue", label="after")
        ax.set_ylabel(label)
    axes[0].legend(loc="upper right")
    axes[0].set_title("camera path")
    kept = axes[4]
    kept.plot(t[:len(crop.kept)], crop.kept, color="tab:orange")
    kept.set_ylabel("crop: width kept")
    kept.set_xlabel("seconds" if fps else "frames")
    _save(figure, path)


PATH_STYLES = {"fallback": ("tab:orange", "o"), "carried": ("tab:purple", "s"), "failed": ("tab:red", "x")}


def write_track_plot(path: str | Path, confidence: np.ndarray, fps: float, failed_below: float = 0.0,
                     paths: list[str] | None = None) -> None:
    """Each pair's confidence over time; failed pairs (confidence at or below ``failed_below``)
    marked, and with ``paths`` (the learned estimator's, per pair) the pairs the classical
    fallback made and those the carried motion placed, each in its own colour."""
    figure, axes = _figure(1)
    confidence = np.asarray(confidence, float)
    t = (np.arange(len(confidence)) + 1) / (fps or 1.0)  # pair t -> t+1 is known at frame t+1
    ax = axes[0]
    ax.plot(t, confidence, color="tab:blue", label="confidence")
    kinds = np.asarray(paths) if paths is not None else np.where(confidence <= failed_below, "failed", "")
    for kind, (colour, marker) in PATH_STYLES.items():
        marked = kinds == kind
        if marked.any():
            ax.scatter(t[marked], confidence[marked], color=colour, marker=marker, label=kind, zorder=3)
    ax.set_ylim(-0.05, 1.05)
    ax.set_ylabel("confidence")
    ax.set_xlabel("seconds" if fps else "frames")
    ax.legend(loc="lower right")
    _save(figure, path)
