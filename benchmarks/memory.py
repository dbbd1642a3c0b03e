"""Memory: the peak memory of ``mosaic track`` and ``mosaic stabilize`` as the clip grows (it should not grow with the length)."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import imageio_ffmpeg

from benchmarks.common import decoded_count, make_parser, run_commands

SUITE = "memory"


# Linux keeps a process's peak RSS across exec, and a child forked (or vforked) from this process
# starts from this process's own peak: a stitch started after a survey of 504 photos was made
# here read 9.6 GB where it held 1.7.  A small launcher process starts the command instead, so
# that the figure is the command's alone.
_LAUNCHER = """
import os, subprocess, sys
child = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL)
_, status, usage = os.wait4(child.pid, 0)
print(usage.ru_maxrss, flush=True)
sys.exit(os.waitstatus_to_exitcode(status) & 0xFF)
"""


def run_child(cmd: list[str], keep_stderr: bool = False):
    """(peak RSS in MiB, wall seconds) of one child process, and its stderr with ``keep_stderr``."""
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", _LAUNCHER, *cmd], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out, err_bytes = proc.communicate()  # stderr drained as it comes: a full pipe would stall the child
    wall = time.perf_counter() - start
    err = err_bytes.decode("utf-8", "replace")
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {err.strip()[-2000:]}")
    peak = int(out.split()[-1]) / 1024.0  # ru_maxrss is in KiB on Linux
    return (peak, wall, err) if keep_stderr else (peak, wall)


def looped_clips(base: Path, lengths: list[int], name: str) -> list[tuple[int, Path]]:
    """Clips of each of ``lengths`` frames made from ``base`` (the shortest) by looping it inside
    ffmpeg (no re-encoding), beside it: ``name`` with the length filled in."""
    base_len = min(lengths)
    clips = []
    for n in lengths:
        clip = base.with_name(name.format(n))
        if not clip.exists():
            loops = -(-n // base_len) - 1
            subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-loglevel", "error", "-y",
                            "-stream_loop", str(loops), "-i", str(base), "-frames:v", str(n), "-c", "copy", str(clip)], check=True)
        clips.append((n, clip))
    return clips


# -- python -m benchmarks memory track -------------------------------------------------------------


def track_command(argv: list[str] | None = None) -> int | None:
    """Peak memory of ``mosaic track`` as the clip grows: it should not grow with the length.

    Renders a short simulated flight, makes longer clips by looping it inside ffmpeg (no
    re-encoding), runs ``mosaic track`` on each in a child process and reports the child's peak
    resident memory (``os.wait4`` rusage) and ms per frame.

        python -m benchmarks memory track                       # 300 vs 3000 frames at 640x360
        python -m benchmarks memory track --lengths 300 3000 --size 1280x720 --workdir /tmp/mem
        python -m benchmarks memory track --overlays all --workdir /tmp/mem-overlays  # a logo, a timestamp, letterbox bars
    """
    parser = make_parser(SUITE, 'track', track_command.__doc__)
    parser.add_argument("--lengths", type=int, nargs="+", default=[300, 3000])
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--estimator", default="orb")
    parser.add_argument("--workdir", default=None, help="keep the clips here (default: a temporary folder)")
    parser.add_argument("--overlays", default=None, help="burn these into the flight (mosaic simulate --overlays; use its own --workdir)")
    parser.add_argument("--no-overlay-detect", action="store_true", help="track with overlay detection off")
    args = parser.parse_args(argv)

    work = Path(args.workdir or tempfile.mkdtemp(prefix="mosaic-mem-"))
    work.mkdir(parents=True, exist_ok=True)
    base_len = min(args.lengths)
    base = work / f"flight_{base_len}.mp4"
    if not base.exists():
        subprocess.run([sys.executable, "-m", "mosaic_cli", "simulate", "-o", str(base), "-n", str(base_len),
                        "--size", args.size, "--preset", "veryfast", "-q"] + (["--overlays", args.overlays] if args.overlays else []),
                       check=True)
    rows = []
    for n, clip in looped_clips(base, args.lengths, "flight_{}.mp4"):
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


# -- python -m benchmarks memory stabilize ---------------------------------------------------------


def stabilize_command(argv: list[str] | None = None) -> int | None:
    """Peak memory of ``mosaic stabilize`` as the clip grows, with and without ``-q``: it should
    not grow with the length.

    Renders a short shaky simulated flight, makes longer clips by looping it inside ffmpeg (no
    re-encoding), runs ``mosaic stabilize`` on each in a child process, with progress and summary
    (stderr to a pipe) and with ``-q``, and reports the child's peak resident memory
    (``os.wait4`` rusage), its wall time and the output's frame count (decoded by OpenCV).

        python -m benchmarks memory stabilize                          # 1000 vs 10000 frames at 320x180
        python -m benchmarks memory stabilize --lengths 1000 10000 --size 852x480 --workdir /tmp/mem
    """
    parser = make_parser(SUITE, 'stabilize', stabilize_command.__doc__)
    parser.add_argument("--lengths", type=int, nargs="+", default=[1000, 10000])
    parser.add_argument("--size", default="320x180")
    parser.add_argument("--estimator", default=None, help="default: mosaic's own default")
    parser.add_argument("--workdir", default=None, help="keep the clips here (default: a temporary folder)")
    args = parser.parse_args(argv)

    work = Path(args.workdir or tempfile.mkdtemp(prefix="mosaic-stabmem-"))
    work.mkdir(parents=True, exist_ok=True)
    base_len = min(args.lengths)
    base = work / f"shaky_{args.size}_{base_len}.mp4"
    if not base.exists():
        subprocess.run([sys.executable, "-m", "mosaic_cli", "simulate", "-o", str(base), "-n", str(base_len),
                        "--profile", "shaky", "--size", args.size, "--preset", "veryfast", "-q"], check=True)
    estimator = ["-e", args.estimator] if args.estimator else []
    rows = []
    for n, clip in looped_clips(base, args.lengths, f"shaky_{args.size}_{{}}.mp4"):
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


COMMANDS = {
    "track": track_command,
    "stabilize": stabilize_command,
}


def main(argv: list[str]) -> int:
    return run_commands(SUITE, __doc__, COMMANDS, argv)
