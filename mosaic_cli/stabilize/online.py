"""A lookahead-bounded L1 camera path, for video that is still arriving.

The offline :class:`~mosaic_cli.stabilize.smoothing.L1Smoother` already solves its linear
program over overlapping windows whose first transforms are fixed to the previous window's
solution.  Online the same program runs over short windows that end at the newest frame: each
solve settles the next ``step`` frames, planned with ``lookahead`` more frames of the future in
view whose transforms stay free (the window's tail is not held to anything), and the next
window starts from the settled frames' last three transforms.  A frame therefore waits for at
most ``step + lookahead`` frames after its own arrival before its view is known; memory is the
window's motions, whatever the length of the stream.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.stabilize.crop import zoom_matrix
from mosaic_cli.stabilize.path import MotionModel, fit_model, to_normalized
from mosaic_cli.stabilize.smoothing import CARRIED, L1Smoother, _solve_window

# Part of the latency budget left for the work itself (tracking, warping, encoding, queues).
WORK_SHARE = 0.15
MIN_LOOKAHEAD = 4


@dataclass(frozen=True)
class Horizon:
    """Frames a view waits for: ``step`` settled per solve, ``lookahead`` beyond them."""

    step: int
    lookahead: int

    @property
    def frames(self) -> int:
        return self.step + self.lookahead

    @classmethod
    def for_latency(cls, latency: float, fps: float, estimator_delay: int = 0) -> "Horizon":
        """The longest horizon whose frames fit in ``latency`` seconds at ``fps``, after the
        estimator's own delay (a batching estimator answers a chunk at a time) and a share of
        the budget kept for the work."""
        budget = int(np.floor(latency * fps * (1.0 - WORK_SHARE))) - estimator_delay
        if budget < CARRIED + MIN_LOOKAHEAD:
            need = (CARRIED + MIN_LOOKAHEAD + estimator_delay) / fps / (1.0 - WORK_SHARE)
            raise BadInput(f"--latency {latency:g} s is too short at {fps:g} fps for this estimator: give at least {need:.2f} s")
        # A quarter of the horizon: shorter steps re-plan more often with the future in view
        # (half the horizon left twice the jitter of a quarter: docs/live.md).
        step = max(CARRIED, budget // 4)
        return cls(step=step, lookahead=budget - step)


@dataclass
class OnlineL1Path:
    """Feed the camera motion frame by frame (:meth:`push`); :meth:`settle` returns the views
    (normalised output -> input, as the offline smoothers' ``V``) of the frames now settled."""

    model: MotionModel
    size: tuple[int, int]
    crop: float | None
    horizon: Horizon
    options: L1Smoother = field(default_factory=L1Smoother)
    # Frames beyond the newest planned as if the camera kept its recent mean motion: without
    # them the window's free tail stops following the camera, and the next window bends the
    # path back (see docs/live.md).  Only the real frames' views are used.
    predicted: int | None = None  # None: as many as the lookahead
    recent: int = 15  # frames whose mean motion is carried on

    def __post_init__(self) -> None:
        if self.horizon.step < CARRIED:
            raise ValueError(f"step must be at least {CARRIED}")
        self.frames = 0  # frames pushed
        self.settled = 0  # frames whose view has been returned
        self._start = 0  # first frame of the next window
        self._motion: list[np.ndarray] = []  # F_{t+1} (t+1 -> t) for t >= _start
        self._fixed: np.ndarray | None = None  # settled parameters of frames _start .. _start + CARRIED
        self._last_good: np.ndarray | None = None
        self._zoom = zoom_matrix(1.0 if self.crop is None else self.crop)

    def push(self, pairwise: np.ndarray | None = None, confidence: float = 1.0) -> None:
        """The next frame: ``pairwise`` is the previous frame -> this one (pixels), None for the
        first frame.  A failed estimate (confidence 0) reuses the last good motion, as the
        offline path's nearest-neighbour fill does for a failure after the first success."""
        if self.frames == 0:
            self.frames = 1
            return
        if pairwise is None:
            raise ValueError("every frame after the first needs its pairwise motion")
        if confidence > 0 or self._last_good is None:
            backward = np.linalg.inv(to_normalized(np.asarray(pairwise, dtype=np.float64), self.size))
            motion = fit_model(backward, self.model)
            if confidence > 0:
                self._last_good = motion
        else:
            motion = self._last_good
        self._motion.append(motion)
        self.frames += 1

    def settle(self, final: bool = False) -> np.ndarray:
        """(n, 3, 3) views of the frames settled by this call (none until a window is full;
        with ``final`` every frame pushed)."""
        views: list[np.ndarray] = []
        while self.settled < self.frames and (final or self.frames - self.settled >= self.horizon.frames):
            end = self.frames if final else self.settled + self.horizon.frames
            motion = np.array(self._motion[:end - 1 - self._start]).reshape(-1, 3, 3)
            extra = 0 if final else (self.horizon.lookahead if self.predicted is None else self.predicted)
            if extra and len(motion):
                mean = motion[-self.recent:].mean(axis=0)
                motion = np.concatenate([motion, np.repeat(mean[None], extra, axis=0)])
            solution = _solve_window(motion, self.model, self._fixed, self.size, self.crop, self.options)
            keep = end if final else self.settled + self.horizon.step
            views.append(self.model.matrices(solution[self.settled - self._start:keep - self._start]) @ self._zoom)
            self.settled = keep
            if keep < self.frames:
                start = keep - CARRIED
                self._fixed = solution[start - self._start:keep - self._start]
                del self._motion[:start - self._start]
                self._start = start
        return np.concatenate(views) if views else np.zeros((0, 3, 3))
