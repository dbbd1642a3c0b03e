#!/usr/bin/env python
"""Benchmark ``mosaic stabilize`` against ffmpeg's vid.stab on shaky simulated flights.

Each clip is a 'shaky' virtual flight (3-8 Hz shake over a smooth drone path, exact ground
truth) rendered over a real orthophoto from ../shared/data/aerial_stills when present (a
procedural map otherwise).  In one run, side by side, on the same clips:

* mosaic stabilize (defaults unless told otherwise; ``--estimators orb,lstm`` gives a row for
  each), timed end to end (tracking, path,
  warping and H.264 encoding, file to file);
* vid.stab (vidstabdetect + vidstabtransform, in the imageio-ffmpeg binary) with its defaults
  and with smoothing=30, encoded with the same x264 settings, timed the same way.

Scores (see mosaic_cli/stabilize/metrics.py):
* gt jitter: residual jitter of the output path against the known jitter-free path, input
  pixels, and its ratio to the input's.  For mosaic from its exact warps; for every method
  also from warps measured input -> output from the pixels (ORB + ECC), so all share one ruler;
* video jitter: from the output video alone (track it, chain the frame-to-frame homographies,
  high-pass the corners' path), output pixels;
* cropping and distortion (Liu et al. 2013) from the measured input -> output warps;
* fps: frames / wall seconds, encoding included.

    python scripts/bench_stabilize.py                    # 3 clips, 300 frames at 1280x720
    python scripts/bench_stabilize.py --variants         # + the model / smoother comparison
    python scripts/bench_stabilize.py --frames 90 --size 640x360 --clips 1   # a quick look
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import imageio_ffmpeg
import numpy as np

from mosaic_cli.estimators import DEFAULT_ESTIMATOR
from mosaic_cli.geometry import normalize
from mosaic_cli.simulate import load_ground_truth, load_map, plan_flight, write_flight
from mosaic_cli.stabilize import StabilizeOptions, stabilize
from mosaic_cli.stabilize.crop import output_warps
from mosaic_cli.stabilize.metrics import (
    cropping_ratio,
    distortion,
    ground_truth_jitter,
    matched_warps,
    pairwise_jitter,
    track_pairwise,
)
from mosaic_cli.stabilize.path import camera_motion, motion_model
from mosaic_cli.stabilize.smoothing import GaussianSmoother, L1Smoother

STILLS = Path(__file__).resolve().parents[2] / "shared" / "data" / "aerial_stills"
MAPS = [
    "deepforest_neon_orthophoto/2019_YELL_2_528000_4978000_image_crop2.png",
    "odm_orthomosaic_previews/aukerman.png",
    "odm_orthomosaic_previews/zoo.png",
    "odm_orthomosaic_previews/lewis.png",
    "deepforest_neon_orthophoto/2019_YELL_2_541000_4977000_image_crop.png",
]
FFMPEG = imageio_ffmpeg.get_ffmpeg_exe()


def cpu_seconds() -> float:
    """User + system CPU time of this process and its finished children (ffmpeg)."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


@dataclass
class Row:
    clip: str
    method: str
    fps: float | None = None
    cpu_ms: float | None = None  # CPU milliseconds per frame, all threads and processes
    gt_jitter: float | None = None  # exact warps (mosaic only), input px
    gt_jitter_measured: float | None = None  # warps measured from the pixels, input px
    video_jitter: float | None = None  # output px
    cropping: float | None = None
    distortion: float | None = None
    extra: dict = field(default_factory=dict)


def make_clip(folder: Path, map_path: Path | None, seed: int, frames: int, size: tuple[int, int]) -> Path:
    name = (map_path.stem if map_path else "procedural") + f"_s{seed}_{frames}f_{size[0]}x{size[1]}"
    clip = folder / f"{name}.mp4"
    if not clip.exists() or not clip.with_suffix(".gt.json").exists():
        rgb = load_map(map_path, seed=seed)
        plan = plan_flight((rgb.shape[1], rgb.shape[0]), "shaky", frames, size, seed)
        write_flight(clip, rgb, plan, map_name=map_path.name if map_path else "procedural", show_progress=False)
    return clip


def run_vidstab(clip: Path, out: Path, smoothing: int | None, crf: int, preset: str) -> tuple[float, float]:
    """vidstabdetect then vidstabtransform (+ x264); returns wall and CPU seconds for both."""
    clip, out = clip.resolve(), out.resolve()
    trf = out.with_suffix(".trf")
    transform = f"vidstabtransform=input={trf.name}" + ("" if smoothing is None else f":smoothing={smoothing}")
    start, cpu = time.perf_counter(), cpu_seconds()
    subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-y", "-i", str(clip), "-vf",
                    f"vidstabdetect=result={trf.name}", "-f", "null", "-"], check=True, cwd=out.parent)
    subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-y", "-i", str(clip), "-vf", transform,
                    "-c:v", "libx264", "-preset", preset, "-crf", str(crf), "-pix_fmt", "yuv420p", "-c:a", "copy",
                    str(out)], check=True, cwd=out.parent)
    return time.perf_counter() - start, cpu_seconds() - cpu


def pixel_scores(row: Row, clip: Path, out: Path, gt) -> None:
    """Everything measured from the output video's pixels (the same for every method)."""
    pairwise, size, fps = track_pairwise(out)
    row.video_jitter = pairwise_jitter(pairwise, size, fps)
    index, warps = matched_warps(clip, out)
    row.cropping, row.distortion = cropping_ratio(warps, size), distortion(warps, size)
    row.extra["matched_frames"] = len(index)
    if len(index) == gt.frames:  # the high-pass needs every frame
        row.gt_jitter_measured = ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, gt.size, gt.fps, warps)


def variants(clip: Path, gt, track_width: int) -> list[Row]:
    """Planning-only comparison of motion models and smoothers on one tracking of the clip."""
    from mosaic_cli.estimators import OrbEstimator
    from mosaic_cli.track import track_video

    track = track_video(clip, OrbEstimator(track_width), show_progress=False)
    size = gt.size
    rows = []
    for smoother_name, smoother in (("l1", L1Smoother()), ("gaussian r30", GaussianSmoother(30))):
        for model_name in ("tilt", "similarity", "affine", "homography"):
            model = motion_model(model_name)
            start = time.perf_counter()
            motion = camera_motion(track.pairwise, size, model, track.confidence)
            warps = output_warps(smoother.smooth(motion, size, model, None), size)
            seconds = time.perf_counter() - start
            rows.append(Row(clip.stem, f"{smoother_name} {model_name} (plan only)",
                            gt_jitter=ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, size, gt.fps, warps),
                            cropping=cropping_ratio(warps, size), distortion=distortion(warps, size),
                            extra={"plan_ms_per_frame": 1000 * seconds / gt.frames}))
    return rows


def fmt(value, spec=".3f") -> str:
    return "-" if value is None else format(value, spec)


def print_table(rows: list[Row], input_jitter: dict[str, float]) -> None:
    head = f"{'clip':<34} {'method':<36} {'fps':>6} {'cpu ms':>6} {'gt jit':>7} {'ratio':>6} {'gt jit*':>7} {'ratio*':>6} {'vid jit':>7} {'crop':>6} {'dist':>6}"
    print(head)
    print("-" * len(head))
    for r in rows:
        base = input_jitter.get(r.clip)
        ratio = None if r.gt_jitter is None or not base else r.gt_jitter / base
        ratio_m = None if r.gt_jitter_measured is None or not base else r.gt_jitter_measured / base
        print(f"{r.clip[:34]:<34} {r.method[:36]:<36} {fmt(r.fps, '.1f'):>6} {fmt(r.cpu_ms, '.1f'):>6} {fmt(r.gt_jitter):>7} {fmt(ratio):>6} "
              f"{fmt(r.gt_jitter_measured):>7} {fmt(ratio_m):>6} {fmt(r.video_jitter):>7} {fmt(r.cropping):>6} {fmt(r.distortion):>6}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--clips", type=int, default=3, help="number of shaky flights (one map each)")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--seed", type=int, default=1, help="seed of the first clip (the next ones count up)")
    parser.add_argument("--out", type=Path, default=Path(".dev/bench_stabilize"), help="working folder (clips are cached)")
    parser.add_argument("--crf", type=int, default=18)
    parser.add_argument("--preset", default="veryfast")
    parser.add_argument("--model", default=StabilizeOptions().model)
    parser.add_argument("--smoothing", default="l1")
    parser.add_argument("--variants", action="store_true", help="also compare models and smoothers (planning only)")
    parser.add_argument("--estimators", type=lambda text: [e.strip() for e in text.split(",") if e.strip()],
                        default=[DEFAULT_ESTIMATOR], help=f"comma-separated mosaic estimators, one row each [{DEFAULT_ESTIMATOR}]")
    parser.add_argument("--no-vidstab", action="store_true")
    parser.add_argument("--json", type=Path, help="write all rows here")
    args = parser.parse_args()
    print("command:", shlex.join([sys.executable, *sys.argv]))
    print(f"cpus: {os.cpu_count()}, load average at start: {' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    size = tuple(int(v) for v in args.size.lower().split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    maps = [STILLS / m for m in MAPS if (STILLS / m).exists()] or [None]
    rows: list[Row] = []
    input_jitter: dict[str, float] = {}
    for k in range(args.clips):
        map_path = maps[k % len(maps)]
        clip = make_clip(args.out, map_path, args.seed + k, args.frames, size)
        gt = load_ground_truth(clip.with_suffix(".gt.json"))
        input_jitter[clip.stem] = ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, gt.size, gt.fps)
        measured = track_pairwise(clip)[0]
        # The ruler's own noise: the jitter of a video whose only motion is its errors.
        errors = normalize(measured @ np.linalg.inv(gt.pairwise))
        source = Row(clip.stem, "input (shaky)", gt_jitter=input_jitter[clip.stem],
                     video_jitter=pairwise_jitter(measured, gt.size, gt.fps),
                     extra={"true_video_jitter": pairwise_jitter(gt.pairwise, gt.size, gt.fps),
                            "ruler_noise": pairwise_jitter(errors, gt.size, gt.fps)})
        print(f"{clip.stem}: ruler noise floor {source.extra['ruler_noise']:.3f} px (video jitter of its errors)")
        rows.append(source)

        for estimator in args.estimators:
            out = args.out / f"{clip.stem}.mosaic.{estimator}.mp4"
            options = StabilizeOptions(estimator=estimator, model=args.model, smoothing=args.smoothing, crf=args.crf,
                                       preset=args.preset)
            start, cpu = time.perf_counter(), cpu_seconds()
            result = stabilize(clip, out, options, show_progress=False)
            seconds, cpu = time.perf_counter() - start, cpu_seconds() - cpu
            row = Row(clip.stem, f"mosaic {args.smoothing} {args.model} ({estimator})", fps=result.frames / seconds,
                      cpu_ms=1000 * cpu / result.frames,
                      gt_jitter=ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, gt.size, gt.fps, result.warps),
                      extra={"stage_seconds": result.seconds, "exact_cropping": result.cropping,
                             "exact_distortion": result.distortion, "border": result.border})
            pixel_scores(row, clip, out, gt)
            rows.append(row)

        if not args.no_vidstab:
            for smoothing in (None, 30):
                out = args.out / f"{clip.stem}.vidstab{'' if smoothing is None else smoothing}.mp4"
                seconds, cpu = run_vidstab(clip, out, smoothing, args.crf, args.preset)
                row = Row(clip.stem, "vid.stab " + ("defaults" if smoothing is None else f"smoothing={smoothing}"),
                          fps=gt.frames / seconds, cpu_ms=1000 * cpu / gt.frames)
                pixel_scores(row, clip, out, gt)
                rows.append(row)
        if args.variants:
            rows += variants(clip, gt, 640)
        print_table([r for r in rows if r.clip == clip.stem], input_jitter)
        print(flush=True)

    print(f"load average at end: {' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    print("all clips (gt jit: input px vs the known smooth path, exact warps; * : warps measured from the pixels;")
    print("vid jit: output px from the output video alone; crop/dist: Liu et al. from measured warps)")
    print_table(rows, input_jitter)
    print("\nmedians over clips:")
    for method in dict.fromkeys(r.method for r in rows):
        sel = [r for r in rows if r.method == method]

        def med(attr):
            vals = [getattr(r, attr) for r in sel if getattr(r, attr) is not None]
            return float(np.median(vals)) if vals else None

        ratios = [r.gt_jitter_measured / input_jitter[r.clip] for r in sel if r.gt_jitter_measured is not None]
        exact = [r.gt_jitter / input_jitter[r.clip] for r in sel if r.gt_jitter is not None]
        print(f"  {method:<40} fps {fmt(med('fps'), '.1f'):>5}  cpu ms/frame {fmt(med('cpu_ms'), '.1f'):>5}  gt ratio {fmt(float(np.median(exact)) if exact else None)}"
              f"  gt ratio* {fmt(float(np.median(ratios)) if ratios else None)}  video jitter {fmt(med('video_jitter'))}"
              f"  cropping {fmt(med('cropping'))}  distortion {fmt(med('distortion'))}")
    if args.json:
        args.json.write_text(json.dumps([asdict(r) for r in rows], indent=1, default=float) + "\n")


if __name__ == "__main__":
    main()
