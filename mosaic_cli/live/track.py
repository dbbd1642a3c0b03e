"""``track`` as frames arrive: the homographies as JSON Lines, one pair a line, flushed at once.

Each line is ``{"frame": t, "H": [[...], [...], [...]], "confidence": c}`` (and, from the learned
estimator, ``"path"``: learned, fallback, carried or failed): H maps pixel
(x, y) of frame t to frame t+1 (full-resolution pixels, OpenCV pixel centres), as ``pairwise[t]``
of the JSON format.  A program can follow the file (or the pipe) line by line.  From a live
source a ``.json`` or ``.npy`` output is written once, at the end, from every frame received.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import itertools
import json
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import numpy as np

from mosaic_cli.atomic import check_writable
from mosaic_cli.errors import BadInput, ProcessingError
from mosaic_cli.estimators import Estimator, estimate_stream
from mosaic_cli.live.loading import begin, waited_for
from mosaic_cli.live.source import DEFAULT_TIMEOUT, LiveStream, is_live_source
from mosaic_cli.overlay import MaskOptions, live_mask
from mosaic_cli.progress import stream_progress
from mosaic_cli.track import TrackResult
from mosaic_cli.video import VideoInfo, open_video
from mosaic_cli.video.lens_filter import ImageFilter

STDOUT = "-"
JSONL_SUFFIXES = (".jsonl", ".ndjson")


def is_jsonl(out: str | Path) -> bool:
    return str(out) == STDOUT or Path(out).suffix.lower() in JSONL_SUFFIXES


def pair_line(index: int, H: np.ndarray, confidence: float, path: str | None = None) -> str:
    line = {"frame": int(index), "H": np.asarray(H, dtype=np.float64).tolist(), "confidence": float(confidence)}
    if path is not None:
        line["path"] = path
    return json.dumps(line) + "\n"


@contextlib.contextmanager
def _line_sink(out: str | Path, keep_on_failure: bool) -> Iterator[IO[str]]:
    """Standard output, or the file under its final name (a follower reads it as it grows).
    A failed or interrupted run removes the file unless ``keep_on_failure`` (a live run:
    the lines so far are what was received)."""
    if str(out) == STDOUT:
        yield sys.stdout
        return
    path = check_writable(out)
    fh = open(path, "w")
    try:
        yield fh
    except BaseException:
        fh.close()
        if not keep_on_failure:
            path.unlink(missing_ok=True)
        raise
    fh.close()


def track_stream(source: str | Path, estimator: Estimator | concurrent.futures.Future, out: str | Path, timeout: float = DEFAULT_TIMEOUT,
                 max_frames: int | None = None, show_progress: bool = True, mask: MaskOptions | None = None,
                 info: VideoInfo | None = None, width: int | None = None, lens: ImageFilter | None = None) -> TrackResult:
    """Track ``source`` (a live source, or a file when ``out`` takes JSON Lines), writing
    each pair as it is estimated when ``out`` takes JSON Lines; returns everything tracked.
    ``mask``: the ``--mask`` of a live input, applied once the stream gives the frame size
    (overlay detection is skipped: see :func:`mosaic_cli.overlay.live_mask`); a file's mask
    is set on the estimator beforehand; ``info``: a file's probe, when the caller has it.
    ``estimator`` may still be loading (a future of it, :func:`~mosaic_cli.live.loading.built_beside`:
    a live input's stream then opens first, its frames decoded ``width`` wide, and waits for it).
    The estimator is closed when the stream ends (:meth:`~mosaic_cli.estimators.Estimator.close`).
    ``lens``: the frames through this filter as they are decoded (``--lens``)."""
    loading = estimator if isinstance(estimator, concurrent.futures.Future) else None
    live = is_live_source(source)
    pairwise: list[np.ndarray] = []
    confidence: list[float] = []
    paths: list[str | None] = []
    if loading is not None and (not live or width is None):
        raise ValueError("a loading estimator goes with a live input and the width it works at")
    with waited_for(loading):
        if live:
            stream = LiveStream(str(source), "gray", width=width if loading is not None else estimator.input_width, timeout=timeout,
                                quiet=not show_progress, on_started=lambda: begin(loading), lens=lens)
        else:
            stream = open_video(source, width=estimator.input_width, gray=True, info=info, lens=lens)
        if loading is not None:
            try:
                estimator = loading.result()
            except BaseException:
                stream.close()  # a failed load: its error, the stream closed first
                raise
    assert isinstance(estimator, Estimator)
    lines = is_jsonl(out)
    with estimator, stream, (_line_sink(out, keep_on_failure=live) if lines else contextlib.nullcontext()) as sink:
        info = stream.info
        masked = None
        if mask is not None:
            masked = live_mask(mask, info.source_size, show_progress, lens)
            estimator.set_mask(masked.use)

        start = time.perf_counter()
        with stream_progress(f"track ({estimator.name})", disable=not show_progress) as advance:
            advance(1)  # the first frame yields no pair
            for t, estimate in enumerate(estimate_stream(estimator, itertools.islice(stream, max_frames), info.source_size)):
                pairwise.append(estimate.H)
                confidence.append(estimate.confidence)
                paths.append(estimate.path)
                if sink is not None:
                    try:
                        sink.write(pair_line(t, estimate.H, estimate.confidence, estimate.path))
                        sink.flush()
                    except BrokenPipeError:
                        raise ProcessingError("standard output was closed by the reader") from None
                advance(1)
        elapsed = time.perf_counter() - start
    if not pairwise:
        raise BadInput(f"{info.path}: fewer than two frames received")
    n = len(pairwise) + 1
    meta = {"ms_per_frame": 1000.0 * elapsed / n, "seconds": elapsed, "work_width": estimator.work_width}
    if getattr(estimator, "path_counts", None):  # the learned estimator: which path made each pair
        meta["paths"] = dict(estimator.path_counts)
    if live:
        meta["ended_by"] = stream.ended_by
    if masked is not None:
        meta["mask"] = masked.to_json()
    from dataclasses import replace

    info = replace(info, frame_count=n)
    return TrackResult(info, estimator.name, np.array(pairwise).reshape(-1, 3, 3),
                       np.array(confidence, dtype=np.float64), meta,
                       [str(p) for p in paths] if all(p is not None for p in paths) else None)
