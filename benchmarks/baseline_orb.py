"""The paper's classical baseline written on its own, to check ``mosaic track --estimator orb``
against: ORB (500 features, WTA_K=2) on the whole grayscale frame resized to the working width
(320x180 for 1280x720 video), brute-force Hamming matching with cross-check, findHomography
with RANSAC at 5 px, identity on failure; the small-frame homography is scaled to full
resolution as the authors' code does, H_full = diag(s, s, 1) H_small diag(1/s, 1/s, 1).

Deliberately independent of mosaic_cli (nothing here imports it; OpenCV decodes the video), so that agreement means
something.  Writes the ``mosaic track`` JSON format, which ``mosaic eval`` reads.

    python -m benchmarks estimators orb-baseline flight.mp4 -o baseline.json [--work-width 320]
"""

from __future__ import annotations

import json
import time

import cv2
import numpy as np

from benchmarks.common import make_parser

SUITE = "estimators"


def estimate(prev, cur, orb, matcher):
    kp1, d1 = orb.detectAndCompute(prev, None)
    kp2, d2 = orb.detectAndCompute(cur, None)
    if d1 is None or d2 is None or len(kp1) < 4 or len(kp2) < 4:
        return np.eye(3), 0.0
    matches = matcher.match(d1, d2)
    if len(matches) < 4:
        return np.eye(3), 0.0
    src = np.float32([kp1[m.queryIdx].pt for m in matches])
    dst = np.float32([kp2[m.trainIdx].pt for m in matches])
    H, mask = cv2.findHomography(src, dst, cv2.RANSAC, 5.0)
    if H is None or not np.all(np.isfinite(H)):
        return np.eye(3), 0.0
    return H, float(mask.sum()) / len(matches)


def track_baseline(video: str, work_width: int = 320, max_frames: int | None = None) -> dict:
    """The baseline over a whole video, as a ``mosaic track`` JSON document."""
    cap = cv2.VideoCapture(video)
    if not cap.isOpened():
        raise SystemExit(f"cannot open {video}")
    orb = cv2.ORB_create(nfeatures=500, WTA_K=2)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    pairwise, confidence = [], []
    prev = size = None
    n = 0
    start = time.perf_counter()
    while max_frames is None or n < max_frames:
        ok, frame = cap.read()
        if not ok:
            break
        n += 1
        if size is None:
            size = (frame.shape[1], frame.shape[0])
            small = (work_width, int(round(size[1] * work_width / size[0])))
            s = size[0] / small[0]
            up, down = np.diag([s, s, 1.0]), np.diag([1 / s, 1 / s, 1.0])
        gray = cv2.resize(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), small, interpolation=cv2.INTER_AREA)
        if prev is not None:
            H, c = estimate(prev, gray, orb, matcher)
            H = up @ H @ down
            pairwise.append((H / H[2, 2]).tolist())
            confidence.append(c)
        prev = gray
    elapsed = time.perf_counter() - start
    return {
        "version": 1, "frames": n, "size": list(size), "fps": cap.get(cv2.CAP_PROP_FPS) or 30.0,
        "estimator": "baseline-orb2-ransac", "direction": "t_to_t+1", "pairwise": pairwise, "confidence": confidence,
        "meta": {"ms_per_frame": 1000 * elapsed / max(n, 1), "work_width": work_width},
    }


def main(argv: list[str] | None = None) -> int | None:
    """The paper's classical baseline, independent of mosaic_cli: a video's track to check ``orb`` against."""
    parser = make_parser(SUITE, "orb-baseline", __doc__)
    parser.add_argument("video")
    parser.add_argument("-o", "--out", required=True)
    parser.add_argument("--work-width", type=int, default=320)
    parser.add_argument("--max-frames", type=int, default=None)
    args = parser.parse_args(argv)
    out = track_baseline(args.video, args.work_width, args.max_frames)
    with open(args.out, "w") as fh:
        json.dump(out, fh)
    print(f"{out['frames']} frames, {out['meta']['ms_per_frame']:.1f} ms/frame -> {args.out}")
