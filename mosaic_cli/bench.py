"""Benchmark estimators: latency per stage, throughput and accuracy on one clip.

Stages are timed separately, per frame:

* decode: pulling the frame out of the encoded video (``open_video``, gray, at the
  estimator's input width; every estimator with the same input width gets the very same
  decoded frames, decoded once and kept in memory);
* preprocess: ``estimator.prepare(frame)``;
* estimate: ``estimator.feed`` on the prepared frame (a batching estimator's time is spread
  over the frames of the batch it returns).

With no video, a short flight is simulated first, so accuracy (MACE, corner error, failure
rate, see :mod:`mosaic_cli.evaluate`) comes with the timings.  A video with a ``.gt.json``
beside it (a simulated flight) is scored too; any other video gives latency only.

:func:`run_flights` scores a folder of flights (every video ``X.mp4`` with its ``X.gt.json``): each
flight is decoded once and every estimator runs on the same frames; MACE pools the landmark
pairs of all flights (the paper's protocol), corner errors and failures pool the frame pairs,
and a breakdown per flight profile (paper / fast / hard ...) comes with the totals.

Estimators are named as on the command line, options included (``cnn:refine=none``); their
name is their label in the report, so one estimator can be run with several settings.
"""

from __future__ import annotations

import os
import platform
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mosaic_cli.errors import BadInput, MosaicError
from mosaic_cli.estimators import LEARNED
from mosaic_cli.inputs import check_weights_file
from mosaic_cli.simulate import SimulateOptions

DEFAULT_ESTIMATORS = (*LEARNED, "orb", "orb-paper", "identity")
MAX_DECODED_BYTES = 1_500_000_000  # frames kept in memory for one input width


@dataclass
class StageTimes:
    decode: list[float] = field(default_factory=list)
    preprocess: list[float] = field(default_factory=list)
    estimate: list[float] = field(default_factory=list)
    cpu: list[float] = field(default_factory=list)


def _stats(ms: list[float] | np.ndarray) -> dict:
    a = np.asarray(ms, dtype=np.float64)
    if len(a) == 0:
        return {"p50": None, "p95": None, "mean": None}
    return {"p50": float(np.percentile(a, 50)), "p95": float(np.percentile(a, 95)), "mean": float(a.mean())}


def decode_frames(path: str | Path, width: int | None, max_frames: int | None = None) -> tuple[list[np.ndarray], list[float], object]:
    """Decode gray frames at ``width`` into memory; per-frame decode times (ms) and the info."""
    from mosaic_cli.video import open_video

    frames: list[np.ndarray] = []
    times: list[float] = []
    with open_video(path, width=width, gray=True) as stream:
        info = stream.info
        it = iter(stream)
        budget = MAX_DECODED_BYTES
        while max_frames is None or len(frames) < max_frames:
            t0 = time.perf_counter()
            try:
                frame = next(it)
            except StopIteration:
                break
            times.append((time.perf_counter() - t0) * 1000.0)
            frames.append(frame)
            budget -= frame.nbytes
            if budget < 0:
                raise BadInput(f"{path}: too many frames to benchmark in memory at width {frame.shape[1]}: use --frames")
    return frames, times, info


def time_estimator(estimator, frames: list[np.ndarray], full_size: tuple[int, int], advance=None) -> tuple[np.ndarray, StageTimes]:
    """Run ``estimator`` over in-memory frames; pairwise (N-1, 3, 3) and per-frame stage times
    (ms): wall clock per stage, and the process's CPU time of preprocess + estimate in ``cpu``
    (all threads; less moved by other jobs on a shared machine).  Preprocess is what the
    estimator's own :class:`~mosaic_cli.estimators.base.StageTimer` records for ``prepare``; the
    rest of each ``feed`` is estimation, spread evenly over the frames of a batch when a batched
    estimator answers several at once."""
    from mosaic_cli.estimators.base import StageTimer

    times = StageTimes()
    estimates = []
    estimator.reset(full_size)
    timer, previous = StageTimer(), estimator.timings
    estimator.timings = timer
    try:
        pending = pending_cpu = 0.0
        waiting = 0
        for frame in frames:
            before = timer.total("prepare")
            c0, t0 = time.process_time(), time.perf_counter()
            out = estimator.feed(frame)
            t2, c2 = time.perf_counter(), time.process_time()
            prepare_ms = timer.total("prepare") - before
            times.preprocess.append(prepare_ms)
            pending += (t2 - t0) * 1000.0 - prepare_ms
            pending_cpu += (c2 - c0) * 1000.0
            waiting += 1
            if out:
                estimates.extend(out)
                times.estimate.extend([pending / waiting] * waiting)
                times.cpu.extend([pending_cpu / waiting] * waiting)
                pending, pending_cpu, waiting = 0.0, 0.0, 0
            if advance is not None:
                advance(1)
        c0, t0 = time.process_time(), time.perf_counter()
        out = estimator.finish()
        pending += (time.perf_counter() - t0) * 1000.0
        pending_cpu += (time.process_time() - c0) * 1000.0
        estimates.extend(out)
        if waiting:
            times.estimate.extend([pending / waiting] * waiting)
            times.cpu.extend([pending_cpu / waiting] * waiting)
        elif times.estimate and pending > 0:
            times.estimate[-1] += pending
            times.cpu[-1] += pending_cpu
    finally:
        estimator.timings = previous
    pairwise = np.array([e.H for e in estimates], dtype=np.float64).reshape(-1, 3, 3)
    return pairwise, times


def _gpu_name() -> str | None:
    try:
        import torch

        if torch.cuda.is_available():
            return torch.cuda.get_device_name(0)
    except Exception:  # torch missing or broken CUDA: no GPU to report
        return None
    return None


def _learned(label: str) -> bool:
    from mosaic_cli.estimators import parse_spec

    return parse_spec(label)[0] in LEARNED


def build_estimators(labels: list[str], work_width: int, device: str, weights: str | None, explicit: bool, notes: list[str]) -> dict:
    """label -> estimator, for names as the command line gives them (options included).  The
    learned ones get ``weights``; when the names are the defaults (not ``explicit``), a learned
    estimator that cannot be built (no shipped weights, a checkpoint of the other head) is
    skipped with a note instead of failing."""
    from mosaic_cli.estimators import make_estimator

    built = {}
    for label in labels:
        learned = _learned(label)
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


def _labels(estimators: list[str] | None) -> list[str]:
    # Not lowercased: a weights=FILE option keeps its case (parse_spec lowercases names and keys).
    return [n.strip() for n in (estimators if estimators is not None else list(DEFAULT_ESTIMATORS)) if n.strip()]


def _warm_up(estimator, frames: list[np.ndarray], full_size: tuple[int, int]) -> float | None:
    """On a GPU, one chunk run before the timed pass (ms): CUDA builds its kernels and cuDNN its
    plans on first use (1.6 s for the lstm's first 16 pairs on an H200), which a per-frame figure
    would otherwise carry.  The build now warms the network up itself (``LearnedEstimator.warm_up``,
    beside the command's other work): this is what is left of it for a real flight's first chunk.
    None on a CPU, where the timed pass starts cold as a command does."""
    if "cuda" not in str(getattr(estimator, "device", "cpu")):
        return None
    import torch

    chunk = int(getattr(getattr(estimator, "config", None), "chunk", 16))
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    time_estimator(estimator, frames[: chunk + 1], full_size)
    torch.cuda.synchronize()
    return 1000.0 * (time.perf_counter() - t0)


def _gpu_batch(label: str, work_width: int, weights: str | None, frames: list[np.ndarray], full_size, chunks=(1, 16, 64)) -> dict | None:
    """Throughput of a learned estimator on the GPU (frames per second) for chunks of 1 pair (each
    pair answered as its frame arrives, as live input is), 16 (the default) and 64."""
    try:
        import torch

        if not torch.cuda.is_available() or not _learned(label):
            return None
        from mosaic_cli.estimators import make_estimator
    except Exception:  # no torch: no GPU numbers
        return None
    out = {}
    for chunk in chunks:
        est = make_estimator(label, weights=weights, device="cuda", chunk=int(chunk))
        for _ in range(2):  # warm-up, then timed
            torch.cuda.synchronize()
            t0 = time.perf_counter()
            est.reset(full_size)
            for f in frames:
                est.feed(f)
            est.finish()
            torch.cuda.synchronize()
            elapsed = time.perf_counter() - t0
        out[f"chunk_{chunk}"] = {"fps": len(frames) / elapsed, "ms_per_frame": 1000.0 * elapsed / len(frames)}
    return out


def simulated_flight(**options: Any) -> SimulateOptions:
    """The benchmark's simulated flight (``options``: SimulateOptions' profile, frames, size,
    seed, ...): a short clip encoded fast, since the benchmark times the estimators, not the encoder."""
    return SimulateOptions(crf=18, preset="veryfast", **options)


@dataclass
class BenchOptions:
    """What ``mosaic bench`` times and scores: a simulated flight (``flight``), a ``video``
    (at most ``flight.frames`` of it) or a folder of ``flights``."""

    estimators: list[str] | None = None  # as on the command line, options included; None: DEFAULT_ESTIMATORS
    video: Path | None = None
    flights: Path | None = None
    map_image: Path | None = None  # the simulated flight's map; None: procedural
    flight: SimulateOptions = field(default_factory=simulated_flight)
    weights: str | None = None  # for the learned estimators
    work_width: int = 320  # of the classical estimators
    device: str = "auto"
    threads: int | None = None  # torch's CPU threads for the learned estimators

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """The flags (the simulated flight's checked themselves); the paths are the request's (:func:`check_request`)."""
        from mosaic_cli.device import check_device
        from mosaic_cli.estimators import check_work_width
        from mosaic_cli.inputs import check_threads

        if self.estimators is not None:
            labels = _labels(self.estimators)
            if not labels:
                raise BadInput("--estimators is empty")
            if len(set(labels)) != len(labels):
                raise BadInput("--estimators names an estimator twice")
        if self.flights is not None and (self.video is not None or self.map_image is not None):
            raise BadInput("give --flights or --video/--map, not both")
        if self.video is not None and self.map_image is not None:
            raise BadInput("give --video or --map, not both")
        check_work_width(self.work_width)
        check_device(self.device)
        check_threads(self.threads)

    @property
    def labels(self) -> list[str]:
        return _labels(self.estimators)


def check_request(options: BenchOptions) -> None:
    """The inputs exist, before any estimator is built or frame decoded."""
    if options.video is not None and not options.video.exists():
        raise BadInput(f"{options.video}: no such file or folder")
    if options.flights is not None and not options.flights.is_dir():
        raise BadInput(f"--flights {options.flights}: no such folder")
    if options.weights is not None:
        check_weights_file(options.weights)
    if options.map_image is not None and not options.map_image.exists():
        raise BadInput(f"{options.map_image}: no such file")


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
        "machine": _machine(),
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
            warmup_ms = _warm_up(est, frs, full_size)
            pairwise, st = time_estimator(est, frs, full_size)
            st.decode = list(decode_ms)
            n = len(frs)
            per_frame = np.asarray(st.decode[:n]) + np.asarray(st.preprocess[:n]) + np.asarray((st.estimate + [0.0] * n)[:n])
            total_ms = float(per_frame.sum())
            entry: dict = {
                "ms_per_frame": total_ms / n,
                "fps": 1000.0 * n / total_ms if total_ms > 0 else None,
                "stages": {"decode": _stats(st.decode), "preprocess": _stats(st.preprocess), "estimate": _stats(st.estimate)},
                "cpu": _stats(st.cpu),
                "latency": _stats(per_frame),
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
            gpu = _gpu_batch(name, work_width, weights, frs, full_size)
            if gpu:
                entry["gpu_batch"] = gpu
            results[name] = entry
        report["estimators"] = results
    report["notes"] = notes
    return report


# --------------------------------------------------------------------------------------------
# A folder of flights


@dataclass
class Flight:
    name: str
    video: Path
    gt: object  # GroundTruth

    @property
    def profile(self) -> str:
        return self.gt.profile


@dataclass
class FlightScore:
    """One estimator on one flight: the raw errors, so that flights pool exactly."""

    flight: str
    profile: str
    landmark_errors: np.ndarray  # mean landmark error of each (f1, f2) pair (px, 1280x720-equivalent)
    corner_errors: np.ndarray  # per frame pair
    ms: np.ndarray  # per frame: preprocess + estimate, wall clock
    cpu_ms: np.ndarray  # per frame: preprocess + estimate, process CPU time
    metrics: dict  # mosaic_cli.evaluate.evaluate of this flight alone (what `mosaic eval` prints)
    touches_burst: np.ndarray | None = None  # per frame pair: it touches a frame without a motion cue (gt "bursts")


def find_flights(folder: str | Path) -> list[Flight]:
    """The flights of ``folder`` (:func:`mosaic_cli.inputs.find_flights`) with their ground truth."""
    from mosaic_cli.inputs import find_flights as find_flight_videos
    from mosaic_cli.simulate import ground_truth_path, load_ground_truth

    return [Flight(v.stem, v, load_ground_truth(ground_truth_path(v))) for v in find_flight_videos(folder, "--flights")]


def score_flight(flight: Flight, pairwise: np.ndarray, times: StageTimes) -> FlightScore:
    """MACE by the paper's protocol (landmark pairs every 30 frames, from the exact ground truth,
    on the frames the prediction covers), corner errors and per-frame times of one run."""
    from mosaic_cli.evaluate import corner_errors, evaluate, landmarks_from_ground_truth, mace_pairs
    from mosaic_cli.simulate.bursts import burst_pairs

    gt = flight.gt
    n = len(pairwise)
    ann = landmarks_from_ground_truth(gt)
    ann = ann[ann[:, 3] <= n]
    landmark = mace_pairs(pairwise, ann, gt.size)[1] if len(ann) else np.zeros(0)
    corners = corner_errors(pairwise, np.asarray(gt.pairwise)[:n], gt.size)
    frames = len(times.preprocess)
    ms = np.asarray(times.preprocess[:frames]) + np.asarray(times.estimate[:frames])
    touches = burst_pairs(gt.bursts, n) if gt.bursts else None
    return FlightScore(flight.name, flight.profile, landmark, corners, ms, np.asarray(times.cpu[:frames]), evaluate(pairwise, gt, ann),
                       touches)


def pool(scores: list[FlightScore]) -> dict:
    """The metrics of several flights taken together: MACE = mean over all their landmark pairs,
    corner error = median over all their frame pairs, failure rate = share of those pairs with a
    corner error above evaluate.FAILURE_PX, times = p50 over all their frames; on flights with
    bursts, the failure rate of the pairs that touch a burst and of the others apart."""
    from mosaic_cli.evaluate import FAILURE_PX

    touched = [(s.corner_errors, s.touches_burst) for s in scores if s.touches_burst is not None]
    bursts = {}
    if touched:
        errors = np.concatenate([e for e, _ in touched])
        mask = np.concatenate([m for _, m in touched])
        bursts = {"burst_pairs": int(mask.sum()), "burst_failure_rate": float(np.mean(errors[mask] > FAILURE_PX)) if mask.any() else None,
                  "other_failure_rate": float(np.mean(errors[~mask] > FAILURE_PX)) if (~mask).any() else None}
    landmark = np.concatenate([s.landmark_errors for s in scores])
    corners = np.concatenate([s.corner_errors for s in scores])
    ms = np.concatenate([s.ms for s in scores])
    cpu = np.concatenate([s.cpu_ms for s in scores])
    return {
        "mace": float(landmark.mean()) if len(landmark) else None,
        "corner_error": float(np.median(corners)),
        "failure_rate": float(np.mean(corners > FAILURE_PX)),
        "ms_per_frame": _stats(ms),
        "cpu_ms_per_frame": _stats(cpu),
        "flights": len(scores),
        "pairs": int(len(corners)),
        "landmark_pairs": int(len(landmark)),
        **bursts,
    }


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
        "machine": _machine(),
        "source": {"kind": "flights", "path": str(folder), "flights": [f.name for f in flights], "profiles": profiles,
                   "frames": sum(f.gt.frames for f in flights)},
        "settings": {"work_width": work_width, "device": device, "weights": str(weights) if weights else None},
        "decode": _stats(decode_ms),
        "estimators": results,
        "notes": notes,
        "units": "1280x720-equivalent px; ms per frame = preprocess + estimate (decoding excluded, shared)",
    }


PROFILE_ORDER = ("paper", "survey", "fast", "shaky", "shaky-tilt", "hard", "extreme", "bursts")


def _machine() -> dict:
    threads = None
    try:
        import torch

        threads = torch.get_num_threads()
    except Exception:  # no torch: no thread count to report
        pass
    return {"cpus": os.cpu_count(), "platform": platform.platform(), "gpu": _gpu_name(), "torch_threads": threads}


def render_flights_table(report: dict):
    """A rich table of a :func:`run_flights` report: totals, then MACE per profile."""
    from rich.table import Table

    src = report["source"]
    profiles = src["profiles"]
    table = Table(title=f"bench: {len(src['flights'])} flights in {src['path']} ({src['frames']} frames)", title_justify="left")
    table.add_column("estimator", no_wrap=True)
    with_bursts = any(e.get("burst_pairs") for e in report["estimators"].values())
    burst_cols = ("burst pairs\nfailed", "carried\npairs") if with_bursts else ()
    for col in ("MACE\nall", *[f"MACE / failed\n{p}" for p in profiles], "corner px\nmedian", "failure\nrate",
                *burst_cols, "fallback\npairs", "ms/frame\np50", "CPU ms/fr\np50"):
        table.add_column(col, justify="right", no_wrap=True)

    def num(v, fmt):
        return "-" if v is None else fmt.format(v)

    for label, e in report["estimators"].items():
        paths = e.get("paths")
        fallback = paths.get("fallback", 0) / max(1, sum(paths.values())) if paths else None
        carried = paths.get("carried", 0) / max(1, sum(paths.values())) if paths else None
        burst_cells = (num(e.get("burst_failure_rate"), "{:.1%}"), num(carried, "{:.1%}")) if with_bursts else ()
        table.add_row(
            label,
            num(e["mace"], "{:.2f}"),
            *[f"{num(e['profiles'][p]['mace'], '{:.2f}')} / {e['profiles'][p]['failure_rate']:.1%}" for p in profiles],
            num(e["corner_error"], "{:.2f}"),
            num(e["failure_rate"], "{:.1%}"),
            *burst_cells,
            num(fallback, "{:.1%}"),
            num(e["ms_per_frame"]["p50"], "{:.2f}"),
            num(e["cpu_ms_per_frame"]["p50"], "{:.2f}"),
        )
    return table


def render_table(report: dict):
    """A rich table of a bench report."""
    from rich.table import Table

    src = report.get("source", {})
    title = (
        f"bench: simulated {src.get('profile')} flight, {src.get('frames')} frames {src.get('size', ['?', '?'])[0]}x{src.get('size', ['?', '?'])[1]}"
        if src.get("kind") == "simulated"
        else f"bench: {src.get('path')}"
    )
    table = Table(title=title, title_justify="left")
    table.add_column("estimator", no_wrap=True)
    for col in ("decode ms\np50/p95", "prep ms\np50/p95", "estimate ms\np50/p95", "ms per\nframe", "fps", "MACE\npx", "corner px\nmedian", "failure\nrate"):
        table.add_column(col, justify="right", no_wrap=True)

    def pair(s):
        return "-" if s["p50"] is None else f"{s['p50']:.2f}/{s['p95']:.2f}"

    def num(v, fmt):
        return "-" if v is None else fmt.format(v)

    for name, e in report["estimators"].items():
        st = e["stages"]
        table.add_row(
            name,
            pair(st["decode"]),
            pair(st["preprocess"]),
            pair(st["estimate"]),
            num(e["ms_per_frame"], "{:.2f}"),
            num(e["fps"], "{:.1f}"),
            num(e.get("mace"), "{:.2f}"),
            num(e.get("corner_error"), "{:.2f}"),
            num(e.get("failure_rate"), "{:.1%}"),
        )
    return table
