"""The README's before/after still of `mosaic stabilize` (docs/stabilize_before_after.jpg).

A still cannot show shake, so each panel overlays (averages) the same 8 consecutive frames:
the shaky input comes out doubled and blurred, the stabilised output sharp.

    python scripts/make_stabilize_figure.py [--out docs/stabilize_before_after.jpg]

It runs, in a temporary folder:
    mosaic simulate -p shaky -n 90 --size 960x540 --seed 3 -o shaky.mp4
    mosaic stabilize shaky.mp4 stable.mp4
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

FIRST, COUNT, PANEL = 40, 8, (480, 270)


def _frames(path: Path) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            return frames
        frames.append(frame)


def _panel(frames: list[np.ndarray], label: str) -> np.ndarray:
    mean = np.mean([f.astype(np.float32) for f in frames[FIRST : FIRST + COUNT]], axis=0).astype(np.uint8)
    panel = cv2.resize(mean, PANEL, interpolation=cv2.INTER_AREA)
    cv2.rectangle(panel, (0, 0), (PANEL[0], 26), (0, 0, 0), -1)
    cv2.putText(panel, label, (8, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
    return panel


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/stabilize_before_after.jpg"))
    args = parser.parse_args()
    mosaic = [sys.executable, "-m", "mosaic_cli"]
    with tempfile.TemporaryDirectory() as work:
        shaky, stable = Path(work) / "shaky.mp4", Path(work) / "stable.mp4"
        subprocess.run([*mosaic, "simulate", "-p", "shaky", "-n", "90", "--size", "960x540", "--seed", "3", "-o", str(shaky), "-q"], check=True)
        subprocess.run([*mosaic, "stabilize", str(shaky), str(stable), "-q"], check=True)
        before = _panel(_frames(shaky), f"input: {COUNT} frames overlaid")
        after = _panel(_frames(stable), "mosaic stabilize: the same frames")
    gap = np.full((PANEL[1], 6, 3), 255, np.uint8)
    cv2.imwrite(str(args.out), np.hstack([before, gap, after]), [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(args.out)


if __name__ == "__main__":
    main()
