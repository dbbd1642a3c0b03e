"""Stabilize: ``mosaic stabilize`` against vid.stab, the motion models under perspective shake, and the frames it writes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import imageio_ffmpeg
import numpy as np

from benchmarks.common import STILLS, command_line, cpu_seconds, decoded_count, make_parser, print_start, run_commands
from mosaic_cli.estimators import DEFAULT_ESTIMATOR, plan_estimator
from mosaic_cli.geometry import normalize
from mosaic_cli.simulate import PROFILES, load_ground_truth, load_map, plan_flight, write_flight
from mosaic_cli.stabilize import StabilizeOptions, smoothing, stabilize
from mosaic_cli.stabilize.crop import output_warps
from mosaic_cli.stabilize.metrics import cropping_ratio, distortion, ground_truth_jitter, matched_warps, pairwise_jitter, track_pairwise
from mosaic_cli.stabilize.path import camera_motion, motion_model
from mosaic_cli.stabilize.pipeline import WORK_WIDTH
from mosaic_cli.stabilize.smoothing import GaussianSmoother, L1Smoother
from mosaic_cli.track import track_video

SUITE = "stabilize"


# -- python -m benchmarks stabilize ----------------------------------------------------------------

MAPS = [
    "deepforest_neon_orthophoto/2019_YELL_2_528000_4978000_image_crop2.png",
    "odm_orthomosaic_previews/aukerman.png",
    "odm_orthomosaic_previews/zoo.png",
    "odm_orthomosaic_previews/lewis.png",
    "deepforest_neon_orthophoto/2019_YELL_2_541000_4977000_image_crop.png",
]
FFMPEG = imageio_ffmpeg.get_ffmpeg_exe()


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


def stabilize_command(argv: list[str] | None = None) -> int | None:
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

        python -m benchmarks stabilize                    # 3 clips, 300 frames at 1280x720
        python -m benchmarks stabilize --variants         # + the model / smoother comparison
        python -m benchmarks stabilize --frames 90 --size 640x360 --clips 1   # a quick look
    """
    parser = make_parser(SUITE, None, stabilize_command.__doc__)
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
    args = parser.parse_args(argv)
    print_start()
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

        def med(attr, sel=sel):
            vals = [getattr(r, attr) for r in sel if getattr(r, attr) is not None]
            return float(np.median(vals)) if vals else None

        ratios = [r.gt_jitter_measured / input_jitter[r.clip] for r in sel if r.gt_jitter_measured is not None]
        exact = [r.gt_jitter / input_jitter[r.clip] for r in sel if r.gt_jitter is not None]
        print(f"  {method:<40} fps {fmt(med('fps'), '.1f'):>5}  cpu ms/frame {fmt(med('cpu_ms'), '.1f'):>5}  gt ratio {fmt(float(np.median(exact)) if exact else None)}"
              f"  gt ratio* {fmt(float(np.median(ratios)) if ratios else None)}  video jitter {fmt(med('video_jitter'))}"
              f"  cropping {fmt(med('cropping'))}  distortion {fmt(med('distortion'))}")
    if args.json:
        args.json.write_text(json.dumps([asdict(r) for r in rows], indent=1, default=float) + "\n")


# -- python -m benchmarks stabilize perspective ----------------------------------------------------

HELD_OUT = {
    "boruszyn": "odm_orthomosaic_previews/boruszyn.png",
    "yell541": "deepforest_neon_orthophoto/2019_YELL_2_541000_4977000_image_crop.png",
    "soap061": "deepforest_neon_orthophoto/SOAP_061.png",
    "procedural": None,
}
METHODS = ("similarity", "homography", "tilt", "tilt, always", "tilt, exact motion")


def held_out_clip(folder: Path, name: str, profile: str, seed: int, frames: int, size: tuple[int, int]) -> Path:
    clip = folder / f"{name}_{profile}_s{seed}_{frames}f_{size[0]}x{size[1]}.mp4"
    if not clip.exists() or not clip.with_suffix(".gt.json").exists():
        path = HELD_OUT[name]
        rgb = load_map(None if path is None else STILLS / path, seed=seed)
        plan = plan_flight((rgb.shape[1], rgb.shape[0]), profile, frames, size, seed)
        write_flight(clip, rgb, plan, map_name=name, show_progress=False)
    return clip


def plan_warps(pairwise: np.ndarray, confidence, size, model_name: str) -> np.ndarray:
    model = motion_model(model_name)
    motion = camera_motion(pairwise, size, model, confidence)
    return output_warps(smoothing.L1Smoother().smooth(motion, size, model, None), size)


def always_supported(pairwise, confidence, size) -> np.ndarray:
    """The tilt model with the gate open: every window believes its perspective terms."""
    original = smoothing.perspective_support
    smoothing.perspective_support = lambda motion: 1.0
    try:
        return plan_warps(pairwise, confidence, size, "tilt")
    finally:
        smoothing.perspective_support = original


def perspective_command(argv: list[str] | None = None) -> int | None:
    """Perspective (pitch and roll) shake: the stabiliser's motion models side by side, planning only.

    Each clip is a simulated flight over a map held out of the learned estimator's training
    (models/README.md: the Boruszyn orthomosaic, the NEON YELL 541000 tile, SOAP_061; and the
    procedural map), flown with the ``shaky-tilt`` profile (3-8 Hz shake with pitch and roll of up
    to 0.3 degrees) and with ``shaky`` (the same in-plane shake, no pitch or roll), exact ground
    truth.  Each clip is tracked once with the estimator (default: stabilize's), and the L1 path is
    planned from that track with each model:

    * ``similarity`` (the default before), ``homography``, ``tilt`` (the default now: a similarity
      plus the perspective shake where the estimates support it);
    * ``tilt, always``: the tilt model with its gate open everywhere (support forced to 1), to
      show what the gate is for;
    * ``tilt, exact motion``: the tilt model planned from the exact motion, the floor the
      estimates' errors keep the others above.

    Scores (mosaic_cli/stabilize/metrics.py), from the exact warps: residual jitter against the
    known jitter-free path as a share of the input's (``ground_truth_jitter``), cropping ratio
    (mean) and distortion (worst frame), Liu et al. 2013.

        python -m benchmarks stabilize perspective                          # 4 maps x 2 seeds x 2 profiles, 640x360, 240 frames
        python -m benchmarks stabilize perspective --seeds 1 --frames 150   # a quick look
        python -m benchmarks stabilize perspective --seeds 1 --profiles "" --tilt 0.05,0.1,0.15   # weaker pitch and roll shake
    """
    parser = make_parser(SUITE, 'perspective', perspective_command.__doc__)
    parser.add_argument("--maps", default=",".join(HELD_OUT), help=f"comma-separated, of {', '.join(HELD_OUT)}")
    parser.add_argument("--profiles", default="shaky-tilt,shaky")
    parser.add_argument("--tilt", default="", help="also shaky-tilt flights with these pitch and roll amplitudes (degrees, comma-separated)")
    parser.add_argument("--seeds", type=int, default=2, help="flights per map and profile (seeds 1, 2, ...)")
    parser.add_argument("--frames", type=int, default=240)
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--estimator", default=None, help="default: stabilize's")
    parser.add_argument("--out", type=Path, default=Path(".dev/bench_perspective"), help="working folder (clips are cached)")
    args = parser.parse_args(argv)
    print("command:", command_line())
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
    size = tuple(int(v) for v in args.size.lower().split("x"))
    profiles = [p for p in args.profiles.split(",") if p]
    for deg in (float(v) for v in args.tilt.split(",") if v):
        name = f"shaky-tilt-{deg:g}"  # the shaky-tilt profile with another amplitude (this run only)
        PROFILES[name] = replace(PROFILES["shaky-tilt"], name=name, jitter_tilt_deg=deg)
        profiles.append(name)
    args.out.mkdir(parents=True, exist_ok=True)
    options = StabilizeOptions(estimator=args.estimator)
    build = plan_estimator(options.estimator, work_width=None, weights=None, device="cpu", default_width=WORK_WIDTH)
    rows: list[tuple[str, str, str, float, float, float]] = []  # profile, clip, method, ratio, cropping, distortion
    header = f"{'profile':<11} {'clip':<16} {'input px':>8} " + " ".join(f"{m:>20}" for m in METHODS)
    print("gt jitter ratio / cropping / distortion per method")
    print(header)
    for profile in profiles:
        for name in args.maps.split(","):
            for seed in range(1, args.seeds + 1):
                clip = held_out_clip(args.out, name, profile, seed, args.frames, size)
                gt = load_ground_truth(clip.with_suffix(".gt.json"))
                track = track_video(clip, build(), show_progress=False)
                base = ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, gt.size, gt.fps)
                cells = []
                for method in METHODS:
                    if method == "tilt, always":
                        warps = always_supported(track.pairwise, track.confidence, gt.size)
                    elif method == "tilt, exact motion":
                        warps = plan_warps(gt.pairwise, None, gt.size, "tilt")
                    else:
                        warps = plan_warps(track.pairwise, track.confidence, gt.size, method)
                    ratio = ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, gt.size, gt.fps, warps) / base
                    row = (profile, f"{name} s{seed}", method, ratio, cropping_ratio(warps, gt.size), distortion(warps, gt.size))
                    rows.append(row)
                    cells.append(f"{row[3]:.3f}/{row[4]:.3f}/{row[5]:.3f}")
                print(f"{profile:<11} {name + ' s' + str(seed):<16} {base:>8.2f} " + " ".join(f"{c:>20}" for c in cells), flush=True)

    print(f"\nestimator: {options.estimator or DEFAULT_ESTIMATOR}, cpus: {os.cpu_count()}")
    print("\nmedian (min-max) over the clips, as Markdown:\n")
    print("| profile | method | gt jitter ratio | cropping | distortion (worst) |")
    print("|---|---|---|---|---|")
    for profile in profiles:
        for method in METHODS:
            sel = np.array([r[3:] for r in rows if r[0] == profile and r[2] == method])
            if not len(sel):
                continue
            ratio, crop, dist = sel.T
            print(
                f"| {profile} | {method} | {np.median(ratio):.3f} ({ratio.min():.3f}-{ratio.max():.3f}) | "
                f"{np.median(crop):.3f} ({crop.min():.3f}-{crop.max():.3f}) | {dist.min():.3f} |"
            )


# -- python -m benchmarks stabilize frames ---------------------------------------------------------


def ffmpeg(*args: str) -> None:
    subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-y", *args], check=True)


def audio_seconds(path: Path) -> float | None:
    run = subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-i", str(path), "-map", "0:a:0?", "-ac", "1",
                          "-ar", "48000", "-f", "s16le", "-"], capture_output=True)
    return len(run.stdout) / 2 / 48000 if run.stdout else None


def make_inputs(flight: Path, seconds: float, work: Path) -> dict[str, Path]:
    """name -> input file (or folder), all made from ``flight`` (30 fps, no audio)."""
    x264 = ["-c:v", "libx264", "-preset", "veryfast", "-crf", "16", "-pix_fmt", "yuv420p"]

    def sine(duration: float) -> list[str]:
        return ["-f", "lavfi", "-i", f"sine=frequency=440:sample_rate=48000:duration={duration:.3f}"]

    def with_audio(name: str, video: Path, duration: float, codec: str = "aac") -> Path:
        out = work / name
        ffmpeg("-i", str(video), *sine(duration), "-map", "0:v", "-map", "1:a", "-c:v", "copy", "-c:a", codec, str(out))
        return out

    def retimed(name: str, rate: str) -> Path:
        out = work / name
        ffmpeg("-i", str(flight), "-vf", f"setpts=N/({rate})/TB", "-r", rate, *x264, str(out))
        return out

    inputs: dict[str, Path] = {"30 fps, no audio": flight}
    inputs["30 fps, AAC as long"] = with_audio("equal.mp4", flight, seconds)
    inputs["30 fps, AAC 0.02 s shorter"] = with_audio("short002.mp4", flight, seconds - 0.02)
    inputs["30 fps, AAC 0.3 s shorter"] = with_audio("short03.mp4", flight, seconds - 0.3)
    inputs["30 fps, AAC 2 s longer"] = with_audio("long2.mp4", flight, seconds + 2)
    for rate, label, delta in (("30000/1001", "29.97", -0.1), ("24000/1001", "23.976", +1.0), ("25", "25", -0.05),
                               ("60", "60", 0.0)):
        video = retimed(f"r{label}.mp4", rate)
        n = decoded_count(video)
        num, _, den = rate.partition("/")
        length = n * (float(den) if den else 1.0) / float(num)
        inputs[f"{label} fps, AAC {delta:+.2f} s"] = with_audio(f"r{label}_audio.mp4", video, length + delta)
    vfr = work / "vfr.mp4"
    ffmpeg("-i", str(flight), *sine(seconds * 1.2), "-map", "0:v", "-map", "1:a",
           "-vf", "setpts='(N+floor(N/10)*0.6+0.3*sin(N))/30/TB'", "-fps_mode", "vfr", *x264, "-c:a", "aac", str(vfr))
    inputs["variable rate, AAC"] = vfr
    mkv = work / "audio.mkv"
    ffmpeg("-i", str(inputs["30 fps, AAC 0.3 s shorter"]), "-c", "copy", str(mkv))
    inputs["mkv, AAC 0.3 s shorter"] = mkv
    mov = work / "pcm.mov"
    ffmpeg("-i", str(flight), *sine(seconds - 0.1), "-map", "0:v", "-map", "1:a", "-c:v", "copy", "-c:a", "pcm_s16le", str(mov))
    inputs["mov, PCM audio (re-encoded to AAC)"] = mov
    trimmed = work / "trimmed.mp4"
    ffmpeg("-ss", f"{seconds / 3:.2f}", "-i", str(inputs["30 fps, AAC as long"]), "-c", "copy", str(trimmed))
    inputs["cut without re-encoding (edit list), AAC"] = trimmed
    odd = work / "odd.mp4"
    ffmpeg("-i", str(inputs["30 fps, AAC 0.3 s shorter"]), "-vf", "crop=iw-1:ih-1:0:0", "-c:v", "libx264", "-preset",
           "veryfast", "-crf", "16", "-pix_fmt", "yuv444p", "-c:a", "copy", str(odd))
    inputs["odd size (yuv444p), AAC"] = odd
    folder = work / "frames"
    folder.mkdir(exist_ok=True)
    ffmpeg("-i", str(flight), str(folder / "f_%04d.png"))
    inputs["image folder"] = folder
    return inputs


def frames_command(argv: list[str] | None = None) -> int | None:
    """Does ``mosaic stabilize`` write exactly the frames it was given?  On every kind of input a
    camera or an editor makes: with and without audio, audio shorter or longer than the picture,
    odd frame rates (29.97, 23.976, 25, 60), variable frame rate, mkv and mov containers, a clip
    cut without re-encoding (edit list), an odd frame size, an image folder.

    Each input is made here from one shaky simulated flight; input and output frames are counted
    by decoding them with OpenCV (every coded frame once; no ffprobe, no container figures).
    Prints a markdown table and exits 1 if any count differs.

        python -m benchmarks stabilize frames                     # 150 frames at 320x180, -e orb
        python -m benchmarks stabilize frames --frames 300 --size 852x480 --estimator lstm --workdir /tmp/frames
    """
    parser = make_parser(SUITE, 'frames', frames_command.__doc__)
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--size", default="320x180")
    parser.add_argument("--estimator", default="orb")
    parser.add_argument("--workdir", default=None, help="keep the inputs here (default: a temporary folder)")
    args = parser.parse_args(argv)
    work = Path(args.workdir or tempfile.mkdtemp(prefix="mosaic-frames-"))
    work.mkdir(parents=True, exist_ok=True)
    flight = work / "flight.mp4"
    subprocess.run([sys.executable, "-m", "mosaic_cli", "simulate", "-o", str(flight), "-n", str(args.frames),
                    "--profile", "shaky", "--size", args.size, "--preset", "veryfast", "-q"], check=True)
    inputs = make_inputs(flight, args.frames / 30.0, work)
    print("| input | frames in | frames out | audio in (s) | audio out (s) | video out (s) |\n|---|---:|---:|---:|---:|---:|")
    failed = 0
    for name, path in inputs.items():
        out = work / f"out_{path.stem}.mp4"
        run = subprocess.run([sys.executable, "-m", "mosaic_cli", "stabilize", str(path), str(out), "-e", args.estimator, "-q"],
                             capture_output=True, text=True)
        if run.returncode != 0:
            print(f"| {name} | {decoded_count(path)} | failed: {run.stderr.strip()} | | | |")
            failed += 1
            continue
        n_in, n_out = decoded_count(path), decoded_count(out)
        capture = cv2.VideoCapture(str(out), cv2.CAP_FFMPEG)
        video_s = n_out / capture.get(cv2.CAP_PROP_FPS)
        capture.release()
        a_in, a_out = audio_seconds(path) if path.is_file() else None, audio_seconds(out)
        fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
        mark = "" if n_in == n_out else " **differs**"
        failed += n_in != n_out
        print(f"| {name} | {n_in} | {n_out}{mark} | {fmt(a_in)} | {fmt(a_out)} | {video_s:.3f} |", flush=True)
    print(f"\n{len(inputs) - failed} of {len(inputs)} inputs kept every frame")
    raise SystemExit(1 if failed else 0)


COMMANDS = {
    "perspective": perspective_command,
    "frames": frames_command,
}


def main(argv: list[str]) -> int:
    return run_commands(SUITE, __doc__, COMMANDS, argv, default=stabilize_command)
