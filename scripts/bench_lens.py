"""Lenses (issue 41, item 5): wide-angle and fisheye flights over a held-out image, stitched with
``--lens none``, the true lens FILE and ``--lens auto``, each panorama fitted to the ground (the
source image) with one homography; and auto's coefficients against the truth at the corners.

    python scripts/bench_lens.py --out runs/lens [--frames 120 --size 640x360 --map boruszyn]

Per flight and lens option: the median residual (px of the panorama) of SIFT matches between the
panorama and the map after one homography (RANSAC 4 px, residuals of the matches within 8 px:
the fit's own spread), the matches within 4 px; for auto, what it estimated, the residual it
saw, the corner error of its lens against the truth (px at the flight's size, and as a share of
the true lens's corner displacement) and its time.  Writes <out>/lens.json and a PNG of each
panorama downscaled beside it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.geometry.lens import corner_displacement, corner_error
from mosaic_cli.geometry.lens_files import read_lens
from mosaic_cli.simulate import SimulateOptions, load_map, parse_lens, simulate_flight
from mosaic_cli.video import probe

STILLS = Path(__file__).resolve().parents[2] / "shared" / "data" / "aerial_stills"
HELD_OUT = {"boruszyn": "odm_orthomosaic_previews/boruszyn.png", "yell541": "deepforest_neon_orthophoto/2019_YELL_2_541000_4977000_image_crop.png"}
# The flights: k1 -0.15 with k2 = k1^2/4 at 900 px (1280 wide); -0.30 at 1050 px (at 900 px
# that polynomial folds back before the corners; 1050 px is 71 degrees across once undistorted);
# an equidistant fisheye 120 degrees across.  Focal lengths scale with the width.
FLIGHTS = {"pinhole": None, "wide-0.15": "-0.15,0.005625,f={f900}", "wide-0.30": "-0.30,0.0225,f={f1050}", "fisheye": "fisheye"}


def ground_fit(panorama: Path, ground: np.ndarray) -> tuple[float, int]:
    """(median residual px, matches within 4 px) of one homography panorama -> ground (SIFT, RANSAC)."""
    pano = cv2.imread(str(panorama), cv2.IMREAD_UNCHANGED)
    gray = cv2.cvtColor(pano[..., :3], cv2.COLOR_BGR2GRAY)
    mask = None if pano.shape[2] < 4 else (pano[..., 3] > 0).astype(np.uint8) * 255
    sift = cv2.SIFT_create(8000)
    ka, da = sift.detectAndCompute(gray, mask)
    kb, db = sift.detectAndCompute(cv2.cvtColor(ground, cv2.COLOR_RGB2GRAY), None)
    pairs = [m for m, n in cv2.BFMatcher().knnMatch(da, db, k=2) if m.distance < 0.75 * n.distance]
    a = np.float64([ka[m.queryIdx].pt for m in pairs])
    b = np.float64([kb[m.trainIdx].pt for m in pairs])
    H, _ = cv2.findHomography(a, b, cv2.RANSAC, 4.0, maxIters=20000, confidence=0.9999)
    # residuals in panorama px: the ground's pixels mapped back
    back = cv2.perspectiveTransform(b.reshape(-1, 1, 2), np.linalg.inv(H)).reshape(-1, 2)
    err = np.linalg.norm(back - a, axis=1)
    return float(np.median(err[err < 8.0])), int(np.sum(err < 4.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("runs/lens"))
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--map", default="boruszyn", choices=sorted(HELD_OUT))
    parser.add_argument("--flights", default=",".join(FLIGHTS))
    args = parser.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    map_path = STILLS / HELD_OUT[args.map]
    ground = load_map(map_path)
    results = []
    for name in args.flights.split(","):
        spec = FLIGHTS[name]
        clip = args.out / f"{name}.mp4"
        if not clip.exists():
            lens = parse_lens(spec.format(f900=900 * w / 1280, f1050=1050 * w / 1280), (w, h)) if spec else None
            simulate_flight(clip, map_path, SimulateOptions(profile="survey", frames=args.frames, size=(w, h), seed=1, lens=lens), show_progress=False)
        gt = clip.with_suffix(".gt.json")
        options = {"none": "none", "auto": "auto"} | ({"file": str(gt)} if spec else {})
        for option, value in options.items():
            pano = args.out / f"{name}_{option}.png"
            clock = time.perf_counter()
            run = subprocess.run([sys.executable, "-m", "mosaic_cli", "stitch", str(clip), "-o", str(pano), "-e", "orb", "--lens", value,
                                  "--no-overlay-detect"], capture_output=True, text=True)
            seconds = time.perf_counter() - clock
            if run.returncode:
                print(name, option, "failed:", run.stderr.strip()[-300:])
                continue
            residual, matches = ground_fit(pano, ground)
            row = {"flight": name, "lens": option, "residual_px": residual, "matches_4px": matches, "stitch_seconds": seconds}
            said = [line for line in run.stdout.splitlines() if line.startswith("lens:")]
            if said:
                row["said"] = said[0]
            if option == "auto":
                from mosaic_cli.estimators.lens import estimate_lens

                choice = estimate_lens(probe(clip))
                row["auto_seconds"] = choice.seconds
                row["auto_applied"] = choice.lens is not None
                if spec and choice.estimate is not None:
                    truth = read_lens(gt)
                    err = corner_error(choice.estimate, truth)
                    row.update(corner_error_px=err, corner_error_share=err / corner_displacement(truth), true_corner_px=corner_displacement(truth))
            small = cv2.imread(str(pano), cv2.IMREAD_UNCHANGED)
            scale = 900.0 / max(small.shape[:2])
            cv2.imwrite(str(pano.with_name(pano.stem + "_small.png")), cv2.resize(small, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA))
            results.append(row)
            print(json.dumps(row), flush=True)
    (args.out / "lens.json").write_text(json.dumps({"map": args.map, "frames": args.frames, "size": [w, h], "results": results}, indent=1))


if __name__ == "__main__":
    main()
