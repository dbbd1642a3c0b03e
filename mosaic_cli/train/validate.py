"""Validation during training: the paper's MACE on flights with known homographies.

``--val VAL_DIR`` holds videos written by ``mosaic simulate`` (``X.mp4`` with ``X.gt.json``
beside it).  The network runs alone, as ``mosaic track --weights W -e lstm:refine=none:fallback=none``
runs it (the learned estimator without the polish it seeds and without the classical fallback: the
centre patch of each gray working frame, the LSTM state carried through the whole flight,
implausible estimates replaced by the identity), its pairwise homographies
are scored against landmarks derived from the ground truth every 30 frames, and the errors
are averaged over the (f1, f2) pairs of all flights together, as in the paper.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mosaic_cli import inputs
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators.learned import LearnedConfig, LearnedEstimator
from mosaic_cli.evaluate import landmarks_from_ground_truth, mace_pairs
from mosaic_cli.model.network import HomographyNet
from mosaic_cli.simulate import load_ground_truth
from mosaic_cli.track import track_video


@dataclass(frozen=True)
class ValFlight:
    video: Path
    gt: object  # mosaic_cli.simulate.GroundTruth
    landmarks: np.ndarray  # (n, 6) f1 x1 y1 f2 x2 y2


def find_flights(folder: str | Path) -> list[ValFlight]:
    """Every flight of ``folder`` (:func:`mosaic_cli.inputs.find_flights`) long enough to hold a
    landmark pair (30+ frames)."""
    flights = []
    for video in inputs.find_flights(folder, "--val"):
        gt = load_ground_truth(video)
        landmarks = landmarks_from_ground_truth(gt)
        if len(landmarks):
            flights.append(ValFlight(video, gt, landmarks))
    if not flights:
        raise BadInput(f"--val {folder}: no flight of 30+ frames (make some with mosaic simulate)")
    return flights


def flight_pairwise(net: HomographyNet, video: Path, device: torch.device, work_size: tuple[int, int],
                    variant: str = "base") -> np.ndarray:
    """Pairwise homographies (N-1, 3, 3), frame t -> t+1 in full-resolution pixels: exactly what
    ``mosaic track --weights W -e NAME:refine=none:fallback=none`` would output for this net (a copy, so
    that the estimator's inference settings never touch the weights being trained)."""
    meta = {"work_size": tuple(work_size), "variant": variant}
    # The network alone: the LK polish it seeds at inference, or ORB taking over the pairs it
    # cannot confirm, would hide what training changes (and flatter the network in val.csv).
    alone = LearnedConfig(refine=None, fallback="none", carry="none")
    estimator = LearnedEstimator(copy.deepcopy(net), meta, device=str(device), config=alone)
    return track_video(video, estimator, show_progress=False).pairwise


def validation_mace(net: HomographyNet, flights: list[ValFlight], device: torch.device,
                    work_size: tuple[int, int], variant: str = "base") -> float:
    """MACE (1280x720-equivalent px) over all landmark pairs of all flights."""
    errors = []
    for flight in flights:
        pairwise = flight_pairwise(net, flight.video, device, work_size, variant)
        n = len(pairwise)
        landmarks = flight.landmarks[flight.landmarks[:, 3] <= n]
        if len(landmarks):
            errors.append(mace_pairs(pairwise, landmarks, flight.gt.size)[1])
    return float(np.mean(np.concatenate(errors))) if errors else float("nan")
