"""Where a live frame's time goes: one time stamp per frame and stage, and the CPU time of each
stage's work, so that a latency figure can be taken apart (``python -m benchmarks live`` prints it).

Each stage sees the frames in order, so a stage's stamps are a plain growing array (8 bytes a
frame): frame ``k``'s stamp is the ``k``-th.
"""

from __future__ import annotations

import gc
import time
from array import array

import numpy as np


class Timeline:
    """Per-frame stamps (``time.monotonic()``) of named stages, and CPU seconds per named job."""

    def __init__(self, stages: tuple[str, ...]):
        self.stages = stages
        self._stamps = {stage: array("d") for stage in stages}
        self.cpu: dict[str, float] = {}
        self.counts: dict[str, int] = {}
        self.gc_pauses: list[float] = []
        self._gc_start = 0.0

    def stamp(self, stage: str, when: float | None = None, frames: int = 1) -> None:
        value = time.monotonic() if when is None else when
        stamps = self._stamps[stage]
        for _ in range(frames):
            stamps.append(value)

    def add_cpu(self, job: str, seconds: float, count: int = 1) -> None:
        self.cpu[job] = self.cpu.get(job, 0.0) + seconds
        self.counts[job] = self.counts.get(job, 0) + count

    def times(self, stage: str) -> np.ndarray:
        return np.frombuffer(self._stamps[stage], dtype=np.float64).copy() if len(self._stamps[stage]) else np.zeros(0)

    # Python's collector stops every thread while it runs: its pauses are part of the picture.
    def watch_gc(self) -> None:
        gc.callbacks.append(self._on_gc)

    def unwatch_gc(self) -> None:
        if self._on_gc in gc.callbacks:
            gc.callbacks.remove(self._on_gc)

    def _on_gc(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._gc_start = time.perf_counter()
        else:
            self.gc_pauses.append(time.perf_counter() - self._gc_start)
