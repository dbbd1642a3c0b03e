#!/usr/bin/env python3
"""A carry head's gate, pair by pair, over one flight's centre patch (the network alone).

    python scripts/carry_gates.py FLIGHT.mp4 --weights W [--pairs FIRST LAST]

Prints, for each pair in [FIRST, LAST), the gate (the weight of the carried motion), how far the
head's answer lies from its BASE's (mean corner distance, working px) and the x offset of the
BASE's and the head's top-left corner.  The state is carried from the flight's first pair.
models/README.md, "The carry head", runs 9-19.
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np
import torch

from mosaic_cli.model import load_weights
from mosaic_cli.model.checkpoint import DEFAULT_WORK_SIZE


def centre_patches(path: str, patch: int) -> torch.Tensor:
    """(1, n-1, 2, P, P) centre patch pairs of the flight at the working size, in [-1, 1]."""
    capture, crops = cv2.VideoCapture(path), []
    w, h = DEFAULT_WORK_SIZE
    x, y = (w - patch) // 2, (h - patch) // 2
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        gray = cv2.resize(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), DEFAULT_WORK_SIZE, interpolation=cv2.INTER_AREA)
        crops.append(gray[y : y + patch, x : x + patch])
    frames = torch.from_numpy(np.stack(crops)).float() / 127.5 - 1.0
    return torch.stack([frames[:-1], frames[1:]], dim=1)[None]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("flight")
    ap.add_argument("--weights", required=True, help="a carry head's weights")
    ap.add_argument("--pairs", type=int, nargs=2, default=(0, 50), metavar=("FIRST", "LAST"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    net, _ = load_weights(args.weights)
    if net.carry is None:
        raise SystemExit(f"{args.weights} holds a {net.head} network, not a carry head")
    pairs = centre_patches(args.flight, net.config.patch)
    with torch.no_grad():
        flat = pairs.flatten(0, 1)
        features = net.head_inputs(flat, net.features(flat)).unflatten(0, pairs.shape[:2])
        out, _, gate = net.carry_step(features)
        base, _ = net.base_offsets(features[..., : net.config.embed])
    apart = (out - base).unflatten(-1, (4, 2)).norm(dim=-1).mean(-1)
    first, last = args.pairs
    print(f"{'pair':>5} {'gate':>6} {'apart':>7} {'base x':>7} {'head x':>7}")
    for k in range(max(first, 0), min(last, gate.shape[1])):
        print(f"{k:5d} {float(gate[0, k]):6.2f} {float(apart[0, k]):7.2f} {float(base[0, k, 0]):7.2f} {float(out[0, k, 0]):7.2f}")


if __name__ == "__main__":
    main()
