#!/usr/bin/env python
"""Perspective (pitch and roll) shake: the stabiliser's motion models side by side, planning only.

Each clip is a simulated flight over a map held out of the learned estimator's training
(models/README.md: the Boruszyn orthomosaic, the NEON YELL 541000 tile, SOAP_061; and the
procedural map), flown with the ``shaky-tilt`` profile (3-8 Hz shake with pitch and roll of up
to 0.3 degrees) and with ``shaky`` (the same in-plane shake, no pitch or roll), exact ground
truth.  Each clip is tracked once with the estimator (default: stabilize's), and the L1 path is
planned from that track with each model:

* ``similarity`` (the default before), ``homography``, ``tilt`` (the default now: a similarity
  plus the perspective shake where the estimates support it);
* ``tilt, always``: the tilt model with its gate open everywhere (support forced to 1), to
  show what the gate is for;
* ``tilt, exact motion``: the tilt model planned from the exact motion, the floor the
  estimates' errors keep the others above.

Scores (mosaic_cli/stabilize/metrics.py), from the exact warps: residual jitter against the
known jitter-free path as a share of the input's (``ground_truth_jitter``), cropping ratio
(mean) and distortion (worst frame), Liu et al. 2013.

    python scripts/bench_perspective.py                          # 4 maps x 2 seeds x 2 profiles, 640x360, 240 frames
    python scripts/bench_perspective.py --seeds 1 --frames 150   # a quick look
    python scripts/bench_perspective.py --seeds 1 --profiles "" --tilt 0.05,0.1,0.15   # weaker pitch and roll shake
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from mosaic_cli.estimators import DEFAULT_ESTIMATOR, plan_estimator
from mosaic_cli.simulate import PROFILES, load_ground_truth, load_map, plan_flight, write_flight
from mosaic_cli.stabilize import smoothing
from mosaic_cli.stabilize.crop import output_warps
from mosaic_cli.stabilize.metrics import cropping_ratio, distortion, ground_truth_jitter
from mosaic_cli.stabilize.path import camera_motion, motion_model
from mosaic_cli.stabilize.pipeline import WORK_WIDTH, StabilizeOptions
from mosaic_cli.track import track_video

STILLS = Path(__file__).resolve().parents[2] / "shared" / "data" / "aerial_stills"
HELD_OUT = {
    "boruszyn": "odm_orthomosaic_previews/boruszyn.png",
    "yell541": "deepforest_neon_orthophoto/2019_YELL_2_541000_4977000_image_crop.png",
    "soap061": "deepforest_neon_orthophoto/SOAP_061.png",
    "procedural": None,
}
METHODS = ("similarity", "homography", "tilt", "tilt, always", "tilt, exact motion")


def make_clip(folder: Path, name: str, profile: str, seed: int, frames: int, size: tuple[int, int]) -> Path:
    clip = folder / f"{name}_{profile}_s{seed}_{frames}f_{size[0]}x{size[1]}.mp4"
    if not clip.exists() or not clip.with_suffix(".gt.json").exists():
        path = HELD_OUT[name]
        rgb = load_map(None if path is None else STILLS / path, seed=seed)
        plan = plan_flight((rgb.shape[1], rgb.shape[0]), profile, frames, size, seed)
        write_flight(clip, rgb, plan, map_name=name, show_progress=False)
    return clip


def plan_warps(pairwise: np.ndarray, confidence, size, model_name: str) -> np.ndarray:
    model = motion_model(model_name)
    motion = camera_motion(pairwise, size, model, confidence)
    return output_warps(smoothing.L1Smoother().smooth(motion, size, model, None), size)


def always_supported(pairwise, confidence, size) -> np.ndarray:
    """The tilt model with the gate open: every window believes its perspective terms."""
    original = smoothing.perspective_support
    smoothing.perspective_support = lambda motion: 1.0
    try:
        return plan_warps(pairwise, confidence, size, "tilt")
    finally:
        smoothing.perspective_support = original


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--maps", default=",".join(HELD_OUT), help=f"comma-separated, of {', '.join(HELD_OUT)}")
    parser.add_argument("--profiles", default="shaky-tilt,shaky")
    parser.add_argument("--tilt", default="", help="also shaky-tilt flights with these pitch and roll amplitudes (degrees, comma-separated)")
    parser.add_argument("--seeds", type=int, default=2, help="flights per map and profile (seeds 1, 2, ...)")
    parser.add_argument("--frames", type=int, default=240)
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--estimator", default=None, help="default: stabilize's")
    parser.add_argument("--out", type=Path, default=Path(".dev/bench_perspective"), help="working folder (clips are cached)")
    args = parser.parse_args()
    print("command:", shlex.join([sys.executable, *sys.argv]))
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
    size = tuple(int(v) for v in args.size.lower().split("x"))
    profiles = [p for p in args.profiles.split(",") if p]
    for deg in (float(v) for v in args.tilt.split(",") if v):
        name = f"shaky-tilt-{deg:g}"  # the shaky-tilt profile with another amplitude (this run only)
        PROFILES[name] = replace(PROFILES["shaky-tilt"], name=name, jitter_tilt_deg=deg)
        profiles.append(name)
    args.out.mkdir(parents=True, exist_ok=True)
    options = StabilizeOptions(estimator=args.estimator)
    build = plan_estimator(options.estimator, work_width=None, weights=None, device="cpu", default_width=WORK_WIDTH)
    rows: list[tuple[str, str, str, float, float, float]] = []  # profile, clip, method, ratio, cropping, distortion
    header = f"{'profile':<11} {'clip':<16} {'input px':>8} " + " ".join(f"{m:>20}" for m in METHODS)
    print("gt jitter ratio / cropping / distortion per method")
    print(header)
    for profile in profiles:
        for name in args.maps.split(","):
            for seed in range(1, args.seeds + 1):
                clip = make_clip(args.out, name, profile, seed, args.frames, size)
                gt = load_ground_truth(clip.with_suffix(".gt.json"))
                track = track_video(clip, build(), show_progress=False)
                base = ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, gt.size, gt.fps)
                cells = []
                for method in METHODS:
                    if method == "tilt, always":
                        warps = always_supported(track.pairwise, track.confidence, gt.size)
                    elif method == "tilt, exact motion":
                        warps = plan_warps(gt.pairwise, None, gt.size, "tilt")
                    else:
                        warps = plan_warps(track.pairwise, track.confidence, gt.size, method)
                    ratio = ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, gt.size, gt.fps, warps) / base
                    row = (profile, f"{name} s{seed}", method, ratio, cropping_ratio(warps, gt.size), distortion(warps, gt.size))
                    rows.append(row)
                    cells.append(f"{row[3]:.3f}/{row[4]:.3f}/{row[5]:.3f}")
                print(f"{profile:<11} {name + ' s' + str(seed):<16} {base:>8.2f} " + " ".join(f"{c:>20}" for c in cells), flush=True)

    print(f"\nestimator: {options.estimator or DEFAULT_ESTIMATOR}, cpus: {os.cpu_count()}")
    print("\nmedian (min-max) over the clips, as Markdown:\n")
    print("| profile | method | gt jitter ratio | cropping | distortion (worst) |")
    print("|---|---|---|---|---|")
    for profile in profiles:
        for method in METHODS:
            sel = np.array([r[3:] for r in rows if r[0] == profile and r[2] == method])
            if not len(sel):
                continue
            ratio, crop, dist = sel.T
            print(
                f"| {profile} | {method} | {np.median(ratio):.3f} ({ratio.min():.3f}-{ratio.max():.3f}) | "
                f"{np.median(crop):.3f} ({crop.min():.3f}-{crop.max():.3f}) | {dist.min():.3f} |"
            )


if __name__ == "__main__":
    main()
