"""The before/after picture of `stabilize --rolling-shutter` (docs/rolling_shutter_before_after.jpg).

A still cannot show wobble, so each panel is a time slice: one row of the video (near the top,
then near the bottom of the frame) taken from every frame and stacked downwards, time running
down.  Ground that the video holds steady draws smooth lines; a frame-to-frame jitter draws
ragged ones.  The input is ragged everywhere; `--rolling-shutter off` (one warp per frame) takes
out what the whole frame shares but leaves each row's own vibration; `auto` (the default) smooths both.

    python scripts/make_rolling_shutter_figure.py [--map PHOTO] [--out docs/rolling_shutter_before_after.jpg]

It paints a grid of straight lines on the map (the Zoo orthophoto of ../shared/data when there,
else a procedural map) and runs, in a temporary folder:
    mosaic simulate grid.png -p paper -n 90 --size 960x540 --seed 3 --rolling-shutter 0.9 --vibration 8,5 -o rs.mp4
    mosaic stabilize rs.mp4 off.mp4 --rolling-shutter off
    mosaic stabilize rs.mp4 auto.mp4
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MAP = ROOT.parent / "shared" / "data" / "aerial_stills" / "odm_orthomosaic_previews" / "zoo.png"
ROWS, COLUMNS, SCALE = (70, 470), slice(330, 630), (2, 3)  # rows sliced; the columns kept; zoom (x, time)


def _grid_map(photo: Path | None, out: Path) -> None:
    """The map with straight lines painted on it every 96 px (a procedural map without ``photo``)."""
    from mosaic_cli.simulate import load_map

    ground = cv2.cvtColor(load_map(str(photo) if photo else None, seed=3), cv2.COLOR_RGB2BGR)
    ground = cv2.resize(ground, (2400, round(2400 * ground.shape[0] / ground.shape[1])), interpolation=cv2.INTER_CUBIC)
    h, w = ground.shape[:2]
    for k in range(48, max(h, w) - 48, 96):
        cv2.line(ground, (k, 48), (k, h - 48), (0, 220, 255), 3)
        cv2.line(ground, (48, k), (w - 48, k), (0, 220, 255), 3)
    cv2.imwrite(str(out), ground)


def _slices(video: Path, label: str) -> np.ndarray:
    capture = cv2.VideoCapture(str(video))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    parts = []
    for y in ROWS:
        cut = np.stack([f[y, COLUMNS] for f in frames])  # (time, width, 3)
        parts.append(cv2.resize(cut, (cut.shape[1] * SCALE[0], cut.shape[0] * SCALE[1]), interpolation=cv2.INTER_NEAREST))
        parts.append(np.full((6, parts[-1].shape[1], 3), 255, np.uint8))
    column = np.vstack([np.zeros((30, parts[0].shape[1], 3), np.uint8), *parts[:-1]])
    cv2.putText(column, label, (8, 21), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return column


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--map", type=Path, default=DEFAULT_MAP if DEFAULT_MAP.is_file() else None)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "rolling_shutter_before_after.jpg")
    args = parser.parse_args()
    mosaic = [sys.executable, "-m", "mosaic_cli"]
    with tempfile.TemporaryDirectory() as work:
        grid, rs, off, auto = (Path(work) / name for name in ("grid.png", "rs.mp4", "off.mp4", "auto.mp4"))
        _grid_map(args.map, grid)
        subprocess.run([*mosaic, "simulate", str(grid), "-p", "paper", "-n", "90", "--size", "960x540", "--seed", "3",
                        "--rolling-shutter", "0.9", "--vibration", "8,5", "-o", str(rs), "-q"], check=True)
        subprocess.run([*mosaic, "stabilize", str(rs), str(off), "--rolling-shutter", "off", "-q"], check=True)
        subprocess.run([*mosaic, "stabilize", str(rs), str(auto), "-q"], check=True)
        columns = [_slices(rs, "input"), _slices(off, "--rolling-shutter off"), _slices(auto, "default (auto)")]
    gap = np.full((columns[0].shape[0], 8, 3), 255, np.uint8)
    figure = np.hstack([columns[0], gap, columns[1], gap, columns[2]])
    figure = cv2.resize(figure, (1200, round(1200 * figure.shape[0] / figure.shape[1])), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(args.out), figure, [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(args.out)


if __name__ == "__main__":
    main()
