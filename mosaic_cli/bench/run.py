"""Running ``mosaic bench``: the estimators built, then timed (and scored where there is ground
truth) on a simulated flight or a video (:func:`run_bench`), or over a folder of flights
(:func:`run_flights`); each returns the report dict."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from mosaic_cli.bench.options import BenchOptions, check_request, is_learned
from mosaic_cli.bench.scoring import PROFILE_ORDER, FlightScore, find_flights, pool, score_flight
from mosaic_cli.bench.timing import decode_frames, gpu_batch, machine, time_estimator, time_stats, warm_up
from mosaic_cli.errors import BadInput, MosaicError


def build_estimators(labels: list[str], work_width: int, device: str, weights: str | None, explicit: bool, notes: list[str]) -> dict:
    """label -> estimator, for names as the command line gives them (options included).  The
    learned ones get ``weights``; when the names are the defaults (not ``explicit``), a learned
    estimator that cannot be built (no shipped weights, a checkpoint of the other head) is
    skipped with a note instead of failing."""
    from mosaic_cli.estimators import make_estimator

    built = {}
    for label in labels:
        learned = is_learned(label)
        try:
            # --work-width is the classical estimators' (a learned one works at its weights' width).
            built[label] = make_estimator(label, work_width=None if learned else work_width, device=device,
                                          weights=weights if learned else None)
        except (MosaicError, ImportError, OSError) as exc:
            if explicit or not learned:
                if isinstance(exc, MosaicError):
                    raise
                raise BadInput(f"estimator {label!r} is unavailable: {exc}") from None
            notes.append(f"{label}: skipped ({str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__})")
    if not built:
        raise BadInput("no estimator to benchmark")
    return built


def bench(options: BenchOptions, show_progress: bool = True) -> dict:
    """``mosaic bench``: :func:`run_flights` with ``options.flights``, else :func:`run_bench`."""
    check_request(options)
    return run_flights(options, show_progress) if options.flights is not None else run_bench(options, show_progress)


def run_bench(options: BenchOptions, show_progress: bool = True) -> dict:
    """Benchmark the estimators on ``options.video`` (or a simulated flight) and return the report dict."""
    from mosaic_cli.evaluate import evaluate
    from mosaic_cli.progress import console

    video, map_path, frames = options.video, options.map_image, options.flight.frames
    work_width, device, weights = options.work_width, options.device, options.weights
    notes: list[str] = []
    built = build_estimators(options.labels, work_width, device, weights, options.estimators is not None, notes)

    report: dict = {
        "version": 1,
        "machine": machine(),
        "settings": {"frames": frames, "work_width": work_width, "device": device, "weights": str(weights) if weights else None},
    }
    with tempfile.TemporaryDirectory(prefix="mosaic-bench-") as tmp:
        gt = None
        simulate_seconds = None
        if video is None:
            from mosaic_cli.simulate import simulate_flight

            clip = Path(tmp) / "bench.mp4"
            t0 = time.perf_counter()
            gt = simulate_flight(clip, map_path, options.flight, show_progress=show_progress)
            simulate_seconds = time.perf_counter() - t0
            f = options.flight
            source = {"kind": "simulated", "profile": f.profile, "frames": frames, "size": list(f.size), "map": gt.map_name, "seed": f.seed}
        else:
            clip = Path(video)
            from mosaic_cli.simulate import ground_truth_path, load_ground_truth

            gt_file = ground_truth_path(clip)
            if clip.is_file() and gt_file.exists():
                gt = load_ground_truth(gt_file)
            source = {"kind": "video", "path": str(clip), "ground_truth": str(gt_file) if gt is not None else None}
        report["source"] = source
        if simulate_seconds is not None:
            report["simulate_seconds"] = simulate_seconds

        decoded: dict[int | None, tuple] = {}
        results: dict[str, dict] = {}
        for name, est in built.items():
            width = getattr(est, "input_width", None)
            if width not in decoded:
                limit = frames if video is not None else None
                decoded[width] = decode_frames(clip, width, limit)
            frs, decode_ms, info = decoded[width]
            if len(frs) < 2:
                raise BadInput(f"{clip}: fewer than 2 frames to benchmark")
            full_size = tuple(info.source_size)
            if show_progress:
                console.print(f"[dim]bench: {name} on {len(frs)} frames...[/dim]")
            warmup_ms = warm_up(est, frs, full_size)
            pairwise, st = time_estimator(est, frs, full_size)
            st.decode = list(decode_ms)
            n = len(frs)
            per_frame = np.asarray(st.decode[:n]) + np.asarray(st.preprocess[:n]) + np.asarray((st.estimate + [0.0] * n)[:n])
            total_ms = float(per_frame.sum())
            entry: dict = {
                "ms_per_frame": total_ms / n,
                "fps": 1000.0 * n / total_ms if total_ms > 0 else None,
                "stages": {"decode": time_stats(st.decode), "preprocess": time_stats(st.preprocess), "estimate": time_stats(st.estimate)},
                "cpu": time_stats(st.cpu),
                "latency": time_stats(per_frame),
                "frames": n,
                "work_width": getattr(est, "work_width", None),
                "device": str(getattr(est, "device", "cpu")),
                "mace": None,
            }
            if warmup_ms is not None:
                entry["warmup_ms"] = warmup_ms
            if gt is not None and len(pairwise):
                m = evaluate(pairwise, gt)
                entry.update({k: m[k] for k in ("mace", "corner_error", "corner_error_mean", "failure_rate", "pairs")})
            gpu = gpu_batch(name, work_width, weights, frs, full_size)
            if gpu:
                entry["gpu_batch"] = gpu
            results[name] = entry
        report["estimators"] = results
    report["notes"] = notes
    return report


def run_flights(options: BenchOptions, show_progress: bool = True) -> dict:
    """Score the estimators over every flight of ``options.flights``; returns the report dict
    (see the module doc).  Memory: one flight's decoded frames at a time."""
    from mosaic_cli.progress import progress_task

    folder, work_width, device, weights = options.flights, options.work_width, options.device, options.weights
    assert folder is not None
    flights = find_flights(folder)
    notes: list[str] = []
    built = build_estimators(options.labels, work_width, device, weights, options.estimators is not None, notes)
    widths: dict[int, list[str]] = {}
    for label, est in built.items():
        widths.setdefault(est.input_width, []).append(label)
    scores: dict[str, list[FlightScore]] = {label: [] for label in built}
    paths: dict[str, dict[str, int]] = {label: {} for label in built}  # which path made each pair (learned)
    decode_ms: list[float] = []
    total = sum(f.gt.frames for f in flights) * len(built)
    with progress_task("bench", total, disable=not show_progress) as advance:
        for flight in flights:
            for width, labels in widths.items():
                frames, decode, info = decode_frames(flight.video, width)
                decode_ms += decode
                for label in labels:
                    advance(0, status=f"{label} on {flight.name}")
                    pairwise, times = time_estimator(built[label], frames, tuple(info.source_size), advance)
                    scores[label].append(score_flight(flight, pairwise, times))
                    for path, count in getattr(built[label], "path_counts", {}).items():
                        paths[label][path] = paths[label].get(path, 0) + count
                del frames
    profiles = sorted({f.profile for f in flights}, key=lambda p: (PROFILE_ORDER.index(p) if p in PROFILE_ORDER else len(PROFILE_ORDER), p))
    results = {}
    for label, runs in scores.items():
        entry = pool(runs)
        entry["profiles"] = {p: pool([r for r in runs if r.profile == p]) for p in profiles}
        entry["per_flight"] = {r.flight: r.metrics for r in runs}
        # Every pair's corner error (and whether it touches a burst), so that two estimators can be
        # compared pair by pair (``python -m benchmarks estimators paired-failures``).
        entry["per_pair"] = {r.flight: {"corner_errors": [round(float(e), 3) if np.isfinite(e) else None for e in r.corner_errors],
                                        **({"touches_burst": r.touches_burst.astype(int).tolist()} if r.touches_burst is not None else {})}
                             for r in runs}
        entry["device"] = str(getattr(built[label], "device", "cpu"))
        entry["work_width"] = getattr(built[label], "work_width", None)
        if paths[label]:
            entry["paths"] = paths[label]
        results[label] = entry
    return {
        "version": 1,
        "machine": machine(),
        "source": {"kind": "flights", "path": str(folder), "flights": [f.name for f in flights], "profiles": profiles,
                   "frames": sum(f.gt.frames for f in flights)},
        "settings": {"work_width": work_width, "device": device, "weights": str(weights) if weights else None},
        "decode": time_stats(decode_ms),
        "estimators": results,
        "notes": notes,
        "units": "1280x720-equivalent px; ms per frame = preprocess + estimate (decoding excluded, shared)",
    }
