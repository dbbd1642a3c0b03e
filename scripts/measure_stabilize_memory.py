#!/usr/bin/env python3
"""Peak memory of ``mosaic stabilize`` as the clip grows, with and without ``-q``: it should
not grow with the length.

Renders a short shaky simulated flight, makes longer clips by looping it inside ffmpeg (no
re-encoding), runs ``mosaic stabilize`` on each in a child process, with progress and summary
(stderr to a pipe) and with ``-q``, and reports the child's peak resident memory
(``os.wait4`` rusage), its wall time and the output's frame count (decoded by OpenCV).

    python scripts/measure_stabilize_memory.py                          # 1000 vs 10000 frames at 320x180
    python scripts/measure_stabilize_memory.py --lengths 1000 10000 --size 852x480 --workdir /tmp/mem
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import imageio_ffmpeg


def run_child(cmd: list[str]) -> tuple[float, float]:
    """(peak RSS in MiB, wall seconds) of one child process."""
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    err = proc.stderr.read().decode("utf-8", "replace")  # drained as it comes: a full pipe would stall the child
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {err.strip()[-2000:]}")
    return usage.ru_maxrss / 1024.0, wall  # ru_maxrss is in KiB on Linux


def decoded_count(path: Path) -> int:
    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    count = 0
    while capture.grab():
        count += 1
    capture.release()
    return count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lengths", type=int, nargs="+", default=[1000, 10000])
    parser.add_argument("--size", default="320x180")
    parser.add_argument("--estimator", default=None, help="default: mosaic's own default")
    parser.add_argument("--workdir", default=None, help="keep the clips here (default: a temporary folder)")
    args = parser.parse_args()

    work = Path(args.workdir or tempfile.mkdtemp(prefix="mosaic-stabmem-"))
    work.mkdir(parents=True, exist_ok=True)
    base_len = min(args.lengths)
    base = work / f"shaky_{args.size}_{base_len}.mp4"
    if not base.exists():
        subprocess.run([sys.executable, "-m", "mosaic_cli", "simulate", "-o", str(base), "-n", str(base_len),
                        "--profile", "shaky", "--size", args.size, "--preset", "veryfast", "-q"], check=True)
    estimator = ["-e", args.estimator] if args.estimator else []
    rows = []
    for n in args.lengths:
        clip = work / f"shaky_{args.size}_{n}.mp4"
        if not clip.exists():
            loops = -(-n // base_len) - 1
            subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-loglevel", "error", "-y",
                            "-stream_loop", str(loops), "-i", str(base), "-frames:v", str(n), "-c", "copy", str(clip)], check=True)
        for quiet in (False, True):
            out = work / f"steady_{n}{'_q' if quiet else ''}.mp4"
            rss, wall = run_child([sys.executable, "-m", "mosaic_cli", "stabilize", str(clip), str(out), *estimator,
                                   *(["-q"] if quiet else [])])
            frames = decoded_count(out)
            rows.append({"frames": n, "quiet": quiet, "output_frames": frames, "peak_rss_mib": round(rss, 1),
                         "wall_s": round(wall, 1)})
            print(f"{n:6d} frames{' -q' if quiet else '   '}  peak RSS {rss:7.1f} MiB  {wall:7.1f} s  output {frames} frames",
                  flush=True)
            out.unlink()
    for quiet in (False, True):
        runs = [r for r in rows if r["quiet"] == quiet]
        first, last = runs[0], runs[-1]
        growth = last["peak_rss_mib"] / first["peak_rss_mib"] - 1
        print(f"{'-q' if quiet else 'progress'}: peak RSS {first['frames']} -> {last['frames']} frames: {100 * growth:+.1f}%")
    print(json.dumps({"size": args.size, "estimator": args.estimator or "default", "runs": rows}))


if __name__ == "__main__":
    main()
