"""Rolling shutter: ``--rolling-shutter`` of stabilize (and vid.stab) and of stitch on simulated flights, and auto's probe."""

from __future__ import annotations

import itertools
import os
import subprocess
import time
from pathlib import Path

import imageio_ffmpeg
import numpy as np

import mosaic_cli.stitch.scan as stitch_scan
from benchmarks.common import cpu_seconds, make_parser, run_commands
from mosaic_cli.estimators import make_estimator
from mosaic_cli.estimators.rolling import AUTO_PROBE_FRAMES, PROBE_CORNERS, PROBE_READOUTS, RollingProbe
from mosaic_cli.geometry import project
from mosaic_cli.geometry.rolling_shutter import band_centres, estimate_readout
from mosaic_cli.simulate import GroundTruth, RollingShutter, SimulateOptions, load_ground_truth, parse_vibration, simulate_flight
from mosaic_cli.stabilize import StabilizeOptions, stabilize
from mosaic_cli.stabilize.metrics import ground_truth_jitter
from mosaic_cli.stabilize.rolling import RollingCorrection
from mosaic_cli.stabilize.wobble import ground_truth_band_placement, ground_truth_wobble, video_wobble
from mosaic_cli.stitch import StitchOptions, stitch
from mosaic_cli.video import open_video, probe

SUITE = "rolling-shutter"


# -- python -m benchmarks rolling-shutter ----------------------------------------------------------

FFMPEG = imageio_ffmpeg.get_ffmpeg_exe()
# (readout, vibration Hz, vibration px at 1280 wide, profile)
STABILIZE_FLIGHTS = [(0.5, 15.0, 3.0, "paper"), (0.7, 12.0, 4.0, "paper"), (0.9, 8.0, 5.0, "paper"), (0.7, 20.0, 3.0, "fast"),
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


def stabilize_command(argv: list[str] | None = None) -> int | None:
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

        python -m benchmarks rolling-shutter --out /tmp/rsbench [--frames 120] [--size 1280x720]

    Broadband vibration (issue 41): ``--vibration SPEC`` flies ``--readouts`` (default 0.5, 0.7,
    0.9 and a global-shutter twin, 0) with that ``mosaic simulate --vibration`` instead of the
    one-tone flights, e.g. ``--vibration noise:10-25,2.5,0.25`` or ``--vibration 12,2+31,1``;
    ``--map IMAGE`` flies over an image instead of the procedural map (``--profile`` their path).
    ``--truth`` adds the corrections' error against the simulator's (each band's row points moved
    by the estimated correction and by the true one, RMS px), and ``auto`` with the true readout given.
    """
    parser = make_parser(SUITE, None, stabilize_command.__doc__)
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
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    flights = [(readout, RollingShutter(readout, hz, px), f"{profile} R{readout:g} {hz:g}Hz {px:g}px",
                f"{profile}_r{readout:g}_{hz:g}hz_{px:g}px", profile) for readout, hz, px, profile in STABILIZE_FLIGHTS]
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


# -- python -m benchmarks rolling-shutter probe ----------------------------------------------------

PROBE_WIDTH = 320  # the default estimator's (lstm) frames, which the probe rides on


def separation(clips: list[Path], width: int = PROBE_WIDTH) -> None:
    """`auto`'s probe as stabilize, stitch and track run it (:class:`RollingProbe` on the first
    ``AUTO_PROBE_FRAMES`` frames, decoded ``width`` wide and gray: the default estimator's
    tracking pass), its readout and the cost of readout 0 against the best over ``PROBE_READOUTS``;
    CPU seconds of its tracking and of the readouts."""
    print(f"probe: {AUTO_PROBE_FRAMES} frames at {width} px, {PROBE_CORNERS} corners, readouts {PROBE_READOUTS}")
    for clip in clips:
        info = probe(clip)
        rolling_probe = RollingProbe(info)
        cpu = 0.0
        with open_video(clip, width=width, gray=True, info=info) as frames:
            for frame in itertools.islice(frames, AUTO_PROBE_FRAMES):
                clock = time.process_time()
                rolling_probe.push(frame)
                cpu += time.process_time() - clock
        rolling_probe.finish()
        motion, weights = rolling_probe.measured().arrays()
        clock = time.process_time()
        readout, costs = estimate_readout(motion, info.source_size[1], weights, PROBE_READOUTS)
        fit = time.process_time() - clock
        print(f"{clip.name:<40} readout {readout:.2f} (x{costs[0] / costs.min():.1f} at 0); CPU: tracking "
              f"{1000 * cpu / max(len(motion), 1):.1f} ms a pair, readouts {1000 * fit:.0f} ms", flush=True)


def overhead(out: Path, lengths: list[int], rounds: int = 1) -> None:
    out.mkdir(parents=True, exist_ok=True)
    print(f"probe: {AUTO_PROBE_FRAMES} frames")
    for frames in lengths:
        clip = out / f"gs_paper_{frames}.mp4"
        if not clip.exists():
            simulate_flight(clip, None, SimulateOptions(profile="paper", frames=frames, size=(1280, 720), seed=4), show_progress=False)
        stabilize(clip, clip.with_suffix(".warm.mp4"), StabilizeOptions(rolling_shutter="off"), show_progress=False)  # imports, caches
        runs = []
        for mode in ("off", "auto", "auto", "off") * rounds:
            clock = cpu_seconds()
            result = stabilize(clip, clip.with_suffix(f".{mode}.mp4"), StabilizeOptions(rolling_shutter=mode), show_progress=False)
            s = result.seconds
            runs.append((mode, s.get("rolling", 0.0), s.get("rolling_cpu", 0.0), s["total"], cpu_seconds() - clock, os.getloadavg()[0]))
        off = [r for r in runs if r[0] == "off"]
        auto = [r for r in runs if r[0] == "auto"]

        def spread(values: list[float], digits: int = 2) -> str:
            return f"{min(values):.{digits}f}-{max(values):.{digits}f}"

        mean = lambda rows, i: sum(r[i] for r in rows) / len(rows)  # noqa: E731
        print(f"{frames:>5} frames: probe {spread([r[1] for r in auto])} s wall, {spread([r[2] for r in auto])} s CPU; "
              f"whole run CPU off {spread([r[4] for r in off])}, auto {spread([r[4] for r in auto])} s "
              f"(means: auto - off {mean(auto, 4) - mean(off, 4):+.2f} s, probe CPU / off CPU {100 * mean(auto, 2) / mean(off, 4):.1f}%); "
              f"wall off {spread([r[3] for r in off])}, auto {spread([r[3] for r in auto])} s "
              f"(means {100 * (mean(auto, 3) / mean(off, 3) - 1):+.1f}%); load {spread([r[5] for r in runs], 1)}", flush=True)


def probe_command(argv: list[str] | None = None) -> int | None:
    """``--rolling-shutter auto``'s probe: does it tell rolling from global shutters, and what does it cost?

    * ``separation CLIP... [--width 320]``: `auto`'s probe on each clip's first frames as the
      tracking pass decodes them, then the readout and the cost of readout 0 against the best
      (``estimate_readout``; a global shutter under ``GLOBAL_COST_RATIO``), and its CPU time;
    * ``overhead --out DIR``: global-shutter clips of 120, 600 and 1200 frames at 1280x720
      (simulated once), ``stabilize`` with ``--rolling-shutter off`` and ``auto`` in A-B-B-A order
      (``--rounds`` times, after one warm-up run): the probe's own seconds and CPU seconds (its
      thread's), each whole run's CPU seconds (the process's threads and its ffmpeg children) and
      wall seconds (say whether the machine was shared: CPU seconds suffer less from it).

        python -m benchmarks rolling-shutter probe separation /tmp/rs/*.mp4 [--width 320]
        python -m benchmarks rolling-shutter probe overhead --out /tmp/rsprobe [--frames 120 600 1200] [--rounds 2]
    """
    parser = make_parser(SUITE, 'probe', probe_command.__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sep = sub.add_parser("separation")
    sep.add_argument("clips", type=Path, nargs="+")
    sep.add_argument("--width", type=int, default=PROBE_WIDTH, help="frames decoded this wide (the estimator's; default: lstm's 320)")
    ov = sub.add_parser("overhead")
    ov.add_argument("--out", type=Path, required=True)
    ov.add_argument("--frames", type=int, nargs="+", default=[120, 600, 1200])
    ov.add_argument("--rounds", type=int, default=1, help="off, auto, auto, off this many times")
    args = parser.parse_args(argv)
    if args.command == "separation":
        separation(args.clips, args.width)
    else:
        overhead(args.out, args.frames, args.rounds)


# -- python -m benchmarks rolling-shutter stitch ---------------------------------------------------

# (readout, vibration Hz, vibration px at 1280 wide, profile)
STITCH_FLIGHTS = [(0.5, 15.0, 3.0, "fast"), (0.7, 12.0, 4.0, "fast"), (0.9, 8.0, 5.0, "fast"), (0.7, 20.0, 3.0, "fast"),
           (0.7, 12.0, 4.0, "paper"), (0.0, 12.0, 4.0, "fast")]


def truth_corrections(gt: GroundTruth) -> RollingCorrection:
    """Each band's correction channels fitted (least squares) to the truth's band -> mid-time homography."""
    assert gt.row_bands is not None
    w, h = gt.size
    K = gt.row_bands.shape[1]
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    out = np.zeros((gt.frames, K, 4))
    xs = np.linspace(0, w - 1, 9)
    for t in range(gt.frames):
        for k, yk in enumerate(band_centres(h, K)):
            p = np.stack([xs, np.full(9, yk)], 1)
            d = project(gt.map_to_frame[t] @ np.linalg.inv(gt.row_bands[t, k]), p) - p
            x, y = p[:, 0] - cx, p[:, 1] - cy
            one, zero = np.ones_like(x), np.zeros_like(x)
            A = np.concatenate([np.stack([one, zero, -y, x], 1), np.stack([zero, one, x, y], 1)])
            out[t, k] = np.linalg.lstsq(A, np.concatenate([d[:, 0], d[:, 1]]), rcond=None)[0]
    return RollingCorrection(gt.readout, out, gt.size, False)


def stitch_command(argv: list[str] | None = None) -> int | None:
    """Benchmark ``mosaic stitch --rolling-shutter`` on simulated rolling-shutter flights.

    For each flight (``mosaic simulate --rolling-shutter R --vibration HZ,PX``, and a global-shutter
    one), stitch with ``--rolling-shutter off`` and ``auto`` and score where the panorama drew each
    keyframe's row bands against the simulator's truth
    (``stabilize.wobble.ground_truth_band_placement``: points along each band's centre row, the
    map -> panorama gauge fitted to each panorama); print one table:

    * readout: the flight's, and what ``auto`` read;
    * band placement, px: RMS (``rms``) and with each keyframe's mean shift taken out (``shape``);
    * seconds: wall time of off and auto (the machine may be shared: say so with the figures);
    * ``--truth``: also the stitch with the truth's corrections in place of the estimate (each
      band's similarity fitted to the simulator's band -> mid-time homography): what is left when
      the corrections are exact.

        python -m benchmarks rolling-shutter stitch --out /tmp/rsstitch [--frames 200] [--size 640x360] [--estimator orb]
    """
    parser = make_parser(SUITE, 'stitch', stitch_command.__doc__)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--estimator", default="orb")
    parser.add_argument("--truth", action="store_true", help="also stitch with the truth's corrections")
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    head = (f"{'flight':<26} {'R':>4} {'auto':>5} {'keys':>4} | {'rms off':>7} {'auto':>6} {'ratio':>6} | "
            f"{'shape off':>9} {'auto':>6} {'ratio':>6} | {'s off':>6} {'auto':>6}" + (f" | {'rms truth':>9}" if args.truth else ""))
    print(head)
    print("-" * len(head))
    for readout, hz, px, profile in STITCH_FLIGHTS:
        name = f"{profile} R{readout:g} {hz:g}Hz {px:g}px"
        clip = args.out / f"{profile}_r{readout:g}_{hz:g}hz_{px:g}px_{size[0]}_{args.frames}.mp4"
        if not clip.exists():
            simulate_flight(clip, None, SimulateOptions(profile=profile, frames=args.frames, size=size, seed=args.seed,
                                                        rolling=RollingShutter(readout, hz, px)), show_progress=False)
        gt = load_ground_truth(clip)
        assert gt.row_bands is not None
        scores = {}
        for mode in ("off", "auto"):
            start = time.perf_counter()
            result = stitch(clip, clip.with_suffix(f".{mode}.png"), make_estimator(args.estimator), StitchOptions(rolling_shutter=mode),
                            show_progress=False)
            seconds = time.perf_counter() - start
            pano = result.panoramas[0]
            score = ground_truth_band_placement(gt.row_bands, gt.map_to_frame, gt.size, pano.transforms, pano.bands)
            rs = result.rolling
            scores[mode] = dict(**score, seconds=seconds, keys=len(pano.transforms), readout=rs.readout if rs is not None else float("nan"))
        truth = ""
        if args.truth and gt.readout > 0:
            plan = stitch_scan.plan_rolling
            exact = truth_corrections(gt)
            stitch_scan.plan_rolling = lambda *a, exact=exact, **k: exact  # the stitch's one call of it
            try:
                result = stitch(clip, clip.with_suffix(".truth.png"), make_estimator(args.estimator),
                                StitchOptions(rolling_shutter=gt.readout), show_progress=False)
            finally:
                stitch_scan.plan_rolling = plan
            pano = result.panoramas[0]
            truth = f" | {ground_truth_band_placement(gt.row_bands, gt.map_to_frame, gt.size, pano.transforms, pano.bands)['rms']:>9.3f}"
        off, auto = scores["off"], scores["auto"]
        print(f"{name:<26} {readout:>4.2f} {auto['readout']:>5.2f} {off['keys']:>4d} | {off['rms']:>7.3f} {auto['rms']:>6.3f} "
              f"{auto['rms'] / off['rms']:>6.3f} | {off['shape']:>9.3f} {auto['shape']:>6.3f} {auto['shape'] / off['shape']:>6.3f} | "
              f"{off['seconds']:>6.1f} {auto['seconds']:>6.1f}" + truth, flush=True)


COMMANDS = {
    "probe": probe_command,
    "stitch": stitch_command,
}


def main(argv: list[str]) -> int:
    return run_commands(SUITE, __doc__, COMMANDS, argv, default=stabilize_command)
