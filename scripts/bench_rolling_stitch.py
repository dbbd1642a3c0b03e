"""Benchmark ``mosaic stitch --rolling-shutter`` on simulated rolling-shutter flights.

For each flight (``mosaic simulate --rolling-shutter R --vibration HZ,PX``, and a global-shutter
one), stitch with ``--rolling-shutter off`` and ``auto`` and score where the panorama drew each
keyframe's row bands against the simulator's truth
(``stabilize.wobble.ground_truth_band_placement``: points along each band's centre row, the
map -> panorama gauge fitted to each panorama); print one table:

* readout: the flight's, and what ``auto`` read;
* band placement, px: RMS (``rms``) and with each keyframe's mean shift taken out (``shape``);
* seconds: wall time of off and auto (the machine may be shared: say so with the figures);
* ``--truth``: also the stitch with the truth's corrections in place of the estimate (each
  band's similarity fitted to the simulator's band -> mid-time homography): what is left when
  the corrections are exact.

    python scripts/bench_rolling_stitch.py --out /tmp/rsstitch [--frames 200] [--size 640x360] [--estimator orb]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import mosaic_cli.stitch.pipeline as stitch_pipeline
from mosaic_cli.estimators import make_estimator
from mosaic_cli.geometry import project
from mosaic_cli.geometry.rolling_shutter import band_centres
from mosaic_cli.simulate import GroundTruth, RollingShutter, SimulateOptions, load_ground_truth, simulate_flight
from mosaic_cli.stabilize.rolling import RollingCorrection
from mosaic_cli.stabilize.wobble import ground_truth_band_placement
from mosaic_cli.stitch import StitchOptions, stitch

# (readout, vibration Hz, vibration px at 1280 wide, profile)
FLIGHTS = [(0.5, 15.0, 3.0, "fast"), (0.7, 12.0, 4.0, "fast"), (0.9, 8.0, 5.0, "fast"), (0.7, 20.0, 3.0, "fast"),
           (0.7, 12.0, 4.0, "paper"), (0.0, 12.0, 4.0, "fast")]


def truth_corrections(gt: GroundTruth) -> RollingCorrection:
    """Each band's correction channels fitted (least squares) to the truth's band -> mid-time homography."""
    assert gt.row_bands is not None
    w, h = gt.size
    K = gt.row_bands.shape[1]
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    out = np.zeros((gt.frames, K, 4))
    xs = np.linspace(0, w - 1, 9)
    for t in range(gt.frames):
        for k, yk in enumerate(band_centres(h, K)):
            p = np.stack([xs, np.full(9, yk)], 1)
            d = project(gt.map_to_frame[t] @ np.linalg.inv(gt.row_bands[t, k]), p) - p
            x, y = p[:, 0] - cx, p[:, 1] - cy
            one, zero = np.ones_like(x), np.zeros_like(x)
            A = np.concatenate([np.stack([one, zero, -y, x], 1), np.stack([zero, one, x, y], 1)])
            out[t, k] = np.linalg.lstsq(A, np.concatenate([d[:, 0], d[:, 1]]), rcond=None)[0]
    return RollingCorrection(gt.readout, out, gt.size, False)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--estimator", default="orb")
    parser.add_argument("--truth", action="store_true", help="also stitch with the truth's corrections")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    head = (f"{'flight':<26} {'R':>4} {'auto':>5} {'keys':>4} | {'rms off':>7} {'auto':>6} {'ratio':>6} | "
            f"{'shape off':>9} {'auto':>6} {'ratio':>6} | {'s off':>6} {'auto':>6}" + (f" | {'rms truth':>9}" if args.truth else ""))
    print(head)
    print("-" * len(head))
    for readout, hz, px, profile in FLIGHTS:
        name = f"{profile} R{readout:g} {hz:g}Hz {px:g}px"
        clip = args.out / f"{profile}_r{readout:g}_{hz:g}hz_{px:g}px_{size[0]}_{args.frames}.mp4"
        if not clip.exists():
            simulate_flight(clip, None, SimulateOptions(profile=profile, frames=args.frames, size=size, seed=args.seed,
                                                        rolling=RollingShutter(readout, hz, px)), show_progress=False)
        gt = load_ground_truth(clip)
        assert gt.row_bands is not None
        scores = {}
        for mode in ("off", "auto"):
            start = time.perf_counter()
            result = stitch(clip, clip.with_suffix(f".{mode}.png"), make_estimator(args.estimator), StitchOptions(rolling_shutter=mode),
                            show_progress=False)
            seconds = time.perf_counter() - start
            pano = result.panoramas[0]
            score = ground_truth_band_placement(gt.row_bands, gt.map_to_frame, gt.size, pano.transforms, pano.bands)
            rs = result.rolling
            scores[mode] = dict(**score, seconds=seconds, keys=len(pano.transforms), readout=rs.readout if rs is not None else float("nan"))
        truth = ""
        if args.truth and gt.readout > 0:
            plan = stitch_pipeline.plan_rolling
            exact = truth_corrections(gt)
            stitch_pipeline.plan_rolling = lambda *a, exact=exact, **k: exact  # the stitch's one call of it
            try:
                result = stitch(clip, clip.with_suffix(".truth.png"), make_estimator(args.estimator),
                                StitchOptions(rolling_shutter=gt.readout), show_progress=False)
            finally:
                stitch_pipeline.plan_rolling = plan
            pano = result.panoramas[0]
            truth = f" | {ground_truth_band_placement(gt.row_bands, gt.map_to_frame, gt.size, pano.transforms, pano.bands)['rms']:>9.3f}"
        off, auto = scores["off"], scores["auto"]
        print(f"{name:<26} {readout:>4.2f} {auto['readout']:>5.2f} {off['keys']:>4d} | {off['rms']:>7.3f} {auto['rms']:>6.3f} "
              f"{auto['rms'] / off['rms']:>6.3f} | {off['shape']:>9.3f} {auto['shape']:>6.3f} {auto['shape'] / off['shape']:>6.3f} | "
              f"{off['seconds']:>6.1f} {auto['seconds']:>6.1f}" + truth, flush=True)


if __name__ == "__main__":
    main()
