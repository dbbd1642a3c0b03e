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
"""

from __future__ import annotations

import os
import platform
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput, MosaicError

DEFAULT_ESTIMATORS = ("lstm", "cnn", "orb", "identity")
LEARNED = ("lstm", "cnn")
MAX_DECODED_BYTES = 1_500_000_000  # frames kept in memory for one input width


@dataclass
class StageTimes:
    decode: list[float] = field(default_factory=list)
    preprocess: list[float] = field(default_factory=list)
    estimate: list[float] = field(default_factory=list)


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


def time_estimator(estimator, frames: list[np.ndarray], full_size: tuple[int, int]) -> tuple[np.ndarray, StageTimes]:
    """Run ``estimator`` over in-memory frames; pairwise (N-1, 3, 3) and per-frame stage times (ms)."""
    times = StageTimes()
    estimates = []
    estimator.reset(full_size)
    holder: list = [None]
    original = estimator.prepare
    # feed() calls self.prepare(frame): hand it the frame prepared (and timed) just before.
    estimator.prepare = lambda _frame: holder[0]
    try:
        pending = 0.0
        waiting = 0
        for frame in frames:
            t0 = time.perf_counter()
            holder[0] = original(frame)
            t1 = time.perf_counter()
            out = estimator.feed(frame)
            t2 = time.perf_counter()
            times.preprocess.append((t1 - t0) * 1000.0)
            pending += (t2 - t1) * 1000.0
            waiting += 1
            if out:
                estimates.extend(out)
                times.estimate.extend([pending / waiting] * waiting)
                pending, waiting = 0.0, 0
        t0 = time.perf_counter()
        out = estimator.finish()
        pending += (time.perf_counter() - t0) * 1000.0
        estimates.extend(out)
        if waiting:
            times.estimate.extend([pending / waiting] * waiting)
        elif times.estimate and pending > 0:
            times.estimate[-1] += pending
    finally:
        del estimator.prepare
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


def _build(name: str, work_width: int, device: str, explicit: bool, notes: list[str]):
    from mosaic_cli.estimators import make_estimator

    try:
        return make_estimator(name, work_width=work_width, device=device)
    except (MosaicError, ImportError, OSError) as exc:
        if explicit or name not in LEARNED:
            if isinstance(exc, MosaicError):
                raise
            raise BadInput(f"estimator {name!r} is unavailable: {exc}") from None
        notes.append(f"{name}: skipped ({str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__})")
        return None


def _gpu_batch(name: str, work_width: int, frames: list[np.ndarray], full_size, chunks=(16, 64)) -> dict | None:
    """Throughput of a learned estimator on the GPU for larger batches (frames per second)."""
    try:
        import torch

        if not torch.cuda.is_available() or name not in LEARNED:
            return None
        from mosaic_cli.estimators import make_estimator
    except Exception:  # no torch: no GPU numbers
        return None
    out = {}
    for chunk in chunks:
        est = make_estimator(name, work_width=work_width, device="cuda")
        if not hasattr(est, "config") or not hasattr(est.config, "chunk"):
            return None
        est.config.chunk = int(chunk)
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


def run_bench(
    video: str | Path | None = None,
    map_path: str | Path | None = None,
    estimators: list[str] | None = None,
    profile: str = "paper",
    frames: int = 300,
    size: tuple[int, int] = (1280, 720),
    work_width: int = 320,
    device: str = "auto",
    seed: int = 0,
    show_progress: bool = True,
) -> dict:
    """Benchmark ``estimators`` on ``video`` (or a simulated flight) and return the report dict."""
    from mosaic_cli.evaluate import evaluate
    from mosaic_cli.progress import console

    if video is not None and map_path is not None:
        raise BadInput("give --video or --map, not both")
    if frames < 2:
        raise BadInput(f"--frames must be at least 2, got {frames}")
    explicit = estimators is not None
    names = [n.strip().lower() for n in (estimators or list(DEFAULT_ESTIMATORS)) if n.strip()]
    if not names:
        raise BadInput("--estimators is empty")
    if len(set(names)) != len(names):
        raise BadInput("--estimators names an estimator twice")
    notes: list[str] = []
    built = {}
    for name in names:
        est = _build(name, work_width, device, explicit, notes)
        if est is not None:
            built[name] = est
    if not built:
        raise BadInput("no estimator to benchmark")

    report: dict = {
        "version": 1,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "gpu": _gpu_name()},
        "settings": {"frames": frames, "work_width": work_width, "device": device},
    }
    with tempfile.TemporaryDirectory(prefix="mosaic-bench-") as tmp:
        gt = None
        simulate_seconds = None
        if video is None:
            from mosaic_cli.simulate import simulate_flight

            clip = Path(tmp) / "bench.mp4"
            t0 = time.perf_counter()
            gt = simulate_flight(clip, map_path, profile, frames, size, 30.0, seed, crf=18, preset="veryfast", show_progress=show_progress)
            simulate_seconds = time.perf_counter() - t0
            source = {"kind": "simulated", "profile": profile, "frames": frames, "size": list(size), "map": gt.map_name, "seed": seed}
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
            pairwise, st = time_estimator(est, frs, full_size)
            st.decode = list(decode_ms)
            n = len(frs)
            per_frame = np.asarray(st.decode[:n]) + np.asarray(st.preprocess[:n]) + np.asarray((st.estimate + [0.0] * n)[:n])
            total_ms = float(per_frame.sum())
            entry: dict = {
                "ms_per_frame": total_ms / n,
                "fps": 1000.0 * n / total_ms if total_ms > 0 else None,
                "stages": {"decode": _stats(st.decode), "preprocess": _stats(st.preprocess), "estimate": _stats(st.estimate)},
                "latency": _stats(per_frame),
                "frames": n,
                "work_width": getattr(est, "work_width", None),
                "device": str(getattr(est, "device", "cpu")),
                "mace": None,
            }
            if gt is not None and len(pairwise):
                m = evaluate(pairwise, gt)
                entry.update({k: m[k] for k in ("mace", "corner_error", "corner_error_mean", "failure_rate", "pairs")})
            gpu = _gpu_batch(name, work_width, frs, full_size) if name in LEARNED else None
            if gpu:
                entry["gpu_batch"] = gpu
            results[name] = entry
        report["estimators"] = results
    report["notes"] = notes
    return report


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
