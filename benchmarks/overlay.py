"""Overlays: burned-in overlays on simulated flights with exact truth, and how tight the detector's mask is."""

from __future__ import annotations

import json
import os
import subprocess
import time
from pathlib import Path

import cv2
import imageio_ffmpeg
import numpy as np

from benchmarks.common import ORTHOPHOTO, ROOT, cpu_seconds, make_parser, placement_errors, run_commands
from mosaic_cli.estimators import make_estimator
from mosaic_cli.evaluate import evaluate
from mosaic_cli.overlay import MaskOptions, OverlayOptions, detect_overlays, frame_mask, sample_frames, sample_width
from mosaic_cli.simulate import OverlaySpec, load_ground_truth, load_map, plan_flight, write_flight
from mosaic_cli.simulate.overlay import OverlayBurner
from mosaic_cli.stitch import StitchOptions, stitch
from mosaic_cli.track import track_video
from mosaic_cli.video import probe

SUITE = "overlay"


# -- python -m benchmarks overlay ------------------------------------------------------------------

DEFAULT_WORKDIR = ROOT / ".dev" / "bench_overlay"  # the flights, shared by both commands
SIZE = (1280, 720)
GAP = 60  # frames: placements are scored between used frames at least this far apart


def flights(workdir: Path, frames: int, seed: int, overlays: str) -> tuple[Path, Path]:
    """(clean, burned) renderings of one survey plan, cached."""
    known = ORTHOPHOTO.exists()
    stem = f"survey_{SIZE[0]}x{SIZE[1]}_{frames}_s{seed}"
    clean, burned = workdir / f"{stem}.mp4", workdir / f"{stem}_{overlays.replace(',', '+')}.mp4"
    if not clean.exists() or not burned.exists():
        ground = load_map(ORTHOPHOTO if known else None, seed=seed)
        plan = plan_flight((ground.shape[1], ground.shape[0]), "survey", frames, SIZE, seed)
        name = ORTHOPHOTO.name if known else "procedural"
        write_flight(clean, ground, plan, map_name=name, preset="veryfast", show_progress=False)
        write_flight(burned, ground, plan, map_name=name, preset="veryfast", show_progress=False, overlays=OverlaySpec.parse(overlays))
    return clean, burned


def overlay_coloured(path: Path) -> int:
    """Covered panorama pixels in the logo's (magenta) or the timestamp's (yellow) colour."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    b, g, r, a = (image[..., k].astype(int) for k in range(4))
    hit = ((r > 200) & (g < 70) & (b > 200)) | ((r > 200) & (g > 200) & (b < 70))
    return int(np.count_nonzero(hit & (a > 0)))


# (name, flight, mask): "detect" (the default), "off" (--no-overlay-detect), "exact" (the
# simulator's mask of what it drew, as --mask), "burned's" (the mask detected on the burned
# flight, as --mask with no margin).
RUNS = (
    ("clean", "clean", "detect"),
    ("burned", "burned", "detect"),
    ("burned-nodetect", "burned", "off"),
    ("burned-exactmask", "burned", "exact"),
    ("clean-burnedmask", "clean", "burned's"),
)
DEFAULT_RUNS = ("clean", "burned", "burned-nodetect")


def mask_options(kind: str, burned: Path, workdir: Path) -> MaskOptions:
    if kind == "detect":
        return MaskOptions()
    if kind == "off":
        return MaskOptions(detect=False)
    if kind == "exact":
        return MaskOptions(file=burned.with_suffix(".mask.png"), detect=False)
    detected = workdir / f"{burned.stem}.detected.png"
    if not detected.exists():
        cv2.imwrite(str(detected), frame_mask(burned, MaskOptions()).use)
    return MaskOptions(file=detected, detect=False, file_margin=0)


def accuracy(args, clean: Path, burned: Path, estimator: str) -> list[dict]:
    gt = load_ground_truth(clean.with_suffix(".gt.json"))
    rows = []
    for label, flight, kind in RUNS:
        if label not in args.runs:
            continue
        video = burned if flight == "burned" else clean
        masking = mask_options(kind, burned, args.workdir)
        row = {"flight": clean.stem, "estimator": estimator, "run": label}
        est = make_estimator(estimator)
        mask = frame_mask(video, masking)
        row["masked %"] = 100 * mask.excluded
        est.set_mask(mask.use)
        row["MACE"] = row["pair error"] = float("nan")
        if not args.no_track:
            track = track_video(video, est, show_progress=False)
            scores = evaluate(track.pairwise, gt)
            row["MACE"], row["pair error"] = scores["mace"], scores["corner_error"]
        out = args.workdir / f"{video.stem}_{estimator}_{kind.replace(chr(39), '')}.png"
        result = stitch(video, out, make_estimator(estimator), StitchOptions(mask=masking), show_progress=False)
        indices = [i for i, _ in result.transforms]
        errors = placement_errors(indices, [H for _, H in result.transforms], gt.map_to_frame, gt.size, GAP)
        row["placement median"], row["placement p90"] = float(np.median(errors)), float(np.percentile(errors, 90))
        row["overlay px in panorama"] = overlay_coloured(out)
        row["canvas"] = f"{result.canvas_size[0]}x{result.canvas_size[1]}"
        rows.append(row)
        print(f"{row['flight']} {estimator:5s} {label:22s} masked {row['masked %']:5.1f}%  MACE {row['MACE']:.2f}  pair {row['pair error']:.2f}  "
              f"placement median {row['placement median']:.2f} p90 {row['placement p90']:.2f} px  overlay px {row['overlay px in panorama']}  "
              f"canvas {row['canvas']}", flush=True)
    return rows


def _paired_summary(rows: list[dict]) -> None:
    """Each run against the clean flight, flight by flight: is a difference a bias or noise?"""
    by: dict = {}
    for row in rows:
        by.setdefault((row["estimator"], row["flight"]), {})[row["run"]] = row
    for estimator in sorted({e for e, _ in by}):
        for label, _, _ in RUNS[1:]:
            for stat in ("placement median", "placement p90"):
                diffs = [runs[label][stat] - runs["clean"][stat] for (e, _), runs in by.items() if e == estimator and {"clean", label} <= set(runs)]
                if diffs:
                    d = np.array(diffs)
                    print(f"{estimator:5s} {stat}, {label} minus clean over {len(d)} flights: mean {d.mean():+.3f} px, median {np.median(d):+.3f}, "
                          f"worse on {int((d > 0).sum())} of {len(d)}, range {d.min():+.2f} .. {d.max():+.2f}", flush=True)


def detector_cost(args, burned: Path) -> dict:
    info = probe(burned)
    times, cpu = [], []
    for _ in range(args.repeat):
        clock, used = time.perf_counter(), cpu_seconds()
        frame_mask(burned, MaskOptions(), info)
        times.append(time.perf_counter() - clock)
        cpu.append(cpu_seconds() - used)
    o = OverlayOptions()
    frames = sample_frames(burned, o.samples, sample_width(info.source_size, o), info)  # as frame_mask reads them
    detect, detect_cpu = [], []
    for _ in range(args.repeat):
        clock, used = time.perf_counter(), time.process_time()
        detect_overlays(frames, info.source_size)
        detect.append(time.perf_counter() - clock)
        detect_cpu.append(time.process_time() - used)
    # A long clip with keyframes every second, as drone cameras write them (x264's default,
    # one every 250 frames, leaves too few distinct keyframes to seek to; then the clip is
    # decoded once instead).
    looped = args.workdir / f"{burned.stem}_x10_g30.mp4"
    if not looped.exists():
        subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-stream_loop", "9", "-i", str(burned),
                        "-c:v", "libx264", "-preset", "ultrafast", "-g", "30", str(looped)], check=True)
    long_info = probe(looped)
    seek, seek_cpu = [], []
    for _ in range(args.repeat):
        clock, used = time.perf_counter(), cpu_seconds()
        frame_mask(looped, MaskOptions(), long_info)
        seek.append(time.perf_counter() - clock)
        seek_cpu.append(cpu_seconds() - used)
    cost = {
        "flight": f"{burned.name}, {info.frame_count} frames {info.source_size[0]}x{info.source_size[1]}",
        "sample + detect s (median wall)": float(np.median(times)),
        "sample + detect CPU s (median, ffmpeg included)": float(np.median(cpu)),
        "detect alone ms (median wall)": 1000 * float(np.median(detect)),
        "detect alone CPU ms (median)": 1000 * float(np.median(detect_cpu)),
        "long clip": f"{long_info.frame_count} frames, a keyframe a second (seeking)",
        "long clip sample + detect s (median wall)": float(np.median(seek)),
        "long clip sample + detect CPU s (median, ffmpeg included)": float(np.median(seek_cpu)),
        "load average": os.getloadavg()[0],
    }
    print(json.dumps(cost, indent=1), flush=True)
    return cost


def overlay_command(argv: list[str] | None = None) -> int | None:
    """Burned-in overlays on simulated flights with exact ground truth (docs/measurements/stitch.md, "Burned-in
    overlays").

        python -m benchmarks overlay                  # accuracy + overlay pixels + detector cost
        python -m benchmarks overlay --frames 300 --seeds 1 --estimators orb
        python -m benchmarks overlay --cost-only      # the detector's cost alone

    Each seed's survey flight (1280x720, over the NEON orthophoto in ../shared/data when present,
    a procedural map otherwise) is rendered twice from one plan: clean, and with overlays burned in
    (``mosaic simulate --overlays``; a magenta logo and a yellow running timestamp by default).
    For each estimator:

    * track: the pairwise estimates' MACE and median corner error against the exact homographies
      (clean flight; burned flight with detection; burned flight with detection off; and on
      request, to tell the overlays' pixels from the ground their mask hides: the burned flight
      with the simulator's exact mask, the clean flight with the mask detected on the burned one);
    * stitch: the placement error of used frames at least 60 frames apart (median and 90th
      percentile, 1280x720 px) and the panorama pixels in the overlays' colours, same three runs.

    Then the detector's cost: sampling plus detection on the flight, the detection alone, and the
    sampling of a long clip (the flight looped to 10x its length) by seeking.
    """
    parser = make_parser(SUITE, None, overlay_command.__doc__)
    parser.add_argument("--workdir", type=Path, default=DEFAULT_WORKDIR)
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--estimators", nargs="+", default=["lstm", "orb"])
    parser.add_argument("--overlays", default="logo,timestamp")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--cost-only", action="store_true", help="only the detector's cost (on the first seed's flight)")
    parser.add_argument("--no-cost", action="store_true", help="skip the detector's cost")
    parser.add_argument("--no-track", action="store_true", help="stitch only: skip the pairwise track and its MACE")
    parser.add_argument("--runs", default=",".join(DEFAULT_RUNS), help="which of the runs, comma-separated: " + ", ".join(r[0] for r in RUNS))
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    args.runs = [r.strip() for r in args.runs.split(",")]
    unknown = set(args.runs) - {r[0] for r in RUNS}
    if unknown:
        parser.error(f"unknown --runs {', '.join(sorted(unknown))}")
    args.workdir.mkdir(parents=True, exist_ok=True)
    results: dict = {"load_average_at_start": os.getloadavg()[0], "rows": []}
    burned = None
    for seed in args.seeds:
        clean, burned = flights(args.workdir, args.frames, seed, args.overlays)
        if args.cost_only:
            break
        for estimator in args.estimators:
            results["rows"] += accuracy(args, clean, burned, estimator)
    _paired_summary(results["rows"])
    if not args.no_cost:
        results["detector cost"] = detector_cost(args, burned)
    runs = "" if tuple(args.runs) == DEFAULT_RUNS else f" --runs {','.join(args.runs)}"
    flags = "".join(f" --{f}" for f in ("no-track", "no-cost") if getattr(args, f.replace("-", "_")))
    command = (f"python -m benchmarks overlay --frames {args.frames} --seeds {' '.join(map(str, args.seeds))} "
               + (f"--cost-only --repeat {args.repeat}" if args.cost_only else f"--estimators {' '.join(args.estimators)}")
               + f" --overlays {args.overlays}{runs}{flags}")
    print(f"  reproduce: {command}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=float))


# -- python -m benchmarks overlay mask -------------------------------------------------------------

NEAR = 32  # px: hidden ground farther than this from every overlay is counted as "elsewhere"


def burned_flight(workdir: Path, frames: int, seed: int, overlays: str) -> tuple[Path, dict[str, np.ndarray]]:
    """The burned-in flight (cached; the file ``python -m benchmarks overlay`` renders) and each
    overlay's drawn pixels."""
    known = ORTHOPHOTO.exists()
    ground = load_map(ORTHOPHOTO if known else None, seed=seed)
    plan = plan_flight((ground.shape[1], ground.shape[0]), "survey", frames, SIZE, seed)
    spec = OverlaySpec.parse(overlays)
    path = workdir / f"survey_{SIZE[0]}x{SIZE[1]}_{frames}_s{seed}_{overlays.replace(',', '+')}.mp4"
    if not path.exists():
        write_flight(path, ground, plan, map_name=ORTHOPHOTO.name if known else "procedural", preset="veryfast",
                     show_progress=False, overlays=spec)
    burner = OverlayBurner(spec, SIZE, plan.fps)
    blank = np.zeros((SIZE[1], SIZE[0], 3), np.uint8)
    for t in range(plan.frames):
        burner.draw(blank, t)
    written = cv2.imread(str(path.with_name(path.stem + ".mask.png")), cv2.IMREAD_GRAYSCALE)
    assert np.array_equal(written == 0, burner.drawn), "the replayed burner disagrees with the written mask"
    return path, burner.kinds()


def score(masked: np.ndarray, kinds: dict[str, np.ndarray]) -> dict[str, dict]:
    """Per overlay: drawn, missed, hidden ground (nearest overlay), IoU; and ``elsewhere``."""
    names = list(kinds)
    drawn = np.zeros_like(masked)
    for m in kinds.values():
        drawn |= m
    # Distance of every pixel to each overlay's drawn pixels: the nearest one owns it.
    distances = np.stack([cv2.distanceTransform(np.where(kinds[k], 0, 255).astype(np.uint8), cv2.DIST_L2, 5) for k in names])
    nearest = distances.argmin(axis=0)
    far = distances.min(axis=0) > NEAR
    out = {}
    for i, k in enumerate(names):
        own = (nearest == i) & ~far
        counted = masked & own
        hidden = counted & ~drawn
        missed = kinds[k] & ~masked
        union = np.count_nonzero(counted | kinds[k])
        out[k] = {"overlay px": int(kinds[k].sum()), "masked px": int(counted.sum()), "missed px": int(missed.sum()),
                  "hidden ground px": int(hidden.sum()), "IoU": float(np.count_nonzero(counted & kinds[k]) / max(union, 1))}
    out["elsewhere"] = {"hidden ground px": int(np.count_nonzero(masked & far & ~drawn))}
    union = np.count_nonzero(masked | drawn)
    out["all"] = {"overlay px": int(drawn.sum()), "masked px": int(masked.sum()), "missed px": int(np.count_nonzero(drawn & ~masked)),
                  "hidden ground px": int(np.count_nonzero(masked & ~drawn)), "IoU": float(np.count_nonzero(masked & drawn) / max(union, 1)),
                  "masked %": 100.0 * float(masked.mean()), "overlay %": 100.0 * float(drawn.mean())}
    return out


def cost(path: Path, repeat: int) -> dict:
    info = probe(path)
    wall, cpu = [], []
    for _ in range(repeat):
        clock, used = time.perf_counter(), cpu_seconds()
        frame_mask(path, MaskOptions(), info)
        wall.append(time.perf_counter() - clock)
        cpu.append(cpu_seconds() - used)
    o = OverlayOptions()
    import mosaic_cli.overlay as overlay

    # As frame_mask reads them (the detector before tracing read them at its working width).
    width = overlay.sample_width(info.source_size, o) if hasattr(overlay, "sample_width") else min(o.width, info.source_size[0])
    frames = sample_frames(path, o.samples, width, info)
    alone, alone_cpu = [], []
    for _ in range(repeat):
        clock, used = time.perf_counter(), time.process_time()
        detect_overlays(frames, info.source_size, o)
        alone.append(time.perf_counter() - clock)
        alone_cpu.append(time.process_time() - used)
    n = info.frame_count
    return {"sample + detect ms per clip frame (wall)": 1000 * float(np.median(wall)) / n,
            "sample + detect ms per clip frame (CPU, ffmpeg included)": 1000 * float(np.median(cpu)) / n,
            "detect alone ms per sampled frame (wall)": 1000 * float(np.median(alone)) / len(frames),
            "detect alone ms per sampled frame (CPU)": 1000 * float(np.median(alone_cpu)) / len(frames)}


def mask_command(argv: list[str] | None = None) -> int | None:
    """How tight the overlay detector's mask is, per overlay, against the simulator's exact pixels
    (docs/measurements/stitch.md, "Burned-in overlays").

        python -m benchmarks overlay mask                       # seeds 1-6, logo+timestamp and all
        python -m benchmarks overlay mask --seeds 1 --overlays all --repeat 1

    Each seed's survey flight (1280x720, 600 frames, over the NEON orthophoto in ../shared/data
    when present, a procedural map otherwise; the same plans as ``python -m benchmarks overlay``) is
    rendered with overlays burned in, and the burner is replayed frame by frame for each overlay's
    own pixels (``OverlayBurner.kinds``: every pixel it drew in some frame).  Then
    ``frame_mask`` (sampling plus detection, as every command runs it) and, per overlay:

    * overlay px: what it drew; missed: of those, not masked (the panorama can show them);
    * hidden ground: masked pixels that no overlay drew, each counted for the overlay nearest to it
      (``elsewhere`` beyond 32 px of any);
    * IoU: the masked pixels counted for the overlay against its drawn ones.

    And the detector's cost: sampling plus detection per frame of the clip, and the detection
    alone per sampled frame (median of ``--repeat``; CPU time, ffmpeg's included, is the figure to
    read on a loaded machine).
    """
    parser = make_parser(SUITE, 'mask', mask_command.__doc__)
    parser.add_argument("--workdir", type=Path, default=DEFAULT_WORKDIR)
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    parser.add_argument("--overlays", nargs="+", default=["logo,timestamp", "all"])
    parser.add_argument("--repeat", type=int, default=3, help="timing repeats (0: no timing)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    args.workdir.mkdir(parents=True, exist_ok=True)
    rows = []
    for overlays in args.overlays:
        for seed in args.seeds:
            path, kinds = burned_flight(args.workdir, args.frames, seed, overlays)
            mask = frame_mask(path, MaskOptions())
            masked = np.zeros(next(iter(kinds.values())).shape, bool) if mask.use is None else mask.use == 0
            row = {"overlays": overlays, "seed": seed, "score": score(masked, kinds)}
            if args.repeat > 0:
                row["cost"] = cost(path, args.repeat)
            rows.append(row)
            s = row["score"]
            line = "  ".join(f"{k}: IoU {v['IoU']:.2f} hidden {v['hidden ground px']} missed {v['missed px']} of {v['overlay px']}"
                             for k, v in s.items() if k not in ("all", "elsewhere"))
            print(f"{overlays:15s} seed {seed}  masked {s['all']['masked %']:.2f}% for {s['all']['overlay %']:.2f}% drawn  "
                  f"IoU {s['all']['IoU']:.2f}  missed {s['all']['missed px']}  |  {line}  elsewhere {s['elsewhere']['hidden ground px']}"
                  + (f"  |  {row['cost']['sample + detect ms per clip frame (CPU, ffmpeg included)']:.2f} CPU ms/frame, detect "
                     f"{row['cost']['detect alone ms per sampled frame (CPU)']:.2f} CPU ms/sample" if "cost" in row else ""), flush=True)
    for overlays in args.overlays:
        group = [r["score"] for r in rows if r["overlays"] == overlays]
        kinds = [k for k in group[0] if k != "elsewhere"]
        print(f"{overlays}: mean over {len(group)} flights")
        for k in kinds:
            v = {f: float(np.mean([g[k][f] for g in group])) for f in group[0][k]}
            print(f"  {k:10s} overlay {v['overlay px']:8.0f} px  masked {v['masked px']:8.0f}  hidden ground {v['hidden ground px']:8.0f}  "
                  f"missed {v['missed px']:6.1f} (worst {max(g[k]['missed px'] for g in group)})  IoU {v['IoU']:.3f}")
        print(f"  elsewhere  hidden ground {np.mean([g['elsewhere']['hidden ground px'] for g in group]):.0f} px")
        costs = [r["cost"] for r in rows if r["overlays"] == overlays and "cost" in r]
        if costs:
            print("  " + ", ".join(f"{k} {np.median([c[k] for c in costs]):.2f}" for k in costs[0]))
    print(f"  reproduce: python -m benchmarks overlay mask --frames {args.frames} --seeds {' '.join(map(str, args.seeds))} "
          f"--overlays {' '.join(args.overlays)} --repeat {args.repeat}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


COMMANDS = {
    "mask": mask_command,
}


def main(argv: list[str]) -> int:
    return run_commands(SUITE, __doc__, COMMANDS, argv, default=overlay_command)
