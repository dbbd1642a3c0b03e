"""Georeferencing accuracy of ``mosaic stitch --telemetry`` on simulated flights with exact truth.

    python -m benchmarks georef mapping   # long mapping flights (5 cm GSD, 3 m RMS GPS, 2% dropouts)
    python -m benchmarks georef short     # the simulator's own short profiles (what the GPS allows)
    python -m benchmarks georef all
    python -m benchmarks georef refit     # the current georeferencing re-applied to the last
                                             # mapping stitch's registered placements (no re-stitch)
    python -m benchmarks georef gps-limit # the scale and heading the GPS alone allows on that flight

A mapping flight: a procedural map of 8192x1536 px at 5 cm per pixel (410 x 77 m), a 640x360
camera (focal length = frame width, so 32 m above the ground for 5 cm per frame pixel) flying
four lawnmower lines 9 m apart (50% side overlap) at 6 m/s, with the simulator's slight
tilt and sway, filmed at 10 frames/s.  Its DJI SRT log carries 3 m RMS GPS error (correlated
over 2 s), 2% dropouts and 0.5% bad fixes 20-60 m off.  The stitch is scored against the
truth: the ground error of a 5x5 grid of pixels of every keyframe, and the scale and heading
of the whole mosaic (see mosaic_cli/geo/score.py).  The COG is validated with rio-cogeo and
its CRS and bounds read back with rasterio.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import ROOT, make_parser
from mosaic_cli.geo.score import score_files
from mosaic_cli.simulate import FlightPlan, load_ground_truth, procedural_map, write_flight
from mosaic_cli.simulate.telemetry import GpsErrors, MapGeo, write_telemetry
from mosaic_cli.simulate.trajectory import camera_homography, smooth_signal

SUITE = "georef"
DEFAULT_WORKDIR = ROOT / ".dev" / "bench_georef"
ORIGIN = (47.3977, 8.5456)
GSD = 0.05


def mapping_plan(map_size, size=(640, 360), seed=0, fps=10.0, speed=6.0, lines=4, spacing_m=9.0) -> FlightPlan:
    """Lawnmower lines along the map's x axis at constant height and speed (see module doc)."""
    rng = np.random.default_rng([seed, 31])
    W, H = map_size
    w, h = size
    focal = float(w)
    s = 1.0  # map pixels per frame pixel: frame GSD = map GSD
    spacing = spacing_m / GSD
    margin = 0.5 * math.hypot(w, h) * s * 1.15 + 20
    x0, x1 = margin, W - 1 - margin
    y_first = (H - (lines - 1) * spacing) / 2
    pts = []
    for j in range(lines):
        y = y_first + j * spacing
        xs = np.linspace(x0, x1, 400) if j % 2 == 0 else np.linspace(x1, x0, 400)
        pts.append(np.stack([xs, np.full_like(xs, y)], 1))
        if j + 1 < lines:  # half-circle turn to the next line
            cx = xs[-1]
            side = 1.0 if j % 2 == 0 else -1.0
            ang = np.linspace(-np.pi / 2, np.pi / 2, 40)[1:-1]
            pts.append(np.stack([cx + side * spacing / 2 * np.cos(ang), y + spacing / 2 + spacing / 2 * np.sin(ang)], 1))
    poly = np.vstack(pts)
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    step = speed / fps / GSD
    n = int(cum[-1] // step) + 1
    d = np.arange(n) * step
    X, Y = np.interp(d, cum, poly[:, 0]), np.interp(d, cum, poly[:, 1])
    tilt_dir = rng.uniform(0, 2 * np.pi)
    tilt0 = np.radians(rng.uniform(0.5, 1.5))
    sway = np.radians(1.0)
    pitch = tilt0 * np.cos(tilt_dir) + sway * smooth_signal(rng, n, fps, (20, 60))
    roll = tilt0 * np.sin(tilt_dir) + sway * smooth_signal(rng, n, fps, (20, 60))
    heading = np.radians(2.0) * smooth_signal(rng, n, fps, (20, 60))
    alt = s * (1 + 0.03 * smooth_signal(rng, n, fps, (20, 60)))
    M = np.stack([camera_homography(size, focal, X[t], Y[t], alt[t], heading[t], pitch[t], roll[t]) for t in range(n)])
    return FlightPlan(M, M.copy(), size, "mapping", seed, (W, H), fps)


def mapping_flight(workdir: Path, seed: int, fmt: str = "srt") -> Path:
    path = workdir / f"mapping_s{seed}.mp4"
    if not path.exists() or not path.with_name(path.stem + ".geo.json").exists():
        ground = procedural_map((8192, 1536), seed=seed)
        plan = mapping_plan((ground.shape[1], ground.shape[0]), seed=seed)
        gt = write_flight(path, ground, plan, fps=plan.fps, crf=20, preset="veryfast", show_progress=False)
        geo = MapGeo.from_origin(*ORIGIN, GSD, gt.map_size)
        write_telemetry(path, gt, geo, fmt, GpsErrors(rms=3.0, dropouts=0.02, bad_fixes=0.005, seed=seed))
    return path


def run_stitch(video: Path, telemetry: Path, extra: list[str] = ()) -> dict:
    tif = video.with_suffix(".map.tif")
    transforms = video.with_suffix(".map.json")
    footprints = video.with_suffix(".footprints.geojson")
    # the stitch runs through this suite so that the registered placements are kept for refit
    cmd = [sys.executable, "-m", "benchmarks", "georef", "record-stitch", str(video.with_suffix(".placements.npz")),
           "stitch", str(video), "--telemetry", str(telemetry), "-o", str(tif),
           "--transforms", str(transforms), "--footprints", str(footprints), "-q", *extra]
    clock = time.perf_counter()
    subprocess.run(cmd, check=True)
    seconds = time.perf_counter() - clock
    gt = load_ground_truth(video)
    score = score_files(transforms, gt, video.with_name(video.stem + ".geo.json"))
    valid = subprocess.run(["rio", "cogeo", "validate", str(tif)], capture_output=True, text=True)
    import rasterio

    with rasterio.open(tif) as ds:
        crs, bounds = ds.crs.to_string(), ds.bounds
    truth = json.loads(video.with_name(video.stem + ".geo.json").read_text())
    return {"score": score, "seconds": seconds, "frames": gt.frames, "cog": "is a valid cloud optimized GeoTIFF" in valid.stdout,
            "crs": crs, "crs_truth": truth["crs"], "bounds": bounds}


def report(rows, command: str) -> None:
    print(f"\n$ {command}")
    print("| flight | frames | keyframes | median ground error (m) | max (m) | scale error | heading error (deg) | COG valid | CRS | stitch s |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- | --- | ---: |")
    for name, r in rows:
        s = r["score"]
        print(f"| {name} | {r['frames']} | {s.keyframes} | {s.median_m:.2f} | {s.max_m:.2f} | {100 * s.scale_error:+.2f}% | "
              f"{s.heading_error_deg:+.2f} | {'yes' if r['cog'] else 'NO'} | {r['crs']} ({'right' if r['crs'] == r['crs_truth'] else 'WRONG'}) | {r['seconds']:.0f} |")


def bench_mapping(args) -> None:
    rows = []
    extra, label = (["--level-ground"], " (--level-ground)") if args.level_ground else ([], "")
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        video = mapping_flight(args.workdir, seed)
        rows.append((f"mapping seed {seed}{label}", run_stitch(video, video.with_suffix(".SRT"), extra)))
        report(rows[-1:], "(progress)")
    first = f" --first-seed {args.first_seed}" if args.first_seed else ""
    report(rows, f"python -m benchmarks georef mapping --seeds {args.seeds}{first}{' --level-ground' if args.level_ground else ''}")


def bench_short(args) -> None:
    """Short flights, seconds long, where the GPS barely averages out: the simulator's own
    profiles (its default 3 m GPS error), the docs' example (``mosaic simulate -o flight.mp4 -p
    survey --telemetry srt``: 10 s at 1280x720) and the tests' noisy flight on three seeds."""
    flights = [(f"{profile}, 600 frames at 30 fps", f"short_{profile}", ["-p", profile, "-n", "600", "--size", "640x360", "--gsd", "0.02"])
               for profile in ("paper", "survey")]
    flights.append(("survey, the docs' example (300 frames, 1280x720)", "short_example", ["-p", "survey"]))
    flights += [(f"survey, 150 frames at 320x180, seed {seed} (the tests' noisy flight)", f"short_tests_s{seed}",
                 ["-p", "survey", "-n", "150", "--size", "320x180", "--seed", str(seed), "--gps-dropouts", "0.02", "--baro-bias", "0.5",
                  "--gsd", "0.05"]) for seed in (2, 3, 4)]
    rows = []
    for name, stem, options in flights:
        video = args.workdir / f"{stem}.mp4"
        if not video.exists():
            subprocess.run([sys.executable, "-m", "mosaic_cli", "simulate", "-o", str(video), *options, "--telemetry", "srt",
                            "--preset", "veryfast", "-q"], check=True)
        rows.append((name, run_stitch(video, video.with_suffix(".SRT"))))
    report(rows, "python -m benchmarks georef short")


def bench_refit(args) -> None:
    """Georeference again, with the current code, the placements a finished mapping stitch
    registered (kept by ``record-stitch`` in ``mapping_s<seed>.placements.npz``): the
    georeferencing alone, without re-stitching.  ``--detail`` says where the error lies."""
    from dataclasses import replace

    from mosaic_cli.geo.drift import DriftOptions
    from mosaic_cli.geo.georef import GeorefOptions, georeference
    from mosaic_cli.geo.score import score_map_homographies
    from mosaic_cli.telemetry import read_telemetry

    options = GeorefOptions(attitude_accuracy=None if args.no_gimbal else args.gimbal_accuracy, level_ground=args.level_ground)
    if args.height_accuracy is not None:
        options = replace(options, height_accuracy=args.height_accuracy)
    if args.fov_accuracy is not None:
        options = replace(options, fov_accuracy=args.fov_accuracy)
    if args.hfov is not None:
        options = replace(options, hfov=args.hfov)
    if args.link_fraction is not None:
        options = replace(options, drift=DriftOptions(link_fraction=args.link_fraction))
    if args.scale_step is not None:
        options = replace(options, drift=replace(options.drift, scale_step=args.scale_step))
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        video = args.workdir / f"mapping_s{seed}.mp4"
        record = video.with_suffix(".placements.npz")
        if not record.exists():
            print(f"mapping seed {seed}: no {record.name} (run the mapping bench first)")
            continue
        gt = load_ground_truth(video)
        kept = np.load(record)
        placements, ref, indices = list(kept["placements"]), int(kept["ref"]), [int(i) for i in kept["indices"]]
        track = read_telemetry(video.with_suffix(".SRT"))
        if args.baro_bias is not None:
            # the same flight's log with another barometer: the GPS errors are the same draw (height_offset's own stream)
            from mosaic_cli.simulate.telemetry import simulate_log, srt_text

            geo = MapGeo(truth_crs(video), np.array(json.loads(video.with_name(video.stem + ".geo.json").read_text())["map_to_crs"]), GSD)
            log = simulate_log(gt, geo, GpsErrors(rms=3.0, dropouts=0.02, bad_fixes=0.005, height_bias=args.baro_bias, seed=seed))
            other = video.with_name(f"{video.stem}.baro{args.baro_bias:g}.SRT")
            other.write_text(srt_text(log))
            track = read_telemetry(other)
        if args.gimbal_noise or args.gimbal_bias:
            # a gimbal less exact than the simulator's log: white noise per sample and a bias
            rng = np.random.default_rng([seed, 5])
            for angles in (track.pitch, track.roll):
                angles += args.gimbal_bias * rng.choice([-1.0, 1.0]) + args.gimbal_noise * rng.standard_normal(len(angles))
        g = georeference(placements, ref, indices, tuple(int(v) for v in kept["size"]), float(kept["fps"]), track, options)
        truth = json.loads(video.with_name(video.stem + ".geo.json").read_text())
        map_to_crs = np.array(truth["map_to_crs"])
        map_h = {i: g.frame_to_ground(k, P) for k, (i, P) in enumerate(zip(indices, placements))}
        score = score_map_homographies(map_h, gt, map_to_crs)
        print(f"mapping seed {seed}: {g.summary()}")
        for warning in g.warnings:
            print(f"mapping seed {seed}: warning: {warning}")
        print(f"| mapping seed {seed} (refit{', --level-ground' if args.level_ground else ''}) | {gt.frames} | {score.keyframes} | {score.median_m:.2f} | {score.max_m:.2f} | "
              f"{100 * score.scale_error:+.2f}% | {score.heading_error_deg:+.2f} |")
        if args.detail:
            refit_detail(g, placements, indices, gt, map_to_crs)


def truth_crs(video: Path) -> str:
    return json.loads(video.with_name(video.stem + ".geo.json").read_text())["crs"]


def refit_detail(g, placements, indices, gt, map_to_crs) -> None:
    """Where a georeferenced mapping stitch is wrong: the keyframe of the largest error, how
    far each keyframe's map is from a similarity of the truth (turned, scaled, tilted), and
    what the best homography of the registered mosaic onto the truth would leave (the images'
    own share of the error)."""
    import cv2

    from mosaic_cli.geo.score import score_map_homographies
    from mosaic_cli.geometry import normalize, project

    w, h = gt.size
    xs, ys = np.meshgrid(np.linspace(0, w - 1, 5), np.linspace(0, h - 1, 5))
    grid = np.stack([xs.ravel(), ys.ravel()], 1)
    got = np.stack([project(g.frame_to_ground(k, P), grid) for k, P in enumerate(placements)])
    true = np.stack([project(map_to_crs @ np.linalg.inv(gt.map_to_frame[i]), grid) for i in indices])
    error = np.linalg.norm(got - true, axis=2)  # (keyframes, 25)
    worst = int(np.argmax(error.max(1)))
    centres = true.mean(1)
    gps = "agrees" if g.used[worst] else ("outlier" if g.telemetry.fix[worst] else "none")
    print(f"  largest error {error[worst].max():.2f} m at keyframe {worst} (frame {indices[worst]}, {indices[worst] / gt.fps:.1f} s), "
          f"{np.linalg.norm(centres[worst] - centres.mean(0)):.0f} m from the flight's centre, its centre {error[worst, 12]:.2f} m off; "
          f"its GPS fix: {gps}")
    # each keyframe's map against the best similarity of it onto the truth
    za = got[..., 0] + 1j * got[..., 1]
    zb = true[..., 0] + 1j * true[..., 1]
    za, zb = za - za.mean(1, keepdims=True), zb - zb.mean(1, keepdims=True)
    ratio = (np.conj(za) * zb).sum(1) / (np.abs(za) ** 2).sum(1)
    left = np.abs(ratio[:, None] * za - zb).max(1)
    print(f"  keyframes' maps against the truth: turned {np.median(np.abs(np.degrees(np.angle(ratio)))):.2f} deg, "
          f"scaled {100 * np.median(np.abs(1 / np.abs(ratio) - 1)):.2f}% (medians), non-similar {np.median(left):.2f} m "
          f"(median, max over the frame)")
    size = 1 / np.abs(ratio) - 1
    print(f"  keyframes' own sizes against the truth: {100 * size.min():+.2f}% to {100 * size.max():+.2f}% "
          f"(the worst keyframe's {100 * size[worst]:+.2f}%; chained registrations drift in scale, --level-ground)")
    # the GPS log itself at the keyframes against the true camera positions
    from mosaic_cli.simulate.telemetry import camera_poses

    poses = camera_poses(gt)
    cameras = (np.stack([poses.x, poses.y, np.ones(gt.frames)], 1) @ map_to_crs.T)[np.array(indices), :2]
    fix = g.telemetry.fix
    logged = g.projection.to_map(g.telemetry.lat[fix], g.telemetry.lon[fix])
    zt, zg = cameras[fix, 0] + 1j * cameras[fix, 1], logged[:, 0] + 1j * logged[:, 1]
    zt, zg = zt - zt.mean(), zg - zg.mean()
    r = np.vdot(zt, zg) / np.vdot(zt, zt)
    print(f"  the GPS log at the keyframes against the true camera positions: scale {100 * (abs(r) - 1):+.2f}%, "
          f"heading {np.degrees(np.angle(r)):+.2f} deg (as the mosaic's scale and heading are scored)")
    unshifted = score_map_homographies({i: normalize(g.mosaic_to_ground @ P) for i, P in zip(indices, placements)}, gt, map_to_crs)
    prior = "none" if g.prior is None or g.prior.sigma is None else f"{g.prior.sigma:.2%} sigma"
    print(f"  without the GPS drift shifts: scale {100 * unshifted.scale_error:+.2f}%, heading {unshifted.heading_error_deg:+.2f} deg; "
          f"height x field of view prior: {prior}")
    src = np.concatenate([project(P, grid) for P in placements])
    best, _ = cv2.findHomography(src, true.reshape(-1, 2), 0)
    d = np.linalg.norm(project(best, src) - true.reshape(-1, 2), axis=1)
    print(f"  the best homography of the registered mosaic onto the truth leaves {np.median(d):.2f} m median, {d.max():.2f} m max; "
          f"GPS drift shifts move keyframes by {np.linalg.norm(g.shifts - g.shifts.mean(0), axis=1).max():.2f} m at most, "
          f"the heights scale them by {100 * (g.scales.min() - 1):+.2f}% to {100 * (g.scales.max() - 1):+.2f}%")


def bench_gps_limit(args) -> None:
    """What the GPS alone can tell of the mapping flight's scale and heading: the similarity
    between the true camera positions at keyframe times (every 2.1 s) and the same positions
    with the simulator's GPS error (3 m RMS, correlated over 2 s), over many error draws."""
    from mosaic_cli.simulate.telemetry import camera_poses, gauss_markov

    video = mapping_flight(args.workdir, 0)
    gt = load_ground_truth(video)
    truth = json.loads(video.with_name(video.stem + ".geo.json").read_text())
    poses = camera_poses(gt)
    camera = (np.stack([poses.x, poses.y, np.ones(gt.frames)], 1) @ np.array(truth["map_to_crs"]).T)[:, :2]
    times = np.arange(gt.frames) / gt.fps
    keyframes = np.arange(0, gt.frames, 21)
    centred = camera[keyframes] - camera[keyframes].mean(0)
    truth_z = centred[:, 0] + 1j * centred[:, 1]
    scale, heading = [], []
    for draw in range(args.draws):
        rng = np.random.default_rng([draw, 77])
        sigma = 3.0 / math.sqrt(2.0)
        error = np.stack([gauss_markov(rng, times, sigma, 2.0), gauss_markov(rng, times, sigma, 2.0)], 1)[keyframes]
        gps = centred + error - error.mean(0)
        gps_z = gps[:, 0] + 1j * gps[:, 1]
        ratio = np.vdot(truth_z, gps_z) / np.vdot(truth_z, truth_z)
        scale.append(100 * (abs(ratio) - 1))
        heading.append(math.degrees(np.angle(ratio)))
    signed = np.array(scale)
    scale, heading = np.abs(scale), np.abs(heading)
    print(f"\n$ python -m benchmarks georef gps-limit --draws {args.draws}")
    print(f"GPS scale error over the mapping flight ({len(keyframes)} keyframe fixes, {args.draws} draws): RMS "
          f"{np.sqrt(np.mean(scale**2)):.2f}%, 95th percentile {np.percentile(scale, 95):.2f}%, beyond 0.5%: {np.mean(scale > 0.5):.1%} of flights")
    print(f"GPS heading error: RMS {np.sqrt(np.mean(heading**2)):.2f} deg, 95th percentile {np.percentile(heading, 95):.2f} deg, "
          f"beyond 0.5 deg: {np.mean(heading > 0.5):.1%}")
    # The height x field of view scale weighed in as georef does (prior.py, fit.scale_sigma): the
    # simulator's barometric offset per flight, the field of view exact (as the simulator logs it)
    from mosaic_cli.geo.fit import fix_weights, scale_sigma
    from mosaic_cli.geo.georef import GeorefOptions
    from mosaic_cli.simulate.telemetry import GpsErrors, height_offset

    options = GeorefOptions()
    weights = fix_weights(times[keyframes], np.ones(len(keyframes), bool), options.drift.correlation)
    gps_sigma = scale_sigma(centred, weights, 3.0 / math.sqrt(2.0))
    offsets = np.array([height_offset(GpsErrors(seed=draw)) for draw in range(args.draws)])
    height = float(np.median(poses.z)) * float(truth["gsd"])
    for metres, fov_error, fov_accuracy, what in ((height, 0.0, options.fov_accuracy, "this flight"),
                                                   (height, 0.0, 0.0, "this flight, the field of view taken as exact"),
                                                   (120.0, 0.0, 0.0, "the same flight 120 m up (a 4K camera at 5 cm), the field of view exact")):
        prior_sigma = math.hypot(options.height_accuracy / metres, fov_accuracy)
        prior_error = 100 * (offsets / metres + fov_error)
        w = gps_sigma**-2 / (gps_sigma**-2 + prior_sigma**-2)
        combined = np.abs(w * signed + (1 - w) * prior_error)
        print(f"with the height ({metres:.0f} m, {options.height_accuracy} m RMS offset) x field of view, {what}: prior sigma "
              f"{100 * prior_sigma:.2f}%, GPS {100 * gps_sigma:.2f}%, the GPS's weight {w:.0%}: RMS {np.sqrt(np.mean(combined**2)):.2f}%, "
              f"beyond 0.5%: {np.mean(combined > 0.5):.1%} of flights")


def record_stitch(record: Path, argv: list[str]) -> None:
    """Run ``mosaic <argv>`` in this process, keeping the first panorama's registered keyframe
    placements (before georeferencing) in ``record`` (.npz), for ``refit``."""
    from mosaic_cli import cli
    from mosaic_cli.stitch import pipeline

    georeference = pipeline._georeference

    def recording(placements, ref, indices, scan, track, options, first):
        if first:
            np.savez(record, placements=np.array(placements), ref=ref, indices=np.array(indices),
                     size=np.array(scan.source_size), fps=scan.fps)
        return georeference(placements, ref, indices, scan, track, options, first)

    pipeline._georeference = recording
    cli.main(argv)


def main(argv: list[str] | None = None) -> int | None:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) > 1 and argv[0] == "record-stitch":  # run_stitch's own process
        record_stitch(Path(argv[1]), argv[2:])
        return 0
    parser = make_parser(SUITE, None, __doc__)
    parser.add_argument("what", choices=["mapping", "short", "all", "refit", "gps-limit"])
    parser.add_argument("--workdir", type=Path, default=DEFAULT_WORKDIR)
    parser.add_argument("--seeds", type=int, default=3, help="how many mapping flights (seeds) to run")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--draws", type=int, default=1000, help="gps-limit: GPS error draws")
    parser.add_argument("--level-ground", action="store_true", help="mapping, refit: stitch --level-ground (the heights also correct each keyframe's scale)")
    parser.add_argument("--detail", action="store_true", help="refit: where the error lies")
    parser.add_argument("--gimbal-accuracy", type=float, default=1.0, help="refit: degrees (GeorefOptions.attitude_accuracy)")
    parser.add_argument("--no-gimbal", action="store_true", help="refit: the tilt from the GPS alone, as before adjust.py")
    parser.add_argument("--link-fraction", type=float, help="refit: DriftOptions.link_fraction of the GPS drift shifts")
    parser.add_argument("--scale-step", type=float, help="refit, --level-ground: DriftOptions.scale_step (the heights' scales' stiffness)")
    parser.add_argument("--height-accuracy", type=float, help="refit: metres (GeorefOptions.height_accuracy)")
    parser.add_argument("--baro-bias", type=float, help="refit: metres RMS: the log's heights simulated again with this barometric offset")
    parser.add_argument("--hfov", type=float, help="refit: degrees, in place of the log's (GeorefOptions.hfov)")
    parser.add_argument("--fov-accuracy", type=float, help="refit: relative (GeorefOptions.fov_accuracy)")
    parser.add_argument("--gimbal-noise", type=float, default=0.0, help="refit: degrees of white noise added to the log's pitch and roll")
    parser.add_argument("--gimbal-bias", type=float, default=0.0, help="refit: degrees of bias added to the log's pitch and roll")
    args = parser.parse_args(argv)
    args.workdir.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if args.what in ("mapping", "all"):
        bench_mapping(args)
    if args.what in ("short", "all"):
        bench_short(args)
    if args.what == "refit":
        bench_refit(args)
    if args.what == "gps-limit":
        bench_gps_limit(args)
