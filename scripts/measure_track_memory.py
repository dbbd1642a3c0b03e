#!/usr/bin/env python3
"""Peak memory of ``mosaic track`` as the clip grows: it should not grow with the length.

Renders a short simulated flight, makes longer clips by looping it inside ffmpeg (no
re-encoding), runs ``mosaic track`` on each in a child process and reports the child's peak
resident memory (``os.wait4`` rusage) and ms per frame.

    python scripts/measure_track_memory.py                       # 300 vs 3000 frames at 640x360
    python scripts/measure_track_memory.py --lengths 300 3000 --size 1280x720 --workdir /tmp/mem
    python scripts/measure_track_memory.py --overlays all --workdir /tmp/mem-overlays  # a logo, a timestamp, letterbox bars
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

import imageio_ffmpeg


def run_child(cmd: list[str]) -> tuple[float, float]:
    """(peak RSS in MiB, wall seconds) of one child process."""
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    err = proc.stderr.read().decode() if proc.stderr else ""
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {err.strip()}")
    return usage.ru_maxrss / 1024.0, wall  # ru_maxrss is in KiB on Linux


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lengths", type=int, nargs="+", default=[300, 3000])
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--estimator", default="orb")
    parser.add_argument("--workdir", default=None, help="keep the clips here (default: a temporary folder)")
    parser.add_argument("--overlays", default=None, help="burn these into the flight (mosaic simulate --overlays; use its own --workdir)")
    parser.add_argument("--no-overlay-detect", action="store_true", help="track with overlay detection off")
    args = parser.parse_args()

    work = Path(args.workdir or tempfile.mkdtemp(prefix="mosaic-mem-"))
    work.mkdir(parents=True, exist_ok=True)
    base_len = min(args.lengths)
    base = work / f"flight_{base_len}.mp4"
    if not base.exists():
        subprocess.run([sys.executable, "-m", "mosaic_cli", "simulate", "-o", str(base), "-n", str(base_len),
                        "--size", args.size, "--preset", "veryfast", "-q"] + (["--overlays", args.overlays] if args.overlays else []),
                       check=True)
    rows = []
    for n in args.lengths:
        clip = work / f"flight_{n}.mp4"
        if not clip.exists():
            loops = -(-n // base_len) - 1
            subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-loglevel", "error", "-y",
                            "-stream_loop", str(loops), "-i", str(base), "-frames:v", str(n), "-c", "copy", str(clip)], check=True)
        out = work / f"track_{n}.json"
        rss, wall = run_child([sys.executable, "-m", "mosaic_cli", "track", str(clip), "-o", str(out),
                               "--estimator", args.estimator, "-q"] + (["--no-overlay-detect"] if args.no_overlay_detect else []))
        track = json.loads(out.read_text())
        rows.append({"frames": track["frames"], "peak_rss_mib": round(rss, 1), "wall_s": round(wall, 1),
                     "ms_per_frame": round(track["meta"]["ms_per_frame"], 2)})
        print(f"{track['frames']:6d} frames  peak RSS {rss:7.1f} MiB  {wall:6.1f} s  {track['meta']['ms_per_frame']:.2f} ms/frame", flush=True)
    first, last = rows[0], rows[-1]
    growth = last["peak_rss_mib"] / first["peak_rss_mib"] - 1
    print(f"peak RSS {first['frames']} -> {last['frames']} frames: {100 * growth:+.1f}%")
    print(json.dumps({"size": args.size, "estimator": args.estimator, "runs": rows, "growth": growth}))


if __name__ == "__main__":
    main()
