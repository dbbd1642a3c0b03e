#!/usr/bin/env python
"""mosaic's speed against the encoder's floor and vid.stab, per command and stage, in one run.

For each clip (made once with ``mosaic simulate -p shaky`` over a real image of
../shared/data, or given with --clip), in rounds whose order alternates (A-B-B-A), wall times of:

* decode: ``ffmpeg -i clip -f null -`` (the floor of any command that reads every frame);
* transcode: ``ffmpeg -i clip -c:v libx264 -preset veryfast -crf 18`` (the floor of any
  stabiliser that re-encodes);
* vid.stab: ``vidstabdetect`` then ``vidstabtransform`` with the same encoder settings;
* ``mosaic stabilize``, ``mosaic track`` and ``mosaic stitch`` with their defaults, each
  command's own stage times read from its final line, and each again with
  ``--no-overlay-detect``: what overlay detection costs a command is the difference;

then the medians (wall, and CPU seconds of user and system time), the ratios the speed goals are
stated in, with the machine's load average before and after.  Also the start-up: ``mosaic
track`` of a one-frame clip (median of 5); and the floor of any stabiliser that warps every
pixel and re-encodes on this machine: the transcode's CPU seconds plus those of warping every
frame (mosaic's yuv420p warp, one thread), over the cores, before any tracking.

    python scripts/bench_speed.py                       # 1280x720 x 1200 frames and 3840x2160 x 300
    python scripts/bench_speed.py --sizes 720p --rounds 2
    python scripts/bench_speed.py --gop 30              # clips with a keyframe a second
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
from pathlib import Path

import imageio_ffmpeg
from stage_times import stage_seconds  # scripts/, beside this one

FFMPEG = imageio_ffmpeg.get_ffmpeg_exe()
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
# (frame size, frames, loops of a shorter flight, the image flown over, seed)
SIZES = {
    "720p": ((1280, 720), 300, 4, "aerial_stills/odm_orthomosaic_previews/aukerman.png", 3),
    "4k": ((3840, 2160), 300, 1, "aerial_sequences/odm_caliterra/IMG_9356.jpg", 5),
}
MOSAIC = [sys.executable, "-m", "mosaic_cli"]
X264 = ["-c:v", "libx264", "-preset", "veryfast", "-crf", "18", "-pix_fmt", "yuv420p"]


CPU: dict[str, list[float]] = {}  # CPU seconds (user + system) of each method's runs, by method


def run(cmd: list[str], cwd: Path, name: str | None = None) -> tuple[float, str]:
    """(wall seconds, stderr) of one command, which must succeed; its CPU seconds are added to
    ``CPU[name]``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(cmd, cwd=cwd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise SystemExit(f"failed ({done.returncode}): {shlex.join(cmd)}\n{done.stderr[-2000:]}")
    if name is not None:
        CPU.setdefault(name, []).append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    return wall, done.stderr


def make_clip(folder: Path, name: str, gop: int | None) -> Path:
    (w, h), frames, loops, image, seed = SIZES[name]
    clip = folder / f"shaky_{name}{'' if gop is None else f'_g{gop}'}.mp4"
    if clip.exists():
        return clip
    flight = folder / f"flight_{name}.mp4"
    if not flight.exists():
        source = DATA / image
        subprocess.run([*MOSAIC, "simulate", *([str(source)] if source.exists() else []), "-p", "shaky", "-n", str(frames),
                        "--size", f"{w}x{h}", "--seed", str(seed), "-o", str(flight), "-q"], check=True)
    encoded = flight
    if gop is not None:
        encoded = folder / f"flight_{name}_g{gop}.mp4"
        subprocess.run([FFMPEG, "-v", "error", "-y", "-i", str(flight), *X264, "-g", str(gop), str(encoded)], check=True)
    subprocess.run([FFMPEG, "-v", "error", "-y", "-stream_loop", str(loops - 1), "-i", str(encoded), "-c", "copy", str(clip)], check=True)
    return clip


def methods(clip: Path, work: Path, vidstab: bool) -> dict[str, list[str]]:
    out = work / clip.stem
    table = {
        "decode": [FFMPEG, "-v", "error", "-y", "-i", str(clip), "-f", "null", "-"],
        "transcode": [FFMPEG, "-v", "error", "-y", "-i", str(clip), *X264, "-c:a", "copy", f"{out}_transcode.mp4"],
        "mosaic stabilize": [*MOSAIC, "stabilize", str(clip), f"{out}_mosaic.mp4"],
        "mosaic track": [*MOSAIC, "track", str(clip), "-o", f"{out}_track.json"],
        "mosaic stitch": [*MOSAIC, "stitch", str(clip), "-o", f"{out}_pano.png"],
    }
    for command in ("stabilize", "track", "stitch"):
        table[f"mosaic {command} -O"] = [*table[f"mosaic {command}"], "--no-overlay-detect"]
    if vidstab:
        table["vid.stab"] = ["vidstab"]  # two commands: see run_vidstab
    return table


def run_vidstab(clip: Path, work: Path) -> float:
    trf = f"{clip.stem}.trf"
    detect, _ = run([FFMPEG, "-v", "error", "-y", "-i", str(clip), "-vf", f"vidstabdetect=result={trf}", "-f", "null", "-"], work, "vid.stab")
    transform, _ = run([FFMPEG, "-v", "error", "-y", "-i", str(clip), "-vf", f"vidstabtransform=input={trf}", *X264,
                        "-c:a", "copy", f"{clip.stem}_vidstab.mp4"], work, "vid.stab")
    CPU["vid.stab"][-2:] = [sum(CPU["vid.stab"][-2:])]
    return detect + transform


def warp_cpu_ms(clip: Path, frames: int = 20) -> float:
    """CPU milliseconds of warping one frame of ``clip`` as stabilize's render does (yuv420p, a
    similarity with a slight zoom), on one OpenCV thread: median over ``frames`` frames."""
    import cv2
    import numpy as np

    from mosaic_cli.stabilize.render import warp_yuv
    from mosaic_cli.video import open_video, probe

    info = probe(clip)
    cv2.setNumThreads(1)
    warp = np.array([[1.02, 0.01, -10.0], [-0.01, 1.02, -8.0], [0.0, 0.0, 1.0]])
    spent = []
    with open_video(clip, yuv420p=True, info=info) as stream:
        for k, frame in enumerate(stream):
            if k == frames:
                break
            start = time.process_time()
            warp_yuv(frame, warp, info.source_size, "replicate")
            spent.append(1000 * (time.process_time() - start))
    return statistics.median(spent)


def startup(work: Path, clip: Path, repeats: int = 5) -> float:
    one = work / "one_frame.mp4"
    subprocess.run([FFMPEG, "-v", "error", "-y", "-i", str(clip), "-frames:v", "1", str(one)], check=True)
    return statistics.median(run([*MOSAIC, "track", str(one), "-o", str(work / "one.json"), "-q"], work)[0] for _ in range(repeats))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="720p,4k", help="comma-separated: 720p, 4k")
    parser.add_argument("--clip", type=Path, action="append", help="a clip of your own instead (repeatable)")
    parser.add_argument("--rounds", type=int, default=2, help="rounds; each round runs every method twice, A-B-B-A")
    parser.add_argument("--gop", type=int, help="re-encode the made clips with a keyframe every GOP frames")
    parser.add_argument("--work", type=Path, default=Path(".dev/bench_speed"), help="working folder (clips are kept)")
    parser.add_argument("--no-vidstab", action="store_true")
    parser.add_argument("--json", type=Path, help="write every time measured here")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    work = args.work.resolve()
    print("command:", shlex.join([sys.executable, *sys.argv]))
    print(f"cpus: {os.cpu_count()}, load average at start: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    clips = [c.resolve() for c in args.clip] if args.clip else [make_clip(work, s.strip(), args.gop) for s in args.sizes.split(",")]
    report: dict = {"load_start": os.getloadavg(), "clips": {}}
    for clip in clips:
        table = methods(clip, work, not args.no_vidstab)
        order = list(table)
        times: dict[str, list[float]] = {name: [] for name in order}
        stage_times: dict[str, list[dict[str, float]]] = {name: [] for name in order}
        for k in range(args.rounds):
            for name in order + order[::-1]:  # A-B-B-A: a drifting load weighs on every method alike
                if name == "vid.stab":
                    times[name].append(run_vidstab(clip, work))
                    continue
                wall, err = run(table[name], work, name)
                times[name].append(wall)
                if name.startswith("mosaic"):
                    stage_times[name].append(stage_seconds(err))
            print(f"{clip.name}: round {k + 1} of {args.rounds} done, load {os.getloadavg()[0]:.2f}", file=sys.stderr)
        median = {name: statistics.median(v) for name, v in times.items()}
        cpu = {name: statistics.median(CPU[name]) for name in order}
        CPU.clear()
        floor = floor_of_stabilizing(clip, cpu["transcode"])
        report["clips"][clip.name] = {"times": times, "stages": stage_times, "median": median, "cpu": cpu, "floor": floor}
        _print_clip(clip, median, cpu, stage_times, floor)
    first = clips[0]
    report["startup_one_frame_track"] = startup(work, first)
    report["load_end"] = os.getloadavg()
    print(f"\nstart-up: mosaic track of a one-frame clip, median of 5: {report['startup_one_frame_track']:.2f} s")
    print(f"load average at the end: {' '.join(f'{v:.2f}' for v in report['load_end'])}")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


def floor_of_stabilizing(clip: Path, transcode_cpu: float) -> dict[str, float]:
    """The least wall time any stabiliser that warps every pixel and re-encodes with the same
    settings can take here: the transcode's CPU seconds and the warps', spread over every core
    with nothing lost to waiting; no tracking counted."""
    from mosaic_cli.video import probe

    frames = probe(clip).frame_count
    warp_ms = warp_cpu_ms(clip)
    cpu = transcode_cpu + frames * warp_ms / 1000
    return {"warp_cpu_ms": warp_ms, "transcode_cpu_s": transcode_cpu, "cpu_s": cpu, "cores": os.cpu_count() or 1,
            "wall_s": cpu / (os.cpu_count() or 1)}


def _print_clip(clip: Path, median: dict[str, float], cpu: dict[str, float], stage_times: dict[str, list[dict[str, float]]],
                floor: dict[str, float]) -> None:
    from mosaic_cli.video import probe

    info = probe(clip)
    print(f"\n{clip.name}: {info.source_size[0]}x{info.source_size[1]}, {info.frame_count} frames")
    print(f"{'method':<22} {'wall s':>7} {'CPU s':>7}  stages (medians, s)")
    for name, seconds in median.items():
        runs = stage_times.get(name) or []
        keys = list(runs[0]) if runs else []
        parts = ", ".join(f"{key} {statistics.median(r.get(key, 0.0) for r in runs):.1f}" for key in keys)
        print(f"{name:<22} {seconds:7.1f} {cpu.get(name, float('nan')):7.1f}  {parts}")
    ratios = [
        ("mosaic stabilize / transcode", "mosaic stabilize", "transcode", "<= 1.5"),
        ("vid.stab / mosaic stabilize", "vid.stab", "mosaic stabilize", ">= 2"),
        ("mosaic track / decode", "mosaic track", "decode", "<= 2.5"),
        ("mosaic stitch / decode", "mosaic stitch", "decode", "<= 5"),
    ]
    for label, a, b, goal in ratios:
        if a in median and b in median:
            print(f"{label:<32} {median[a] / median[b]:6.2f}   (goal {goal})")
    for name in ("mosaic stabilize", "mosaic track", "mosaic stitch"):
        if name in median and f"{name} -O" in median:
            cost = median[name] - median[f"{name} -O"]
            print(f"overlay detection in {name:<17} {100 * cost / median[name]:5.1f}% of its wall time "
                  f"({cost:+.1f} s against --no-overlay-detect; goal <= 5%)")
    print(f"floor of warping every pixel and re-encoding: {floor['wall_s']:.1f} s on {floor['cores']} cores "
          f"(transcode {floor['transcode_cpu_s']:.1f} s of CPU, warp {floor['warp_cpu_ms']:.1f} ms a frame); "
          f"against the transcode {floor['wall_s'] / median['transcode']:.2f}x"
          + (f", vid.stab / floor {median['vid.stab'] / floor['wall_s']:.2f}x" if "vid.stab" in median else ""))


if __name__ == "__main__":
    main()
