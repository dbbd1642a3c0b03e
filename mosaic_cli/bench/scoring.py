"""Scoring estimators on flights with their ground truth: each flight's MACE (the paper's landmark
protocol), corner errors and per-frame times, and several flights pooled exactly (per profile too)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mosaic_cli.bench.timing import StageTimes, time_stats

PROFILE_ORDER = ("paper", "survey", "fast", "shaky", "shaky-tilt", "hard", "extreme", "bursts")


@dataclass
class Flight:
    name: str
    video: Path
    gt: object  # GroundTruth

    @property
    def profile(self) -> str:
        return self.gt.profile


@dataclass
class FlightScore:
    """One estimator on one flight: the raw errors, so that flights pool exactly."""

    flight: str
    profile: str
    landmark_errors: np.ndarray  # mean landmark error of each (f1, f2) pair (px, 1280x720-equivalent)
    corner_errors: np.ndarray  # per frame pair
    ms: np.ndarray  # per frame: preprocess + estimate, wall clock
    cpu_ms: np.ndarray  # per frame: preprocess + estimate, process CPU time
    metrics: dict  # mosaic_cli.evaluate.evaluate of this flight alone (what `mosaic eval` prints)
    touches_burst: np.ndarray | None = None  # per frame pair: it touches a frame without a motion cue (gt "bursts")


def find_flights(folder: str | Path) -> list[Flight]:
    """The flights of ``folder`` (:func:`mosaic_cli.inputs.find_flights`) with their ground truth."""
    from mosaic_cli.inputs import find_flights as find_flight_videos
    from mosaic_cli.simulate import ground_truth_path, load_ground_truth

    return [Flight(v.stem, v, load_ground_truth(ground_truth_path(v))) for v in find_flight_videos(folder, "--flights")]


def score_flight(flight: Flight, pairwise: np.ndarray, times: StageTimes) -> FlightScore:
    """MACE by the paper's protocol (landmark pairs every 30 frames, from the exact ground truth,
    on the frames the prediction covers), corner errors and per-frame times of one run."""
    from mosaic_cli.evaluate import corner_errors, evaluate, landmarks_from_ground_truth, mace_pairs
    from mosaic_cli.simulate.bursts import burst_pairs

    gt = flight.gt
    n = len(pairwise)
    ann = landmarks_from_ground_truth(gt)
    ann = ann[ann[:, 3] <= n]
    landmark = mace_pairs(pairwise, ann, gt.size)[1] if len(ann) else np.zeros(0)
    corners = corner_errors(pairwise, np.asarray(gt.pairwise)[:n], gt.size)
    frames = len(times.preprocess)
    ms = np.asarray(times.preprocess[:frames]) + np.asarray(times.estimate[:frames])
    touches = burst_pairs(gt.bursts, n) if gt.bursts else None
    return FlightScore(flight.name, flight.profile, landmark, corners, ms, np.asarray(times.cpu[:frames]), evaluate(pairwise, gt, ann),
                       touches)


def pool(scores: list[FlightScore]) -> dict:
    """The metrics of several flights taken together: MACE = mean over all their landmark pairs,
    corner error = median over all their frame pairs, failure rate = share of those pairs with a
    corner error above evaluate.FAILURE_PX, times = p50 over all their frames; on flights with
    bursts, the failure rate of the pairs that touch a burst and of the others apart."""
    from mosaic_cli.evaluate import FAILURE_PX

    touched = [(s.corner_errors, s.touches_burst) for s in scores if s.touches_burst is not None]
    bursts = {}
    if touched:
        errors = np.concatenate([e for e, _ in touched])
        mask = np.concatenate([m for _, m in touched])
        bursts = {"burst_pairs": int(mask.sum()), "burst_failure_rate": float(np.mean(errors[mask] > FAILURE_PX)) if mask.any() else None,
                  "other_failure_rate": float(np.mean(errors[~mask] > FAILURE_PX)) if (~mask).any() else None}
    landmark = np.concatenate([s.landmark_errors for s in scores])
    corners = np.concatenate([s.corner_errors for s in scores])
    ms = np.concatenate([s.ms for s in scores])
    cpu = np.concatenate([s.cpu_ms for s in scores])
    return {
        "mace": float(landmark.mean()) if len(landmark) else None,
        "corner_error": float(np.median(corners)),
        "failure_rate": float(np.mean(corners > FAILURE_PX)),
        "ms_per_frame": time_stats(ms),
        "cpu_ms_per_frame": time_stats(cpu),
        "flights": len(scores),
        "pairs": int(len(corners)),
        "landmark_pairs": int(len(landmark)),
        **bursts,
    }
