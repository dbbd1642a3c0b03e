"""Timing an estimator: frames decoded into memory, then per frame the wall-clock time of each
stage (decode, preprocess, estimate) and the process's CPU time; on a GPU, the warm-up chunk and
the batch throughput; the machine the times were taken on."""

from __future__ import annotations

import os
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mosaic_cli.bench.options import is_learned
from mosaic_cli.errors import BadInput

MAX_DECODED_BYTES = 1_500_000_000  # frames kept in memory for one input width


@dataclass
class StageTimes:
    decode: list[float] = field(default_factory=list)
    preprocess: list[float] = field(default_factory=list)
    estimate: list[float] = field(default_factory=list)
    cpu: list[float] = field(default_factory=list)


def time_stats(ms: list[float] | np.ndarray) -> dict:
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


def warm_up(estimator, frames: list[np.ndarray], full_size: tuple[int, int]) -> float | None:
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


def gpu_batch(label: str, work_width: int, weights: str | None, frames: list[np.ndarray], full_size, chunks=(1, 16, 64)) -> dict | None:
    """Throughput of a learned estimator on the GPU (frames per second) for chunks of 1 pair (each
    pair answered as its frame arrives, as live input is), 16 (the default) and 64."""
    try:
        import torch

        if not torch.cuda.is_available() or not is_learned(label):
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


def gpu_name() -> str | None:
    try:
        import torch

        if torch.cuda.is_available():
            return torch.cuda.get_device_name(0)
    except Exception:  # torch missing or broken CUDA: no GPU to report
        return None
    return None


def machine() -> dict:
    threads = None
    try:
        import torch

        threads = torch.get_num_threads()
    except Exception:  # no torch: no thread count to report
        pass
    return {"cpus": os.cpu_count(), "platform": platform.platform(), "gpu": gpu_name(), "torch_threads": threads}
