#!/usr/bin/env python
"""Each speed goal of issue #31 against the least time mosaic's design can take on this machine.

The goals are ratios to ffmpeg (decoding alone, a plain transcode) and to vid.stab.  This script
measures, on one clip and in one run, the CPU seconds of the work a command cannot leave out,
each piece on its own, and adds them up over the machine's cores as if nothing ever waited:

* ``torch``: importing torch (``python -c "import torch"``), which any command with the
  learned estimator pays;
* ``track read``: the tracking's decode, at the estimator's input width, in gray (ffmpeg and
  the pipe, as ``track`` reads);
* ``frames read``: the full-size decode ``stitch`` reads (yuv420p piped; RGB converted only for
  the frames it keeps, so not counted);
* ``estimator``: the default estimator's CPU milliseconds a pair on one thread, on frames held in
  memory (no decode), and the network alone (``lstm:refine=none:fallback=none``), which drops
  the checks that keep the default's failures low;
* ``warp``: stabilize's yuv420p warp of one full-size frame, one thread;
* ``overlays``: overlay detection (its samples' decode and the detector), as the commands run it;
* the transcode's CPU seconds (x264 ``veryfast``, crf 18), which cover the render's decode and
  encode.

Floors (CPU seconds over the cores, no waiting, nothing else on the machine):

* ``track``  = torch + track read + pairs x estimator;
* ``stitch`` = torch + frames read + pairs x estimator (no SIFT, no matching, no writing);
* ``stabilize`` = torch + transcode + frames x warp + pairs x estimator: one decode shared by
  the tracking and the render, which no present design does, and no path planning;
* the overlays' share: the command with ``--no-overlay-detect`` leaves some of the cores idle
  (cores x wall - CPU); the detection's CPU beyond that, over the cores, is the least it adds,
  against the command's wall time plus that.

A floor above its goal's line means no tuning of this design reaches the goal on this machine;
below it, the difference is what the rest of the command (pipes, planning, Python, waiting) may
take at most.

    python scripts/speed_floors.py --clip shaky720.mp4 --clip shaky4k.mp4 --json floors.json
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_speed import FFMPEG, MOSAIC, X264, run_vidstab, warp_cpu_ms  # noqa: E402  (a sibling script)
from bench_speed import run as run_command  # noqa: E402

T = TypeVar("T")
WARM_UP = 40  # frames


def cpu_seconds() -> float:
    """User and system seconds of this process (every thread) and its waited-for children."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def measured(work: Callable[[], T]) -> tuple[float, T]:
    """(CPU seconds, result) of ``work()``."""
    start = cpu_seconds()
    result = work()
    return cpu_seconds() - start, result


def torch_import_cpu() -> float:
    """CPU seconds of a fresh interpreter importing torch, less one that imports nothing."""
    def child(code: str) -> float:
        return measured(lambda: subprocess.run([sys.executable, "-c", code], check=True))[0]

    return child("import torch") - child("pass")


def track_read(clip: Path, input_width: int) -> tuple[float, list]:
    """CPU seconds of reading every frame as ``track`` does, and the frames."""
    from mosaic_cli.video import open_video, probe

    info = probe(clip)

    def read() -> list:
        with open_video(clip, width=input_width, gray=True, info=info) as stream:
            return [frame.copy() for frame in stream]

    return measured(read)


def frames_read_cpu(clip: Path) -> float:
    """CPU seconds of reading every frame at full size as ``stitch`` does (none held): yuv420p
    piped, RGB converted only where its pixels are asked for, which nothing does here."""
    from mosaic_cli.video import open_video, probe

    info = probe(clip)

    def read() -> int:
        with open_video(clip, info=info, lazy_rgb=True) as stream:
            return sum(1 for _ in stream)

    return measured(read)[0]


def estimator_ms(spec: str | None, frames: list, full_size: tuple[int, int]) -> float:
    """CPU milliseconds a pair of the estimator ``spec`` (None: the default), built as the
    commands build it (one torch thread), over ``frames`` held in memory, after a pass over
    the first :data:`WARM_UP` of them."""
    from mosaic_cli.estimators import make_estimator
    from mosaic_cli.estimators.base import estimate_stream

    estimator = make_estimator(spec)
    for _ in estimate_stream(estimator, frames[:WARM_UP], full_size):  # torch's first calls are slower
        pass
    spent, pairs = measured(lambda: sum(1 for _ in estimate_stream(estimator, frames, full_size)))
    return 1000 * spent / max(1, pairs)


def overlays_cpu(clip: Path) -> float:
    """CPU seconds of overlay detection as the commands run it (samples decoded, detector)."""
    from mosaic_cli.overlay import MaskOptions
    from mosaic_cli.overlay.merge import frame_mask

    return measured(lambda: frame_mask(clip, MaskOptions()))[0]


def commands_without_detection(clip: Path, work: Path) -> dict[str, list[str]]:
    """The three commands with their defaults but ``--no-overlay-detect``: how much of the
    machine each leaves idle, which overlay detection can use without adding wall time."""
    out = work / clip.stem
    return {name: [*MOSAIC, name, str(clip), *target, "--no-overlay-detect", "-q"] for name, target in
            (("track", ["-o", f"{out}_track.json"]), ("stitch", ["-o", f"{out}_pano.png"]), ("stabilize", [f"{out}_stable.mp4"]))}


def input_width() -> int:
    from mosaic_cli.estimators import make_estimator

    return make_estimator().input_width


def measure_clip(clip: Path, work: Path, rounds: int, vidstab: bool) -> dict:
    from mosaic_cli.video import probe

    info = probe(clip)
    frames = info.frame_count
    without = list(commands_without_detection(clip, work))
    walls: dict[str, list[float]] = {k: [] for k in ["decode", "transcode", "vid.stab", *without]}
    cpus: dict[str, list[float]] = {k: [] for k in ["transcode", "torch", "track read", "frames read", "estimator",
                                                    "network alone", "warp", "overlays", *without]}
    width = input_width()
    for k in range(rounds):
        walls["decode"].append(run_command([FFMPEG, "-v", "error", "-y", "-i", str(clip), "-f", "null", "-"], work)[0])
        spent, (seconds, _) = measured(lambda: run_command([FFMPEG, "-v", "error", "-y", "-i", str(clip), *X264, "-c:a", "copy",
                                                            str(work / f"{clip.stem}_transcode.mp4")], work))
        walls["transcode"].append(seconds)
        cpus["transcode"].append(spent)
        if vidstab:
            walls["vid.stab"].append(run_vidstab(clip, work))
        cpus["torch"].append(torch_import_cpu())
        spent, held = track_read(clip, width)
        cpus["track read"].append(spent)
        cpus["estimator"].append(estimator_ms(None, held, info.source_size))
        cpus["network alone"].append(estimator_ms("lstm:refine=none:fallback=none", held, info.source_size))
        del held
        cpus["frames read"].append(frames_read_cpu(clip))
        cpus["warp"].append(warp_cpu_ms(clip))
        cpus["overlays"].append(overlays_cpu(clip))
        for command, line in commands_without_detection(clip, work).items():
            spent, (seconds, _) = measured(lambda line=line: run_command(line, work))
            walls[command].append(seconds)
            cpus[command].append(spent)
        print(f"{clip.name}: round {k + 1} of {rounds} done, load {os.getloadavg()[0]:.2f}", file=sys.stderr)
    wall = {k: statistics.median(v) for k, v in walls.items() if v}
    cpu = {k: statistics.median(v) for k, v in cpus.items()}
    return {"size": list(info.source_size), "frames": frames, "input_width": width, "wall": wall, "cpu": cpu,
            "runs": {"wall": walls, "cpu": cpus}, "floors": floors(wall, cpu, frames)}


def floors(wall: dict[str, float], cpu: dict[str, float], frames: int) -> list[dict]:
    """Each goal: its line in seconds and the floor of the work it cannot leave out."""
    cores = os.cpu_count() or 1
    pairs = max(0, frames - 1)
    estimate = pairs * cpu["estimator"] / 1000
    track = (cpu["torch"] + cpu["track read"] + estimate) / cores
    network = (cpu["torch"] + cpu["track read"] + pairs * cpu["network alone"] / 1000) / cores
    stitch = (cpu["torch"] + cpu["frames read"] + estimate) / cores
    stabilize = (cpu["torch"] + cpu["transcode"] + frames * cpu["warp"] / 1000 + estimate) / cores
    rows = [
        ("track within 2.5x of decoding alone", 2.5 * wall["decode"], track),
        ("track, the network alone (no checks)", 2.5 * wall["decode"], network),
        ("stitch within 5x of decoding alone", 5 * wall["decode"], stitch),
        ("stabilize within 1.5x of the transcode", 1.5 * wall["transcode"], stabilize),
    ]
    if "vid.stab" in wall:
        rows.append(("stabilize 2x faster than vid.stab", wall["vid.stab"] / 2, stabilize))
    out = [{"goal": goal, "line_s": line, "floor_s": floor, "reachable": floor <= line} for goal, line, floor in rows]
    for name in ("track", "stitch", "stabilize"):
        # The detection adds no wall time only as far as it fits in what the command leaves idle.
        idle = max(0.0, cores * wall[name] - cpu[name])
        added = max(0.0, cpu["overlays"] - idle) / cores
        share = added / (wall[name] + added)
        out.append({"goal": f"overlays at most 5% of {name}", "line_s": 0.05, "floor_s": share, "reachable": share <= 0.05,
                    "share": True, "idle_cpu_s": idle, "added_s": added})
    return out


def report(clip: Path, result: dict) -> None:
    w, h = result["size"]
    print(f"\n{clip.name}: {w}x{h}, {result['frames']} frames; estimator input {result['input_width']} px wide")
    wall, cpu = result["wall"], result["cpu"]
    print("wall s: " + ", ".join(f"{k} {v:.2f}" for k, v in wall.items()))
    print("without overlay detection: " + ", ".join(f"{k} {wall[k]:.2f} s ({cpu[k]:.2f} s CPU)" for k in ("track", "stitch", "stabilize")))
    print(f"CPU: transcode {cpu['transcode']:.2f} s, torch import {cpu['torch']:.2f} s, track read {cpu['track read']:.2f} s, "
          f"frames read {cpu['frames read']:.2f} s, overlays {cpu['overlays']:.2f} s; estimator {cpu['estimator']:.2f} ms a pair "
          f"(network alone {cpu['network alone']:.2f}), warp {cpu['warp']:.2f} ms a frame")
    print(f"{'goal':<42} {'line':>8} {'floor':>8}  floor/line")
    for row in result["floors"]:
        if row.get("share"):
            print(f"{row['goal']:<42} {100 * row['line_s']:7.1f}% {100 * row['floor_s']:7.1f}%  "
                  f"{row['floor_s'] / row['line_s']:5.2f}  {'reachable' if row['reachable'] else 'out of reach'}")
        else:
            print(f"{row['goal']:<42} {row['line_s']:7.2f}s {row['floor_s']:7.2f}s  "
                  f"{row['floor_s'] / row['line_s']:5.2f}  {'reachable' if row['reachable'] else 'out of reach'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--clip", type=Path, action="append", required=True, help="a clip (repeatable)")
    parser.add_argument("--rounds", type=int, default=2, help="each piece measured this many times; medians")
    parser.add_argument("--work", type=Path, default=Path(".dev/speed_floors"), help="working folder")
    parser.add_argument("--no-vidstab", action="store_true")
    parser.add_argument("--json", type=Path, help="write every figure measured here")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    work = args.work.resolve()
    print("command:", shlex.join([sys.executable, *sys.argv]))
    print(f"cpus: {os.cpu_count()}, load average at start: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    results = {"load_start": os.getloadavg(), "clips": {}}
    for clip in args.clip:
        started = time.perf_counter()
        result = measure_clip(clip.resolve(), work, args.rounds, not args.no_vidstab)
        result["seconds"] = time.perf_counter() - started
        results["clips"][clip.name] = result
        report(clip, result)
    results["load_end"] = os.getloadavg()
    print(f"load average at the end: {' '.join(f'{v:.2f}' for v in results['load_end'])}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
