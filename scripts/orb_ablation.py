#!/usr/bin/env python3
"""Choose the OrbConfig defaults by measurement. For ORB variants and for the paper-style
baseline (scripts/baseline_orb.py), report MACE by the paper's protocol, the median corner
error, the failure rate and the estimator's CPU ms per frame. The flights are simulated with
exact ground truth; `mosaic simulate` writes each one's <stem>.gt.json.

    python scripts/orb_ablation.py flights/*.mp4 [--json results.json]

Each flight is decoded once, at the working width and in gray, and every variant runs on the
same frames. Only the estimator is timed, in CPU time (time.process_time), so that the load
from other processes on a shared machine moves the numbers less. The tables quote medians
over the flights.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.estimators import OrbConfig, OrbEstimator
from mosaic_cli.evaluate import evaluate
from mosaic_cli.simulate import ground_truth_path, load_ground_truth
from mosaic_cli.video import open_video

DEFAULT = OrbConfig()
VARIANTS = {
    "orb (default)": DEFAULT,
    "no polish": replace(DEFAULT, refine=None),
    "ECC polish": replace(DEFAULT, refine="ecc"),
    "RANSAC": replace(DEFAULT, method="ransac"),
    "1000 features": replace(DEFAULT, n_features=1000),
    "3 pyramid levels": replace(DEFAULT, n_levels=3),
    "FAST threshold 20": replace(DEFAULT, fast_threshold=20),
}
BASELINE = "baseline (paper)"


def load_baseline_step():
    path = Path(__file__).with_name("baseline_orb.py")
    spec = importlib.util.spec_from_file_location("baseline_orb", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.estimate


def run_baseline(frames, full_size, estimate):
    """The baseline's per-pair step on the same frames, scaled up as its script does."""
    orb = cv2.ORB_create(nfeatures=500, WTA_K=2)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    s = full_size[0] / frames[0].shape[1]
    up, down = np.diag([s, s, 1.0]), np.diag([1 / s, 1 / s, 1.0])
    out = []
    for prev, cur in zip(frames, frames[1:]):
        H, _ = estimate(prev, cur, orb, matcher)
        out.append(up @ H @ down)
    return np.array(out)


def run_variant(frames, full_size, config, work_width):
    est = OrbEstimator(work_width, config)
    est.reset(full_size)
    out = []
    for frame in frames:
        out += est.feed(frame)
    return np.array([e.H for e in out])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("flights", nargs="+")
    parser.add_argument("--work-width", type=int, default=320)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    baseline_step = load_baseline_step()
    names = [BASELINE] + list(VARIANTS)
    results: dict[str, dict[str, dict]] = {name: {} for name in names}
    for flight in args.flights:
        gt = load_ground_truth(ground_truth_path(flight))
        with open_video(flight, width=args.work_width, gray=True) as stream:
            frames = list(stream)
            full_size = stream.info.source_size
        for name in names:
            start = time.process_time()
            if name == BASELINE:
                pairwise = run_baseline(frames, full_size, baseline_step)
            else:
                pairwise = run_variant(frames, full_size, VARIANTS[name], args.work_width)
            ms = 1000 * (time.process_time() - start) / len(frames)
            metrics = evaluate(pairwise, gt)
            metrics["cpu_ms_per_frame"] = ms
            results[name][Path(flight).stem] = metrics
            print(f"{Path(flight).stem:20s} {name:18s} MACE {metrics['mace']:6.2f}  corner {metrics['corner_error']:5.2f}  "
                  f"fail {100 * metrics['failure_rate']:4.1f}%  {ms:5.1f} CPU ms/frame", flush=True)
    print()
    print("| variant | mean MACE | median MACE | median corner error | failures | CPU ms/frame (median) |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    summary = {}
    for name in names:
        rows = list(results[name].values())
        summary[name] = {
            "mean_mace": float(np.mean([r["mace"] for r in rows])),
            "median_mace": float(np.median([r["mace"] for r in rows])),
            "median_corner_error": float(np.median([r["corner_error"] for r in rows])),
            "failure_rate": float(np.mean([r["failure_rate"] for r in rows])),
            "median_cpu_ms_per_frame": float(np.median([r["cpu_ms_per_frame"] for r in rows])),
        }
        s = summary[name]
        print(f"| {name} | {s['mean_mace']:.2f} | {s['median_mace']:.2f} | {s['median_corner_error']:.2f} | "
              f"{100 * s['failure_rate']:.2f}% | {s['median_cpu_ms_per_frame']:.1f} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": summary, "per_flight": results}, indent=1))


if __name__ == "__main__":
    main()
