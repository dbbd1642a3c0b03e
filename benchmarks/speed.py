"""Speed: mosaic's commands against the encoder's floor and vid.stab, and the least time its design can take."""

from __future__ import annotations

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

import imageio_ffmpeg

from benchmarks.common import SHARED_DATA, cpu_seconds, make_parser, print_start, run_commands, stage_seconds

SUITE = "speed"


# -- python -m benchmarks speed --------------------------------------------------------------------

FFMPEG = imageio_ffmpeg.get_ffmpeg_exe()
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
        source = SHARED_DATA / image
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


def speed_command(argv: list[str] | None = None) -> int | None:
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

        python -m benchmarks speed                       # 1280x720 x 1200 frames and 3840x2160 x 300
        python -m benchmarks speed --sizes 720p --rounds 2
        python -m benchmarks speed --gop 30              # clips with a keyframe a second
    """
    parser = make_parser(SUITE, None, speed_command.__doc__)
    parser.add_argument("--sizes", default="720p,4k", help="comma-separated: 720p, 4k")
    parser.add_argument("--clip", type=Path, action="append", help="a clip of your own instead (repeatable)")
    parser.add_argument("--rounds", type=int, default=2, help="rounds; each round runs every method twice, A-B-B-A")
    parser.add_argument("--gop", type=int, help="re-encode the made clips with a keyframe every GOP frames")
    parser.add_argument("--work", type=Path, default=Path(".dev/bench_speed"), help="working folder (clips are kept)")
    parser.add_argument("--no-vidstab", action="store_true")
    parser.add_argument("--json", type=Path, help="write every time measured here")
    args = parser.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    work = args.work.resolve()
    print_start()
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


# -- python -m benchmarks speed floors -------------------------------------------------------------

T = TypeVar("T")
WARM_UP = 40  # frames


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
        walls["decode"].append(run([FFMPEG, "-v", "error", "-y", "-i", str(clip), "-f", "null", "-"], work)[0])
        spent, (seconds, _) = measured(lambda: run([FFMPEG, "-v", "error", "-y", "-i", str(clip), *X264, "-c:a", "copy",
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
            spent, (seconds, _) = measured(lambda line=line: run(line, work))
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


def floors_command(argv: list[str] | None = None) -> int | None:
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

        python -m benchmarks speed floors --clip shaky720.mp4 --clip shaky4k.mp4 --json floors.json
    """
    parser = make_parser(SUITE, 'floors', floors_command.__doc__)
    parser.add_argument("--clip", type=Path, action="append", required=True, help="a clip (repeatable)")
    parser.add_argument("--rounds", type=int, default=2, help="each piece measured this many times; medians")
    parser.add_argument("--work", type=Path, default=Path(".dev/speed_floors"), help="working folder")
    parser.add_argument("--no-vidstab", action="store_true")
    parser.add_argument("--json", type=Path, help="write every figure measured here")
    args = parser.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    work = args.work.resolve()
    print_start()
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


COMMANDS = {
    "floors": floors_command,
}


def main(argv: list[str]) -> int:
    return run_commands(SUITE, __doc__, COMMANDS, argv, default=speed_command)
