"""Scoring a georeferenced stitch against a simulated flight's exact truth, in metres."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from mosaic_cli.geometry import project


class FrameTruth(Protocol):
    """What scoring needs of a flight's truth (``mosaic_cli.simulate.groundtruth.GroundTruth``
    has it; geo, below the simulator, does not import it): the frame size and, per frame, the
    homography from map pixels to frame pixels."""

    @property
    def size(self) -> tuple[int, int]: ...

    @property
    def map_to_frame(self) -> np.ndarray: ...


@dataclass
class GroundScore:
    median_m: float  # ground error of mosaic pixels (a 5x5 grid over every keyframe)
    max_m: float
    scale_error: float  # relative: (mosaic scale / true scale) - 1
    heading_error_deg: float
    keyframes: int


def score_map_homographies(map_h: dict[int, np.ndarray], gt: FrameTruth, map_to_crs: np.ndarray, grid: int = 5) -> GroundScore:
    """Compare where each keyframe's pixels land (``map_h``: frame index -> frame pixels ->
    east, north) with where they truly lie (``gt.map_to_frame`` and the map's geotransform)."""
    w, h = gt.size
    xs, ys = np.meshgrid(np.linspace(0, w - 1, grid), np.linspace(0, h - 1, grid))
    pts = np.stack([xs.ravel(), ys.ravel()], 1)
    got, truth = [], []
    for index, M in map_h.items():
        got.append(project(M, pts))
        truth.append(project(map_to_crs @ np.linalg.inv(gt.map_to_frame[index]), pts))
    got, truth = np.concatenate(got), np.concatenate(truth)
    d = np.linalg.norm(got - truth, axis=1)
    # the similarity between the mosaic's ground points and the truth: its scale and rotation
    cg, ct = got.mean(0), truth.mean(0)
    a, b = got - cg, truth - ct
    zg, zt = a[:, 0] + 1j * a[:, 1], b[:, 0] + 1j * b[:, 1]
    ratio = np.vdot(zg, zt) / np.vdot(zg, zg)  # truth ~ ratio * got
    return GroundScore(float(np.median(d)), float(d.max()), float(1.0 / abs(ratio) - 1.0),
                       float(math.degrees(-np.angle(ratio))), len(map_h))


def score_files(transforms: str | Path, gt: FrameTruth, geo_truth: str | Path) -> GroundScore:
    data = json.loads(Path(transforms).read_text())
    truth = json.loads(Path(geo_truth).read_text())
    map_h = {int(f["index"]): np.array(f["map_H"], dtype=np.float64) for f in data["frames"]}
    return score_map_homographies(map_h, gt, np.array(truth["map_to_crs"], dtype=np.float64))
