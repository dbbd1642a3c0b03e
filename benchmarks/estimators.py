"""Estimators: the network's cost, the learned estimator's threads, the ORB baselines, the model card's tables and failure analyses."""

from __future__ import annotations

import json
import math
import statistics
import tempfile
import time
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import torch

from benchmarks import baseline_orb
from benchmarks.common import make_parser, run_commands
from mosaic_cli import device as mosaic_device
from mosaic_cli.estimators import OrbConfig, OrbEstimator, estimate_stream, make_estimator
from mosaic_cli.estimators.learned import LearnedConfig, make_learned_estimator
from mosaic_cli.estimators.refine import band_pass, points_to_track, track_points
from mosaic_cli.evaluate import FAILURE_PX, corner_errors, evaluate
from mosaic_cli.geometry import frame_corners, project
from mosaic_cli.inputs import find_flights
from mosaic_cli.model import HomographyNet, NetConfig, count_parameters, macs_per_pair
from mosaic_cli.simulate import ground_truth_path, load_ground_truth
from mosaic_cli.track import track_video
from mosaic_cli.video import open_video

SUITE = "estimators"


# -- python -m benchmarks estimators network -------------------------------------------------------

def time_net(model: HomographyNet, batch: int, device: torch.device, chunked: bool) -> float:
    """Milliseconds per pair for one call on ``batch`` consecutive pairs."""
    x = torch.rand(batch, 2, model.config.patch, model.config.patch, device=device) * 2 - 1
    if device.type == "cpu":
        x = x.contiguous(memory_format=torch.channels_last)
    with torch.inference_mode():
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        feats = model.features(x)
        model.step(feats[None] if chunked else feats[:, None])
        if device.type == "cuda":
            torch.cuda.synchronize()
    return 1000.0 * (time.perf_counter() - start) / batch


def bench_networks(args, device: torch.device) -> None:
    configs = [NetConfig(preset=p, head=h) for p in args.presets for h in ("cnn", "lstm")]
    models = []
    for c in configs:
        m = HomographyNet(c).to(device).eval()
        if device.type == "cpu":
            m = m.to(memory_format=torch.channels_last)
        models.append(m)
    modes = [(args.chunk, True), (1, True)]
    times = {(i, b): [] for i in range(len(models)) for b, _ in modes}
    for rep in range(args.repeats + 1):  # the first round warms up
        for i, m in enumerate(models):
            if m.config.preset == "paper" and rep > max(3, args.repeats // 3):
                continue  # 8x slower; a few repeats are enough
            for batch, chunked in modes:
                t = time_net(m, batch, device, chunked)
                if rep:
                    times[(i, batch)].append(t)
    print(f"device {device}, {torch.get_num_threads()} thread(s), medians of interleaved repeats")
    print(f"{'preset':8} {'head':5} {'params':>8} {'MB fp32':>8} {'GMAC/pair':>10} {f'ms/pair x{args.chunk}':>12} {'ms/pair x1':>11}")
    for i, (c, m) in enumerate(zip(configs, models)):
        n = count_parameters(m)
        print(
            f"{c.preset:8} {c.head:5} {n / 1e6:7.2f}M {n * 4 / 1e6:8.1f} {macs_per_pair(c) / 1e9:10.3f} "
            f"{statistics.median(times[(i, args.chunk)]):12.2f} {statistics.median(times[(i, 1)]):11.2f}"
        )


def panning_frames(n: int, size=(320, 180), seed=0) -> list[np.ndarray]:
    """A textured map seen by a camera panning 3 px per frame (RGB frames at ``size``)."""
    rng = np.random.default_rng(seed)
    w, h = size[0] + 3 * n + 8, size[1] + 2 * n + 8
    img = np.zeros((h, w), np.float32)
    for cell, weight in ((64, 1.0), (16, 0.7), (4, 0.4)):
        img += weight * cv2.resize(rng.random((h // cell + 2, w // cell + 2)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
    img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    return [img[2 * t : 2 * t + size[1], 3 * t : 3 * t + size[0]] for t in range(n)]


def bench_estimators(args, device: torch.device) -> None:
    from mosaic_cli.estimators import OrbEstimator, estimate_stream
    from mosaic_cli.estimators.learned import LearnedConfig, make_learned_estimator
    from mosaic_cli.model import save_weights

    frames = panning_frames(args.frames)
    size = (frames[0].shape[1], frames[0].shape[0])
    estimators = {"orb": OrbEstimator(320)}
    with tempfile.TemporaryDirectory() as tmp:
        for head, variant in (("lstm", "lstm-reg-all"), ("cnn", "reg-all")):
            model = HomographyNet(NetConfig(preset="compact", head=head))
            path = Path(tmp) / f"{head}.safetensors"
            save_weights(path, model, model.config, variant)
            estimators[f"compact-{head}"] = make_learned_estimator(head, weights=path, device=str(device), config=LearnedConfig(chunk=args.chunk))
    times = {name: [] for name in estimators}
    for rep in range(args.repeats + 1):
        for name, est in estimators.items():
            start = time.perf_counter()
            n = sum(1 for _ in estimate_stream(est, frames, size))
            if rep:
                times[name].append(1000.0 * (time.perf_counter() - start) / (n + 1))
    print(f"\nwhole estimator on {len(frames)} in-memory 320x180 frames (no decoding), ms per frame:")
    for name, ts in times.items():
        print(f"  {name:14} median {statistics.median(ts):6.2f}   min {min(ts):6.2f}   max {max(ts):6.2f}")


def network_command(argv: list[str] | None = None) -> int | None:
    """Cost of the homography network presets on this machine: parameters, MB, GMAC per frame pair,
    and CPU latency per pair, measured the way the learned estimator runs the net (backbone on a
    chunk of pairs in one channels-last batch, then the head stepped over the chunk) and one pair
    per call; optionally the whole learned estimator against ORB on the same in-memory frames.

        python -m benchmarks estimators network                       # both presets, both heads, 1 thread
        python -m benchmarks estimators network --threads 2 --repeats 15
        python -m benchmarks estimators network --estimators          # + end-to-end ms/frame vs ORB (compact)
        python -m benchmarks estimators network --device cuda --chunk 64

    Timings are medians over interleaved repeats (the configurations take turns, so background load
    hits them alike).  Weights are random: speed does not depend on them.
    """
    parser = make_parser(SUITE, 'network', network_command.__doc__)
    parser.add_argument("--presets", nargs="+", default=["compact", "paper"])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--chunk", type=int, default=16, help="pairs per backbone batch")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--estimators", action="store_true", help="also time the whole estimator vs ORB")
    parser.add_argument("--frames", type=int, default=65)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    device = torch.device(args.device)
    bench_networks(args, device)
    if args.estimators:
        bench_estimators(args, device)


# -- python -m benchmarks estimators threads -------------------------------------------------------

def threads_command(argv: list[str] | None = None) -> int | None:
    """The learned estimator on every core (issue 39, item 1): one video's frames decoded once, then
    estimated with 1..N threads (``--threads``: the pool that checks each pair), with and without a
    file's lookahead (the next chunk's network beside this chunk's checks), rounds in turn; the
    median wall time of each, and whether every run gave the one-thread estimates to the bit.

        python -m benchmarks estimators threads FLIGHT.mp4 [--threads 1,2] [--rounds 3] [-e lstm]

    Estimation only (the decode, the overlay detection and writing the track are left out: see
    ``mosaic track``'s final line for those); say how loaded the machine was beside the figures.
    """
    parser = make_parser(SUITE, 'threads', threads_command.__doc__)
    parser.add_argument("video", type=Path)
    parser.add_argument("--threads", default="1,2", help="pool sizes, comma-separated")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("-e", "--estimator", default="lstm")
    args = parser.parse_args(argv)
    mosaic_device.ask_cpu_threads(None)  # the network on one torch thread, as the commands run it
    estimator = make_estimator(args.estimator, device="cpu")
    with open_video(args.video, width=estimator.input_width, gray=True) as stream:
        frames, size = list(stream), stream.info.source_size
    runs = [(lookahead, int(t)) for lookahead in (False, True) for t in args.threads.split(",")]
    seconds: dict[tuple[bool, int], list[float]] = {run: [] for run in runs}
    reference, identical = None, True
    for _ in range(args.rounds):
        for lookahead, threads in runs:
            estimator.threads = threads
            start = time.perf_counter()
            H = np.array([e.H for e in estimate_stream(estimator, frames, size, lookahead=lookahead)])
            seconds[(lookahead, threads)].append(time.perf_counter() - start)
            reference = H if reference is None else reference
            identical &= bool(np.array_equal(H, reference))
    base = statistics.median(seconds[(False, 1)])
    print(f"{len(frames)} frames of {size[0]}x{size[1]}, -e {args.estimator}, {args.rounds} rounds")
    for (lookahead, threads), times in seconds.items():
        median = statistics.median(times)
        print(f"  threads {threads:>2}  lookahead {'on ' if lookahead else 'off'}  {median:6.2f} s  ({len(frames) / median:5.0f} fr/s, "
              f"{base / median:.2f}x one thread)  runs {', '.join(f'{t:.2f}' for t in times)}")
    print(f"every run gave the one-thread estimates to the bit: {identical}")
    return 0 if identical else 1


# -- python -m benchmarks estimators orb-ablation --------------------------------------------------

DEFAULT = OrbConfig()
VARIANTS = {
    "orb (default)": DEFAULT,
    "no polish": replace(DEFAULT, refine=None),
    "ECC polish": replace(DEFAULT, refine="ecc"),
    "RANSAC": replace(DEFAULT, method="ransac"),
    "1000 features": replace(DEFAULT, n_features=1000),
    "3 pyramid levels": replace(DEFAULT, n_levels=3),
    "FAST threshold 20": replace(DEFAULT, fast_threshold=20),
}
BASELINE = "baseline (paper)"


def run_baseline(frames, full_size, estimate):
    """The baseline's per-pair step on the same frames, scaled up as its script does."""
    orb = cv2.ORB_create(nfeatures=500, WTA_K=2)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    s = full_size[0] / frames[0].shape[1]
    up, down = np.diag([s, s, 1.0]), np.diag([1 / s, 1 / s, 1.0])
    out = []
    for prev, cur in zip(frames, frames[1:]):
        H, _ = estimate(prev, cur, orb, matcher)
        out.append(up @ H @ down)
    return np.array(out)


def run_variant(frames, full_size, config, work_width):
    est = OrbEstimator(work_width, config)
    est.reset(full_size)
    out = []
    for frame in frames:
        out += est.feed(frame)
    return np.array([e.H for e in out])


def orb_ablation_command(argv: list[str] | None = None) -> int | None:
    """Choose the OrbConfig defaults by measurement. For ORB variants and for the paper-style
    baseline (``python -m benchmarks estimators orb-baseline``), report MACE by the paper's protocol, the median corner
    error, the failure rate and the estimator's CPU ms per frame. The flights are simulated with
    exact ground truth; `mosaic simulate` writes each one's <stem>.gt.json.

        python -m benchmarks estimators orb-ablation flights/*.mp4 [--json results.json]

    Each flight is decoded once, at the working width and in gray, and every variant runs on the
    same frames. Only the estimator is timed, in CPU time (time.process_time), so that the load
    from other processes on a shared machine moves the numbers less. The tables quote medians
    over the flights.
    """
    parser = make_parser(SUITE, 'orb-ablation', orb_ablation_command.__doc__)
    parser.add_argument("flights", nargs="+")
    parser.add_argument("--work-width", type=int, default=320)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    baseline_step = baseline_orb.estimate
    names = [BASELINE] + list(VARIANTS)
    results: dict[str, dict[str, dict]] = {name: {} for name in names}
    for flight in args.flights:
        gt = load_ground_truth(ground_truth_path(flight))
        with open_video(flight, width=args.work_width, gray=True) as stream:
            frames = list(stream)
            full_size = stream.info.source_size
        for name in names:
            start = time.process_time()
            if name == BASELINE:
                pairwise = run_baseline(frames, full_size, baseline_step)
            else:
                pairwise = run_variant(frames, full_size, VARIANTS[name], args.work_width)
            ms = 1000 * (time.process_time() - start) / len(frames)
            metrics = evaluate(pairwise, gt)
            metrics["cpu_ms_per_frame"] = ms
            results[name][Path(flight).stem] = metrics
            print(f"{Path(flight).stem:20s} {name:18s} MACE {metrics['mace']:6.2f}  corner {metrics['corner_error']:5.2f}  "
                  f"fail {100 * metrics['failure_rate']:4.1f}%  {ms:5.1f} CPU ms/frame", flush=True)
    print()
    print("| variant | mean MACE | median MACE | median corner error | failures | CPU ms/frame (median) |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    summary = {}
    for name in names:
        rows = list(results[name].values())
        summary[name] = {
            "mean_mace": float(np.mean([r["mace"] for r in rows])),
            "median_mace": float(np.median([r["mace"] for r in rows])),
            "median_corner_error": float(np.median([r["corner_error"] for r in rows])),
            "failure_rate": float(np.mean([r["failure_rate"] for r in rows])),
            "median_cpu_ms_per_frame": float(np.median([r["cpu_ms_per_frame"] for r in rows])),
        }
        s = summary[name]
        print(f"| {name} | {s['mean_mace']:.2f} | {s['median_mace']:.2f} | {s['median_corner_error']:.2f} | "
              f"{100 * s['failure_rate']:.2f}% | {s['median_cpu_ms_per_frame']:.1f} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": summary, "per_flight": results}, indent=1))


# -- python -m benchmarks estimators ablation-table ------------------------------------------------

def ablation_table_command(argv: list[str] | None = None) -> int | None:
    """The model card's ablation table from a ``mosaic bench --flights ... --json`` report.

        python -m benchmarks estimators ablation-table REPORT.json [--name LABEL=NAME ...] [--ratio-to LABEL]

    One row per estimator, in the report's order (or the order of --name): MACE over all flights
    and, per profile, MACE and failure rate; median corner error, failure rate, the share of pairs
    the classical fallback made (learned estimators) and CPU ms per frame (p50); --ratio-to adds each
    MACE as a multiple of that estimator's (per profile too).  A second table gives the CPU ms per
    frame (p50) of each profile.
    """
    parser = make_parser(SUITE, 'ablation-table', ablation_table_command.__doc__)
    parser.add_argument("report", type=Path)
    parser.add_argument("--name", action="append", default=[], help="LABEL=NAME: the row name of a bench label")
    parser.add_argument("--ratio-to", help="bench label whose MACE the others are divided by")
    args = parser.parse_args(argv)

    report = json.loads(args.report.read_text())
    estimators = report["estimators"]
    names: dict[str, str] = {}
    for item in args.name:
        label, _, name = item.rpartition("=")
        names[label] = name
    labels = [label for label in names if label in estimators] or list(estimators)
    profiles = report["source"]["profiles"]
    base = estimators.get(args.ratio_to) if args.ratio_to else None

    def mace(entry: dict, ref: dict | None) -> str:
        text = f"{entry['mace']:.2f}"
        return f"{text} ({entry['mace'] / ref['mace']:.2f}x)" if ref and ref["mace"] > 0 else text

    head = ["method", "MACE, all", *[f"{p}: MACE / failed" for p in profiles], "median corner error (px)", "failure rate",
            "fallback pairs", "CPU ms/frame (p50)"]
    print("| " + " | ".join(head) + " |")
    print("| --- |" + " ---: |" * (len(head) - 1))
    for label in labels:
        e = estimators[label]
        paths = e.get("paths")
        fallback = f"{100 * paths.get('fallback', 0) / max(1, sum(paths.values())):.1f}%" if paths else "-"
        cells = [names.get(label, f"`{label}`"), mace(e, base)]
        cells += [f"{mace(e['profiles'][p], base['profiles'][p] if base else None)} / {100 * e['profiles'][p]['failure_rate']:.1f}%"
                  for p in profiles]
        cells += [f"{e['corner_error']:.2f}", f"{100 * e['failure_rate']:.1f}%", fallback, f"{e['cpu_ms_per_frame']['p50']:.2f}"]
        print("| " + " | ".join(cells) + " |")
    print()
    print("| CPU ms/frame (p50) | " + " | ".join(profiles) + " |")
    print("| --- |" + " ---: |" * len(profiles))
    for label in labels:
        e = estimators[label]
        print(f"| {names.get(label, f'`{label}`')} | " + " | ".join(f"{e['profiles'][p]['cpu_ms_per_frame']['p50']:.2f}" for p in profiles) + " |")
    source = report["source"]
    print(f"\n{source['frames']} frames, {len(source['flights'])} flights in {source['path']}; "
          f"{report['units']}")


# -- python -m benchmarks estimators paired-failures -----------------------------------------------


def pairs_of(entry: dict) -> tuple[np.ndarray, np.ndarray]:
    errors, burst = [], []
    for flight in sorted(entry["per_pair"]):
        row = entry["per_pair"][flight]
        e = np.array([np.inf if v is None else v for v in row["corner_errors"]], float)
        errors.append(e)
        burst.append(np.array(row.get("touches_burst", [0] * len(e)), bool))
    return np.concatenate(errors), np.concatenate(burst)


def compare(report: dict, a: str, b: str) -> dict:
    ea, burst = pairs_of(report["estimators"][a])
    eb, burst_b = pairs_of(report["estimators"][b])
    if len(ea) != len(eb) or not np.array_equal(burst, burst_b):
        raise SystemExit(f"{a} and {b} did not score the same pairs")
    out = {}
    for name, mask in (("burst", burst), ("other", ~burst)):
        fa, fb = ea[mask] > FAILURE_PX, eb[mask] > FAILURE_PX
        n = int(mask.sum())
        only_a, only_b = int((fa & ~fb).sum()), int((fb & ~fa).sum())
        se = math.sqrt(max(only_a + only_b - (only_a - only_b) ** 2 / n, 0.0)) / n if n else float("nan")
        out[name] = {"pairs": n, "failed_a": int(fa.sum()), "failed_b": int(fb.sum()), "only_a": only_a, "only_b": only_b,
                     "ratio": float(fa.sum() / fb.sum()) if fb.sum() else float("inf"), "se_rate_difference": se}
    return out


def paired_failures_command(argv: list[str] | None = None) -> int | None:
    """Two estimators of one ``mosaic bench --flights ... --json REPORT`` run, compared pair by pair.

        python -m benchmarks estimators paired-failures REPORT.json A B [A B ...]

    For each pair of labels: on the pairs that touch a burst and on the others, how many each one
    fails (corner error over 10 px, 1280x720-equivalent), how many only A fails and only B fails
    (the discordant pairs, which alone decide a paired comparison), the ratio of the failure counts
    A / B, and the standard error of the paired difference of the failure rates,
    sqrt(b + c - (b - c)^2 / n) / n with b, c the discordant counts and n the pairs.
    """
    ap = make_parser(SUITE, 'paired-failures', paired_failures_command.__doc__)
    ap.add_argument("report")
    ap.add_argument("labels", nargs="+", help="pairs of estimator labels: A B [A B ...]")
    ap.add_argument("--json", help="also write the comparisons here")
    args = ap.parse_args(argv)
    if len(args.labels) % 2:
        raise SystemExit("labels come in pairs: A B [A B ...]")
    report = json.loads(open(args.report).read())
    results = []
    for a, b in zip(args.labels[::2], args.labels[1::2]):
        result = compare(report, a, b)
        results.append({"a": a, "b": b, **result})
        for name in ("burst", "other"):
            r = result[name]
            print(f"{name:5s} pairs {r['pairs']:5d}: {a} failed {r['failed_a']:4d} ({r['failed_a'] / max(r['pairs'], 1):6.1%}), "
                  f"{b} failed {r['failed_b']:4d} ({r['failed_b'] / max(r['pairs'], 1):6.1%}); ratio {r['ratio']:.2f}; "
                  f"only A {r['only_a']}, only B {r['only_b']}; SE of the rate difference {r['se_rate_difference']:.2%}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)


# -- python -m benchmarks estimators burst-failures ------------------------------------------------

def burst_failures_command(argv: list[str] | None = None) -> int | None:
    """Which burst pairs an estimator fails, by kind: for every flight with bursts in a folder (X.mp4
    with its X.gt.json, made by ``mosaic simulate --bursts`` or ``-p bursts``), the pairs that touch a
    burst, failed (corner error over 10 px, 1280x720-equivalent) or not, counted per burst kind, and
    each failed pair listed with its error and confidence.

        python -m benchmarks estimators burst-failures ../runs/data/dev -e lstm
    """
    ap = make_parser(SUITE, 'burst-failures', burst_failures_command.__doc__)
    ap.add_argument("folder")
    ap.add_argument("-e", "--estimator", default="lstm")
    args = ap.parse_args(argv)
    counts: dict[str, list[int]] = defaultdict(lambda: [0, 0])  # kind -> [failed, pairs]
    for video in find_flights(args.folder, "FOLDER"):
        gt = load_ground_truth(video)
        if not gt.bursts:
            continue
        track = track_video(video, make_estimator(args.estimator, device="cpu"), show_progress=False)
        scale = 1280.0 / gt.size[0]
        errors = corner_errors(track.pairwise, np.asarray(gt.pairwise), gt.size) * scale
        touched: dict[int, str] = {}
        for b in gt.bursts:
            t, kind = int(b["frame"]), str(b["kind"])
            for p in ((t - 1,) if kind in ("drop", "duplicate") else (t - 1, t)):
                touched.setdefault(p, kind)
        for p, kind in sorted(touched.items()):
            if 0 <= p < len(errors):
                failed = bool(errors[p] > FAILURE_PX)
                counts[kind][0] += failed
                counts[kind][1] += 1
                if failed:
                    path = track.paths[p] if track.paths else "-"
                    print(f"{video.stem} pair {p} ({kind}): {errors[p]:.1f} px, confidence {track.confidence[p]:.2f}, {path}")
    for kind, (failed, pairs) in sorted(counts.items()):
        print(f"{kind:10s} {failed:3d} of {pairs:3d} burst pairs failed")


# -- python -m benchmarks estimators extreme -------------------------------------------------------

WORK = (320, 180)
SHIFT_PX = 3.0  # the basin test's displacement (working px)


def shift(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]])


def diagnose(video: Path, frames: int, weights: str | None = None) -> dict:
    gt = load_ground_truth(ground_truth_path(video))
    s = WORK[0] / gt.size[0]
    S = np.diag([s, s, 1.0])
    network = make_learned_estimator("lstm", weights=weights, config=LearnedConfig(refine=None, fallback="none", min_zncc=None))
    pairwise = np.asarray(track_video(str(video), network, max_frames=frames, show_progress=False).pairwise)
    to_work = lambda H: S @ H @ np.linalg.inv(S)  # noqa: E731
    seeds_net = [to_work(H) for H in pairwise]
    truth = [to_work(H) for H in gt.pairwise[: len(pairwise)]]
    corners = frame_corners(*WORK)
    err = lambda A, B: float(np.linalg.norm(project(A, corners) - project(B, corners), axis=-1).mean())  # noqa: E731
    limit = FAILURE_PX * s

    with open_video(str(video), width=WORK[0], gray=True) as stream:
        grays = [g for _, g in zip(range(len(pairwise) + 1), stream)]
    config = LearnedConfig()
    aligned = [band_pass(g, *config.polish_band) for g in grays]
    points = [points_to_track(g, config.corners) for g in grays]
    cheap, wide = config.polish, config.polish_wide
    probe = replace(cheap, window=15, max_shift=2 * SHIFT_PX)

    def polish(k: int, H: np.ndarray) -> np.ndarray | None:
        first = track_points(aligned[k], aligned[k + 1], H, points[k], cheap)
        if first.refined:
            return first.H
        found = track_points(aligned[k], aligned[k + 1], H, points[k], wide)
        if not found.refined:
            return None
        again = track_points(aligned[k], aligned[k + 1], found.H, points[k], cheap)
        return again.H if again.refined else found.H

    def holds(k: int, H: np.ndarray) -> bool:
        for dx, dy in ((SHIFT_PX, 0), (0, SHIFT_PX), (-SHIFT_PX / 1.5, -SHIFT_PX / 1.5)):
            back = track_points(aligned[k], aligned[k + 1], shift(dx, dy) @ H, points[k], probe)
            if not back.refined or err(back.H, H) > 1.0:
                return False
        return True

    seed_err = {"network": [], "velocity": [], "identity": []}
    placed_err = {name: [] for name in seed_err}
    held, velocity = [], np.eye(3)
    for k, T in enumerate(truth):
        for name, seed in (("network", seeds_net[k]), ("velocity", velocity), ("identity", np.eye(3))):
            seed_err[name].append(err(seed, T))
            H = polish(k, seed)
            placed_err[name].append(err(H, T) if H is not None else np.inf)
            if name == "network":
                result = H
        if result is not None:
            velocity = result
            if err(result, T) <= limit:
                held.append(holds(k, result))
    fails = {name: np.asarray(v) > limit for name, v in placed_err.items()}
    return {
        "flight": video.stem, "pairs": len(truth),
        "seed_within": {name: float(np.mean(np.asarray(v) <= limit)) for name, v in seed_err.items()},
        "failed": {name: float(f.mean()) for name, f in fails.items()},
        "oracle_failed": float(np.mean(np.logical_and.reduce(list(fails.values())))),
        "right_that_hold": float(np.mean(held)) if held else float("nan"),
    }


def extreme_command(argv: list[str] | None = None) -> int | None:
    """Why do pairs of a flight fail?  Seeds, the polish, and whether the frames pin the motion down.

        python -m benchmarks estimators extreme FLIGHT.mp4 [FLIGHT.mp4 ...] [--frames 300]

    For every pair of each simulated flight (exact truth from its .gt.json), at the learned
    estimator's working width and with its polish settings (LearnedConfig's defaults):

    * how close each seed is to the truth: the network's estimate (``lstm``, no polish), the
      previous pair's polished motion (constant velocity), the identity;
    * the failure rate of the default polish cascade (cheap, then wide, then cheap again) from each
      seed, and of an oracle that keeps, pair by pair, whichever seed's polish came out right: what
      no choice of seed can beat;
    * the basin test: the correctly placed pairs re-polished from their own result shifted by 3 px
      (three directions, the cheap polish with 15 px windows).  Where the frames determine the
      motion, the polish pulls the estimate back; where it stays where it was put, the pair was
      right only because its seed was, and the frames alone could not have told.

    A failure is a corner error above 10 px at 1280x720 (evaluate.FAILURE_PX), as in ``mosaic bench``.
    """
    parser = make_parser(SUITE, 'extreme', extreme_command.__doc__)
    parser.add_argument("flights", nargs="+", type=Path)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--weights", default=None, help="the network's weights (default: the shipped lstm)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    print("| flight | seed within 10 px: network / velocity / identity | failed after the polish: network / velocity / identity "
          "| best of the three seeds (oracle) | correctly placed pairs whose basin holds |")
    print("| --- | --- | --- | ---: | ---: |")
    for video in args.flights:
        r = diagnose(video, args.frames, args.weights)
        w, f = r["seed_within"], r["failed"]
        print(f"| {r['flight']} | {w['network']:.0%} / {w['velocity']:.0%} / {w['identity']:.0%} "
              f"| {f['network']:.1%} / {f['velocity']:.1%} / {f['identity']:.1%} | {r['oracle_failed']:.1%} "
              f"| {r['right_that_hold']:.0%} |", flush=True)


COMMANDS = {
    "network": network_command,
    "threads": threads_command,
    "orb-baseline": baseline_orb.main,
    "orb-ablation": orb_ablation_command,
    "ablation-table": ablation_table_command,
    "paired-failures": paired_failures_command,
    "burst-failures": burst_failures_command,
    "extreme": extreme_command,
}


def main(argv: list[str]) -> int:
    return run_commands(SUITE, __doc__, COMMANDS, argv)
