"""The streaming estimator interface shared by every homography estimator.

An estimator is stateful: ``reset`` starts a video, ``feed`` takes its frames in order and
returns the pairwise estimates that are ready (zero or more: a batched estimator may hold
frames back to run them together), ``finish`` returns the rest.  Estimate k always maps
frame k to frame k+1 in full-resolution pixels (see :mod:`mosaic_cli.geometry`).

Stage times, for benchmarks: set ``estimator.timings = StageTimer()`` and every ``prepare``
(gray, working size: one per frame) that ``feed`` runs is timed into it, call by call; the
rest of ``feed`` and ``finish`` is estimation.  Nothing is timed while ``timings`` is None.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from mosaic_cli.geometry import to_resolution
from mosaic_cli.mask import work_mask
from mosaic_cli.video.decode import gray_at


@dataclass(frozen=True)
class PairEstimate:
    """Homography frame t -> t+1 (3x3, full-resolution pixels), a confidence in [0, 1], and for
    the learned estimator the path that made it (learned, fallback, carried or failed)."""

    H: np.ndarray
    confidence: float
    path: str | None = None

    @staticmethod
    def failed() -> PairEstimate:
        return PairEstimate(np.eye(3), 0.0)


@dataclass
class StageTimer:
    """Wall-clock milliseconds per call of each timed stage (``ms["prepare"]``), in call order."""

    ms: dict[str, list[float]] = field(default_factory=dict)

    def record(self, stage: str, started: float) -> None:
        """Add the time since ``started`` (a ``time.perf_counter()``) to ``stage``."""
        self.ms.setdefault(stage, []).append((time.perf_counter() - started) * 1000.0)

    def total(self, stage: str) -> float:
        """All the milliseconds ``stage`` took so far."""
        return float(sum(self.ms.get(stage, ())))


def working_size(size: tuple[int, int], work_width: int) -> tuple[int, int]:
    """(w, h) of a frame of ``size`` resized to ``work_width`` (aspect kept, height rounded)."""
    w, h = size
    return (int(work_width), max(1, int(round(h * work_width / w))))


class Estimator(ABC):
    """Base class: subclasses implement ``_estimate(prev, cur)`` on working-resolution gray
    frames, or override ``feed``/``finish`` to batch."""

    name: str = "estimator"
    timings: StageTimer | None = None  # set by a benchmark: see the module doc
    # May ``feed`` hand a batch of estimates back a batch late, so that the next batch's work
    # overlaps this one's (the learned estimator's network beside its pool)?  Only a pass that
    # needs no estimate as soon as it can be made sets it (a video file's: estimate_stream's
    # ``lookahead``); a live one never does.
    lookahead: bool = False

    def frames_held(self, lookahead: bool = False) -> int:
        """The frames ``feed`` may hold before it tells their pairs (with ``lookahead`` set, or
        not): none for an estimator that tells each pair as its second frame comes."""
        return 0

    def __init__(self, work_width: int = 320):
        if work_width < 32:
            raise ValueError("work_width must be at least 32 pixels")
        self.work_width = int(work_width)
        self.requested_width = self.work_width
        # A classical estimator built for a user (make_estimator) works no wider than the video:
        # upscaling adds no detail, only time (1920 -> 4096 px was 10x slower).  Off by default:
        # a learned estimator works at its weights' size, and so must its ORB fallback, which
        # reads the network's frames.  ``width_given``: the user chose the width, so say so.
        self.never_upscale = False
        self.width_given = False
        self.full_size: tuple[int, int] | None = None
        self._prev: np.ndarray | None = None
        self.mask: np.ndarray | None = None  # full-resolution use mask (255 = ground), see set_mask
        self.work_mask: np.ndarray | None = None  # the same at the working size

    def set_mask(self, use: np.ndarray | None) -> None:
        """Estimate from the pixels ``use`` allows only (uint8 (h, w) at the full resolution of
        the frames to come, 255 = use; None: every pixel): burned-in overlays and the user's
        ``--mask`` (see :mod:`mosaic_cli.mask`, :mod:`mosaic_cli.overlay`).  Applies from the next ``reset``."""
        self.mask = None if use is None else np.asarray(use, dtype=np.uint8)

    @property
    def input_width(self) -> int:
        """The narrowest frames this estimator can use: readers may downscale to it for speed."""
        return self.work_width

    def reset(self, full_size: tuple[int, int]) -> None:
        """Start a new video whose full-resolution frames are ``full_size`` (w, h)."""
        self.full_size = (int(full_size[0]), int(full_size[1]))
        self.work_width = self.requested_width
        if self.never_upscale and self.work_width > self.full_size[0]:
            if self.width_given:
                from mosaic_cli.errors import warn

                warn(f"--work-width {self.work_width} is wider than the video ({self.full_size[0]} px): working at "
                     f"{self.full_size[0]} px (upscaling adds no detail, only time)")
            self.work_width = self.full_size[0]
        self.work_size = working_size(self.full_size, self.work_width)
        self._prev = None
        self.work_mask = None
        if self.mask is not None:
            if (self.mask.shape[1], self.mask.shape[0]) != self.full_size:
                raise ValueError(f"mask is {self.mask.shape[1]}x{self.mask.shape[0]}, the frames {self.full_size[0]}x{self.full_size[1]}")
            self.work_mask = work_mask(self.mask, self.work_size)

    def prepare(self, frame: np.ndarray) -> np.ndarray:
        """Gray frame at the working resolution (from a frame at any resolution)."""
        return gray_at(frame, self.work_size)

    def prepared(self, frame: np.ndarray) -> np.ndarray:
        """``prepare(frame)``, timed into :attr:`timings` when it is set: what ``feed`` calls."""
        if self.timings is None:
            return self.prepare(frame)
        started = time.perf_counter()
        out = self.prepare(frame)
        self.timings.record("prepare", started)
        return out

    def feed(self, frame: np.ndarray) -> list[PairEstimate]:
        if self.full_size is None:
            raise RuntimeError("call reset(full_size) before feeding frames")
        cur = self.prepared(frame)
        prev, self._prev = self._prev, cur
        if prev is None:
            return []
        H_work, confidence = self._estimate(prev, cur)
        return [self._to_full(H_work, confidence)]

    def finish(self) -> list[PairEstimate]:
        return []

    def close(self) -> None:
        """Let go of what the estimator holds beyond a video (a pool's threads): nothing here.
        The command that built an estimator closes it when its run ends, however it ends."""
        return None

    def __enter__(self) -> Estimator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _to_full(self, H_work: np.ndarray | None, confidence: float) -> PairEstimate:
        if H_work is None or not np.all(np.isfinite(H_work)):
            return PairEstimate.failed()
        assert self.work_size is not None and self.full_size is not None  # reset() set them
        H = to_resolution(H_work, self.work_size, self.full_size)
        if not np.all(np.isfinite(H)):
            return PairEstimate.failed()
        return PairEstimate(H, float(np.clip(confidence, 0.0, 1.0)))

    @abstractmethod
    def _estimate(self, prev: np.ndarray, cur: np.ndarray) -> tuple[np.ndarray | None, float]:
        """Homography prev -> cur at working resolution and its confidence (None on failure)."""


def estimate_stream(estimator: Estimator, frames: Iterable[np.ndarray], full_size: tuple[int, int],
                    lookahead: bool = False) -> Iterator[PairEstimate]:
    """Run ``estimator`` over ``frames`` and yield pairwise estimates in order, streaming.
    ``lookahead``: the estimates may come a batch late (:attr:`Estimator.lookahead`), the same ones."""
    estimator.reset(full_size)
    kept, estimator.lookahead = estimator.lookahead, lookahead
    try:
        for frame in frames:
            yield from estimator.feed(frame)
        yield from estimator.finish()
    finally:
        estimator.lookahead = kept


class IdentityEstimator(Estimator):
    """No motion at all: the paper's IDENTITY baseline."""

    name = "identity"

    def prepare(self, frame: np.ndarray) -> np.ndarray:
        return frame

    def _estimate(self, prev, cur):
        return np.eye(3), 0.0
