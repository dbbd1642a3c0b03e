"""The lens pictures of the guides, from `scripts/bench_lens.py`'s outputs:

* docs/lens_before_after.jpg (the stitch guide): the k1 -0.30 survey flight's panorama with
  ``--lens none`` and with the true lens file, side by side;
* docs/lens_stabilize_before_after.jpg (the stabilize guide): one frame of the shaky fisheye
  flight stabilised with ``--lens none`` (the lens's bend left in: the roofs' straight edges
  curve) and with ``--lens auto`` (a pinhole view: straight edges straight).

    python scripts/bench_lens.py --out runs/lens
    python scripts/bench_lens.py --out runs/lens_stabilize --stabilize --frames 90 --flights pinhole,wide-0.30,fisheye
    python scripts/make_lens_figures.py --runs runs/lens --stabilized runs/lens_stabilize
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def labelled(image: np.ndarray, text: str) -> np.ndarray:
    """``image`` (BGR) with ``text`` in a dark band along its top."""
    out = image.copy()
    cv2.rectangle(out, (0, 0), (out.shape[1], 26), (0, 0, 0), -1)
    cv2.putText(out, text, (8, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def side_by_side(images: list[np.ndarray], height: int, gap: int = 8) -> np.ndarray:
    """The images scaled to ``height`` and joined left to right, white between them."""
    scaled = [cv2.resize(i, (round(i.shape[1] * height / i.shape[0]), height), interpolation=cv2.INTER_AREA) for i in images]
    parts: list[np.ndarray] = []
    for k, image in enumerate(scaled):
        if k:
            parts.append(np.full((height, gap, 3), 255, np.uint8))
        parts.append(image)
    return np.hstack(parts)


def on_white(path: Path) -> np.ndarray:
    """A panorama PNG (RGBA: transparent where nothing was seen) over white, BGR."""
    rgba = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if rgba is None:
        raise SystemExit(f"{path}: not found (run scripts/bench_lens.py first)")
    if rgba.shape[2] == 3:
        return rgba
    alpha = rgba[..., 3:].astype(np.float32) / 255.0
    return (rgba[..., :3].astype(np.float32) * alpha + 255.0 * (1.0 - alpha)).astype(np.uint8)


def mean_of_frames(path: Path, first: int, count: int) -> np.ndarray:
    """The mean (BGR) of ``count`` consecutive frames of a video from frame ``first``."""
    capture = cv2.VideoCapture(str(path))
    capture.set(cv2.CAP_PROP_POS_FRAMES, first)
    frames = []
    for _ in range(count):
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame.astype(np.float32))
    capture.release()
    if not frames:
        raise SystemExit(f"{path}: no frames (run scripts/bench_lens.py --stabilize first)")
    return np.clip(np.mean(frames, axis=0) + 0.5, 0, 255).astype(np.uint8)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=Path, default=ROOT / "runs" / "lens", help="bench_lens.py's --out")
    parser.add_argument("--stabilized", type=Path, default=ROOT / "runs" / "lens_stabilize", help="bench_lens.py --stabilize's --out")
    parser.add_argument("--frame", type=int, default=40, help="the stabilised frame shown")
    args = parser.parse_args()

    stitch = side_by_side([labelled(on_white(args.runs / "wide-0.30_none.png"), "--lens none"),
                           labelled(on_white(args.runs / "wide-0.30_file.png"), "--lens (the lens file)")], 320)
    cv2.imwrite(str(ROOT / "docs" / "lens_before_after.jpg"), stitch, [cv2.IMWRITE_JPEG_QUALITY, 88])

    panels = [labelled(mean_of_frames(args.stabilized / f"shaky_fisheye_{option}.mp4", args.frame, 1), f"stabilize --lens {option}")
              for option in ("none", "auto")]
    cv2.imwrite(str(ROOT / "docs" / "lens_stabilize_before_after.jpg"), side_by_side(panels, 360), [cv2.IMWRITE_JPEG_QUALITY, 88])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
