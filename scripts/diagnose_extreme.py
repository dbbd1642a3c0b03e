#!/usr/bin/env python3
"""Why do pairs of a flight fail?  Seeds, the polish, and whether the frames pin the motion down.

    python scripts/diagnose_extreme.py FLIGHT.mp4 [FLIGHT.mp4 ...] [--frames 300]

For every pair of each simulated flight (exact truth from its .gt.json), at the learned
estimator's working width and with its polish settings (LearnedConfig's defaults):

* how close each seed is to the truth: the network's estimate (``lstm``, no polish), the
  previous pair's polished motion (constant velocity), the identity;
* the failure rate of the default polish cascade (cheap, then wide, then cheap again) from each
  seed, and of an oracle that keeps, pair by pair, whichever seed's polish came out right: what
  no choice of seed can beat;
* the basin test: the correctly placed pairs re-polished from their own result shifted by 3 px
  (three directions, the cheap polish with 15 px windows).  Where the frames determine the
  motion, the polish pulls the estimate back; where it stays where it was put, the pair was
  right only because its seed was, and the frames alone could not have told.

A failure is a corner error above 10 px at 1280x720 (evaluate.FAILURE_PX), as in ``mosaic bench``.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from mosaic_cli.estimators.learned import LearnedConfig, make_learned_estimator
from mosaic_cli.estimators.refine import band_pass, points_to_track, track_points
from mosaic_cli.evaluate import FAILURE_PX
from mosaic_cli.geometry import frame_corners, project
from mosaic_cli.simulate import ground_truth_path, load_ground_truth
from mosaic_cli.track import track_video
from mosaic_cli.video import open_video

WORK = (320, 180)
SHIFT_PX = 3.0  # the basin test's displacement (working px)


def shift(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]])


def diagnose(video: Path, frames: int, weights: str | None = None) -> dict:
    gt = load_ground_truth(ground_truth_path(video))
    s = WORK[0] / gt.size[0]
    S = np.diag([s, s, 1.0])
    network = make_learned_estimator("lstm", weights=weights, config=LearnedConfig(refine=None, fallback="none", min_zncc=None))
    pairwise = np.asarray(track_video(str(video), network, max_frames=frames, show_progress=False).pairwise)
    to_work = lambda H: S @ H @ np.linalg.inv(S)  # noqa: E731
    seeds_net = [to_work(H) for H in pairwise]
    truth = [to_work(H) for H in gt.pairwise[: len(pairwise)]]
    corners = frame_corners(*WORK)
    err = lambda A, B: float(np.linalg.norm(project(A, corners) - project(B, corners), axis=-1).mean())  # noqa: E731
    limit = FAILURE_PX * s

    with open_video(str(video), width=WORK[0], gray=True) as stream:
        grays = [g for _, g in zip(range(len(pairwise) + 1), stream)]
    config = LearnedConfig()
    aligned = [band_pass(g, *config.polish_band) for g in grays]
    points = [points_to_track(g, config.corners) for g in grays]
    cheap, wide = config.polish, config.polish_wide
    probe = replace(cheap, window=15, max_shift=2 * SHIFT_PX)

    def polish(k: int, H: np.ndarray) -> np.ndarray | None:
        first = track_points(aligned[k], aligned[k + 1], H, points[k], cheap)
        if first.refined:
            return first.H
        found = track_points(aligned[k], aligned[k + 1], H, points[k], wide)
        if not found.refined:
            return None
        again = track_points(aligned[k], aligned[k + 1], found.H, points[k], cheap)
        return again.H if again.refined else found.H

    def holds(k: int, H: np.ndarray) -> bool:
        for dx, dy in ((SHIFT_PX, 0), (0, SHIFT_PX), (-SHIFT_PX / 1.5, -SHIFT_PX / 1.5)):
            back = track_points(aligned[k], aligned[k + 1], shift(dx, dy) @ H, points[k], probe)
            if not back.refined or err(back.H, H) > 1.0:
                return False
        return True

    seed_err = {"network": [], "velocity": [], "identity": []}
    placed_err = {name: [] for name in seed_err}
    held, velocity = [], np.eye(3)
    for k, T in enumerate(truth):
        for name, seed in (("network", seeds_net[k]), ("velocity", velocity), ("identity", np.eye(3))):
            seed_err[name].append(err(seed, T))
            H = polish(k, seed)
            placed_err[name].append(err(H, T) if H is not None else np.inf)
            if name == "network":
                result = H
        if result is not None:
            velocity = result
            if err(result, T) <= limit:
                held.append(holds(k, result))
    fails = {name: np.asarray(v) > limit for name, v in placed_err.items()}
    return {
        "flight": video.stem, "pairs": len(truth),
        "seed_within": {name: float(np.mean(np.asarray(v) <= limit)) for name, v in seed_err.items()},
        "failed": {name: float(f.mean()) for name, f in fails.items()},
        "oracle_failed": float(np.mean(np.logical_and.reduce(list(fails.values())))),
        "right_that_hold": float(np.mean(held)) if held else float("nan"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("flights", nargs="+", type=Path)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--weights", default=None, help="the network's weights (default: the shipped lstm)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print("| flight | seed within 10 px: network / velocity / identity | failed after the polish: network / velocity / identity "
          "| best of the three seeds (oracle) | correctly placed pairs whose basin holds |")
    print("| --- | --- | --- | ---: | ---: |")
    for video in args.flights:
        r = diagnose(video, args.frames, args.weights)
        w, f = r["seed_within"], r["failed"]
        print(f"| {r['flight']} | {w['network']:.0%} / {w['velocity']:.0%} / {w['identity']:.0%} "
              f"| {f['network']:.1%} / {f['velocity']:.1%} / {f['identity']:.1%} | {r['oracle_failed']:.1%} "
              f"| {r['right_that_hold']:.0%} |", flush=True)


if __name__ == "__main__":
    main()
