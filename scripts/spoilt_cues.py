#!/usr/bin/env python3
"""What a spoilt frame looks like to the carry head: on encoded flights, and as training makes it.

    python scripts/spoilt_cues.py FLIGHTS_DIR --clip RUN_DIR/cache/CLIP.npy [--noise 2 1 0.5]

For the centre patch of the working frame (320x180, as the estimator reads it): the median
contrast (standard deviation, [-1, 1] units) and log mean gradient of the glare, dark and flat
frames of each flight with bursts in FLIGHTS_DIR (their ``.gt.json`` names them), and the same
of a cached training clip's frames spoilt by ``mosaic_cli.train.bursts.spoil`` at the low and
high ends of each kind's level, for each training noise (gray levels at the working size,
``mosaic train --carry-noise``).  models/README.md, "The carry head", runs 15 and 16.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import torch

from mosaic_cli.model.checkpoint import DEFAULT_WORK_SIZE
from mosaic_cli.train.bursts import DARK, FLAT, GLARE, LEVELS, spoil

KINDS = {"glare": GLARE, "dark": DARK, "flat": FLAT}
PATCH = 128


def cues(patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, P, P) in [-1, 1] -> contrast (n,), log mean gradient (n,)."""
    gy, gx = np.gradient(patches, axis=(1, 2))
    return patches.std(axis=(1, 2)), np.log(np.abs(gx).mean((1, 2)) + np.abs(gy).mean((1, 2)) + 1e-6)


def centre(frame: np.ndarray) -> np.ndarray:
    w, h = DEFAULT_WORK_SIZE
    x, y = (w - PATCH) // 2, (h - PATCH) // 2
    return frame[y : y + PATCH, x : x + PATCH].astype(np.float32) / 127.5 - 1.0


def flight_patches(folder: Path) -> dict[str, list[np.ndarray]]:
    out: dict[str, list[np.ndarray]] = {k: [] for k in KINDS}
    for video in sorted(folder.glob("*.mp4")):
        truth = video.with_suffix(".gt.json")
        if not truth.is_file():
            continue
        kinds = {b["frame"]: b["kind"] for b in json.loads(truth.read_text()).get("bursts", [])}
        capture, t = cv2.VideoCapture(str(video)), 0
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            if kinds.get(t) in KINDS:
                gray = cv2.resize(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), DEFAULT_WORK_SIZE, interpolation=cv2.INTER_AREA)
                out[kinds[t]].append(centre(gray))
            t += 1
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("flights", type=Path)
    ap.add_argument("--clip", type=Path, required=True, help="a training run's cached clip (RUN_DIR/cache/*.npy)")
    ap.add_argument("--noise", type=float, nargs="+", default=[2.0, 1.0])
    args = ap.parse_args()
    print(f"{'':28} {'frames':>6} {'contrast':>9} {'log grad':>9}")
    for kind, patches in flight_patches(args.flights).items():
        if patches:
            contrast, grad = cues(np.stack(patches))
            print(f"flights {kind:20} {len(patches):6d} {np.median(contrast):9.4f} {np.median(grad):9.2f}")
    frames = torch.from_numpy(np.array(np.load(args.clip, mmap_mode="r")[:64]))[None, :, None].float() / 127.5 - 1.0
    n = frames.shape[1]
    for noise in args.noise:
        for kind, code in KINDS.items():
            for level in LEVELS[code]:
                spoilt = spoil(frames, torch.full((1, n), code), torch.full((1, n), level), torch.zeros(1, n),
                               generator=torch.Generator().manual_seed(0), noise=noise / 127.5)
                contrast, grad = cues(np.stack([centre(((f + 1) * 127.5).numpy()) for f in spoilt[0, :, 0]]))
                label = f"train {kind} {level:g}, noise {noise:g}"
                print(f"{label:28} {n:6d} {np.median(contrast):9.4f} {np.median(grad):9.2f}")


if __name__ == "__main__":
    main()
