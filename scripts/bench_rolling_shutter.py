"""Benchmark ``mosaic stabilize --rolling-shutter`` on simulated rolling-shutter flights.

For each flight (``mosaic simulate --rolling-shutter R --vibration HZ,PX``, and global-shutter
ones), stabilise with ``--rolling-shutter off`` and ``auto`` and run vid.stab (vidstabdetect +
vidstabtransform in the imageio-ffmpeg binary, its defaults); print one table:

* readout: the flight's, and what ``auto`` read;
* wobble (exact): ``stabilize.wobble.ground_truth_wobble`` of the output, px (vid.stab has no
  warps to score exactly);
* wobble (pixels): ``stabilize.wobble.video_wobble`` of each output video, px;
* jitter: ``metrics.ground_truth_jitter`` of off and auto, px;
* seconds: wall time of off and auto (the machine may be shared: say so with the figures).

    python scripts/bench_rolling_shutter.py --out /tmp/rsbench [--frames 120] [--size 1280x720]

Broadband vibration (issue 41): ``--vibration SPEC`` flies ``--readouts`` (default 0.5, 0.7,
0.9 and a global-shutter twin, 0) with that ``mosaic simulate --vibration`` instead of the
one-tone flights, e.g. ``--vibration noise:10-25,2.5,0.25`` or ``--vibration 12,2+31,1``;
``--map IMAGE`` flies over an image instead of the procedural map (``--profile`` their path).
``--truth`` adds the corrections' error against the simulator's (each band's row points moved
by the estimated correction and by the true one, RMS px), and ``auto`` with the true readout given.
"""

from __future__ import annotations

import argparse
import subprocess
import time
from pathlib import Path

import imageio_ffmpeg
import numpy as np

from mosaic_cli.geometry import project
from mosaic_cli.geometry.rolling_shutter import band_centres
from mosaic_cli.simulate import RollingShutter, SimulateOptions, load_ground_truth, parse_vibration, simulate_flight
from mosaic_cli.stabilize import StabilizeOptions, stabilize
from mosaic_cli.stabilize.metrics import ground_truth_jitter
from mosaic_cli.stabilize.wobble import ground_truth_wobble, video_wobble

FFMPEG = imageio_ffmpeg.get_ffmpeg_exe()
# (readout, vibration Hz, vibration px at 1280 wide, profile)
FLIGHTS = [(0.5, 15.0, 3.0, "paper"), (0.7, 12.0, 4.0, "paper"), (0.9, 8.0, 5.0, "paper"), (0.7, 20.0, 3.0, "fast"),
           (0.0, 12.0, 4.0, "paper"), (0.0, 0.0, 0.0, "shaky")]


def run_vidstab(clip: Path, out: Path) -> None:
    clip, out = clip.resolve(), out.resolve()
    trf = out.with_suffix(".trf")
    subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-y", "-i", str(clip), "-vf",
                    f"vidstabdetect=result={trf.name}", "-f", "null", "-"], check=True, cwd=out.parent)
    subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-y", "-i", str(clip), "-vf", f"vidstabtransform=input={trf.name}",
                    "-c:v", "libx264", "-preset", "veryfast", "-crf", "18", "-pix_fmt", "yuv420p", str(out)], check=True, cwd=out.parent)


def correction_error(gt, rs) -> float:
    """RMS px between each band's centre-row points moved by the estimated correction
    (``rs``: a RollingCorrection, or None: none) and by the truth's (band -> mid-time pose)."""
    w, h = gt.size
    K = gt.row_bands.shape[1]
    rows = band_centres(h, K)
    xs = np.linspace(0.05 * w, 0.95 * w, 9)
    errors = []
    for t in range(gt.frames):
        for k, yk in enumerate(rows):
            pts = np.stack([xs, np.full(9, yk)], 1)
            true = project(gt.map_to_frame[t] @ np.linalg.inv(gt.row_bands[t, k]), pts)
            moved = pts if rs is None or not rs.applied else rs.correct_points(t, pts)
            errors.append(np.sum((moved - true) ** 2, axis=1))
    return float(np.sqrt(np.mean(errors)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--no-vidstab", action="store_true")
    parser.add_argument("--vibration", help="fly --readouts with this --vibration of mosaic simulate instead of the one-tone flights")
    parser.add_argument("--readouts", default="0.5,0.7,0.9,0", help="with --vibration (0: a global-shutter twin)")
    parser.add_argument("--profile", default="paper", help="with --vibration")
    parser.add_argument("--map", type=Path, help="an aerial image to fly over (default: the procedural map)")
    parser.add_argument("--truth", action="store_true", help="the corrections' error against the truth; auto with the true readout")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    flights = [(readout, RollingShutter(readout, hz, px), f"{profile} R{readout:g} {hz:g}Hz {px:g}px",
                f"{profile}_r{readout:g}_{hz:g}hz_{px:g}px", profile) for readout, hz, px, profile in FLIGHTS]
    if args.vibration:
        tag = args.vibration.replace(":", "").replace(",", "_").replace("+", "p")
        flights = [(r, RollingShutter(r, *parse_vibration(args.vibration)), f"{args.profile} R{r:g} {args.vibration}",
                    f"{args.profile}_r{r:g}_{tag}", args.profile) for r in (float(v) for v in args.readouts.split(","))]
    map_tag = "" if args.map is None else "_" + args.map.stem
    args.out.mkdir(parents=True, exist_ok=True)
    head = (f"{'flight':<26} {'R':>4} {'auto':>5} | {'wobble exact off':>16} {'auto':>6} {'ratio':>6} | "
            f"{'pixels off':>10} {'auto':>6} {'ratio':>6} {'vid.stab':>8} | {'jitter off':>10} {'auto':>6} | {'s off':>6} {'auto':>6}")
    if args.truth:
        head += f" | {'corr err off':>12} {'auto':>6} {'true R':>6} {'wobble true R':>13}"
    print(head)
    print("-" * len(head))
    for readout, rolling, name, stem, profile in flights:
        clip = args.out / f"{stem}_{size[0]}{map_tag}_s{args.seed}_n{args.frames}.mp4"
        if not clip.exists():
            simulate_flight(clip, args.map, SimulateOptions(profile=profile, frames=args.frames, size=size, seed=args.seed,
                                                            rolling=rolling), show_progress=False)
        gt = load_ground_truth(clip)
        scores = {}
        modes = ("off", "auto") + ((readout,) if args.truth and readout > 0 else ())
        for mode in modes:
            out = clip.with_suffix(f".{mode}.mp4")
            start = time.perf_counter()
            result = stabilize(clip, out, StabilizeOptions(rolling_shutter=mode), show_progress=False)
            seconds = time.perf_counter() - start
            rs = result.rolling
            wobble = float("nan")
            if gt.row_bands is not None:
                bands = None
                if rs is not None and rs.applied:
                    bands = rs.band_warps(result.warps, band_centres(gt.size[1], gt.row_bands.shape[1]))
                wobble = ground_truth_wobble(gt.row_bands, gt.map_to_frame, gt.size, result.warps, bands)
            scores[mode] = dict(wobble=wobble, pixels=video_wobble(out), seconds=seconds,
                                jitter=ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, gt.size, gt.fps, result.warps),
                                readout=rs.readout if rs is not None else float("nan"),
                                error=correction_error(gt, rs) if args.truth and gt.row_bands is not None else float("nan"))
        vidstab = float("nan")
        if not args.no_vidstab:
            vs_out = clip.with_suffix(".vidstab.mp4")
            run_vidstab(clip, vs_out)
            vidstab = video_wobble(vs_out)
        off, auto = scores["off"], scores["auto"]
        ratio = auto["wobble"] / off["wobble"] if off["wobble"] > 0 else float("nan")
        pixel_ratio = auto["pixels"] / off["pixels"] if off["pixels"] > 0 else float("nan")
        line = (f"{name:<26} {readout:>4.2f} {auto['readout']:>5.2f} | {off['wobble']:>16.3f} {auto['wobble']:>6.3f} {ratio:>6.3f} | "
                f"{off['pixels']:>10.3f} {auto['pixels']:>6.3f} {pixel_ratio:>6.3f} {vidstab:>8.3f} | {off['jitter']:>10.3f} "
                f"{auto['jitter']:>6.3f} | {off['seconds']:>6.1f} {auto['seconds']:>6.1f}")
        if args.truth:
            given = scores.get(readout, dict(error=float("nan"), wobble=float("nan")))
            line += f" | {off['error']:>12.3f} {auto['error']:>6.3f} {given['error']:>6.3f} {given['wobble']:>13.3f}"
        print(line, flush=True)


if __name__ == "__main__":
    main()
