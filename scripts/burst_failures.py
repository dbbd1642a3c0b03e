#!/usr/bin/env python3
"""Which burst pairs an estimator fails, by kind: for every flight with bursts in a folder (X.mp4
with its X.gt.json, made by ``mosaic simulate --bursts`` or ``-p bursts``), the pairs that touch a
burst, failed (corner error over 10 px, 1280x720-equivalent) or not, counted per burst kind, and
each failed pair listed with its error and confidence.

    python scripts/burst_failures.py ../runs/data/dev -e lstm
"""

from __future__ import annotations

import argparse
from collections import defaultdict

import numpy as np

from mosaic_cli.estimators import make_estimator
from mosaic_cli.evaluate import FAILURE_PX, corner_errors
from mosaic_cli.inputs import find_flights
from mosaic_cli.simulate import load_ground_truth
from mosaic_cli.track import track_video


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder")
    ap.add_argument("-e", "--estimator", default="lstm")
    args = ap.parse_args()
    counts: dict[str, list[int]] = defaultdict(lambda: [0, 0])  # kind -> [failed, pairs]
    for video in find_flights(args.folder, "FOLDER"):
        gt = load_ground_truth(video)
        if not gt.bursts:
            continue
        track = track_video(video, make_estimator(args.estimator, device="cpu"), show_progress=False)
        scale = 1280.0 / gt.size[0]
        errors = corner_errors(track.pairwise, np.asarray(gt.pairwise), gt.size) * scale
        touched: dict[int, str] = {}
        for b in gt.bursts:
            t, kind = int(b["frame"]), str(b["kind"])
            for p in ((t - 1,) if kind in ("drop", "duplicate") else (t - 1, t)):
                touched.setdefault(p, kind)
        for p, kind in sorted(touched.items()):
            if 0 <= p < len(errors):
                failed = bool(errors[p] > FAILURE_PX)
                counts[kind][0] += failed
                counts[kind][1] += 1
                if failed:
                    path = track.paths[p] if track.paths else "-"
                    print(f"{video.stem} pair {p} ({kind}): {errors[p]:.1f} px, confidence {track.confidence[p]:.2f}, {path}")
    for kind, (failed, pairs) in sorted(counts.items()):
        print(f"{kind:10s} {failed:3d} of {pairs:3d} burst pairs failed")


if __name__ == "__main__":
    main()
