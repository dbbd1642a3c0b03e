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


@dataclass(frozen=True)
class Window:
    """One linear program of an :class:`OnlineL1Path`, posed by :meth:`~OnlineL1Path.pose` and
    solved by :meth:`~OnlineL1Path.solve`, which touches nothing else: another thread may solve
    it while frames keep arriving."""

    first: int  # the frame its first transform belongs to
    settled: int  # frames settled when it was posed: once more are, it is stale
    frames: int  # frames first .. frames - 1 are real; the motion beyond them is predicted
    motion: np.ndarray  # (n - 1, 3, 3) over its n frames, predicted ones included
    fixed: np.ndarray | None  # parameters of the settled frames it starts from


@dataclass
class OnlineL1Path:
    """Feed the camera motion frame by frame (:meth:`push`); :meth:`settle` returns the views
    (normalised output -> input, as the offline smoothers' ``V``) of the frames now settled.

    :meth:`settle` is three steps that a live run spreads over threads: :meth:`pose` a window
    over the frames so far, :meth:`solve` it (the costly part, with no state touched) and
    :meth:`adopt` the solution as the plan; :meth:`commit` then settles frames from the plan.
    A frame may be committed before any window has seen ``lookahead`` frames beyond it (a
    deadline): it gets the plan's view, predicted part included, or past the plan's end the
    last settled transform held.  A window posed before such a commit is stale and not adopted,
    since its fixed start no longer matches what was settled."""

    model: MotionModel
    size: tuple[int, int]
    crop: float | None
    horizon: Horizon
    # The dual simplex solves these short windows in about half the interior point's time, with
    # the same jitter (docs/live.md).
    options: L1Smoother = field(default_factory=lambda: L1Smoother(method="highs-ds"))
    # Frames beyond the newest planned as if the camera kept its recent mean motion: without
    # them the window's free tail stops following the camera, and the next window bends the
    # path back (see docs/live.md).  Only the real frames' views are used, except by a commit
    # ahead of the motion (a deadline).
    predicted: int | None = None  # None: as many as the lookahead
    recent: int = 15  # frames whose mean motion is carried on

    def __post_init__(self) -> None:
        if self.horizon.step < CARRIED:
            raise ValueError(f"step must be at least {CARRIED}")
        self.frames = 0  # frames pushed
        self.settled = 0  # frames whose view has been committed
        self.held = 0  # frames committed beyond the plan (or before any): the last transform held
        self._start = 0  # first frame of the next window
        self._motion: list[np.ndarray] = []  # F_t (t -> t-1) for t > _start
        self._tail: list[np.ndarray] = []  # parameters of the last CARRIED settled frames
        self._plan_first = 0
        self._plan: np.ndarray | None = None  # parameters of frames _plan_first onwards
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
        if self.frames > self._start:  # not settled past it already (a deadline)
            self._motion.append(motion)
        self.frames += 1

    @property
    def extra(self) -> int:
        return self.horizon.lookahead if self.predicted is None else self.predicted

    def pose(self, final: bool = False) -> Window | None:
        """The window over every frame pushed and not settled (None when there is none), with
        the predicted frames beyond them unless ``final``."""
        if self.frames <= self.settled:
            return None
        motion = np.array(self._motion[:self.frames - 1 - self._start]).reshape(-1, 3, 3)
        extra = 0 if final else self.extra
        if extra:
            mean = motion[-self.recent:].mean(axis=0) if len(motion) else np.eye(3)
            motion = np.concatenate([motion, np.repeat(mean[None], extra, axis=0)])
        fixed = np.array(self._tail) if self._tail else None
        return Window(self._start, self.settled, self.frames, motion, fixed)

    def solve(self, window: Window) -> np.ndarray:
        """(n, K) parameters of the window's frames (safe to call from another thread)."""
        return _solve_window(window.motion, self.model, window.fixed, self.size, self.crop, self.options)

    def adopt(self, window: Window, params: np.ndarray) -> bool:
        """Make a solved window the plan; False (and nothing changes) when it is stale."""
        if window.settled != self.settled:
            return False
        self._plan_first, self._plan = window.first, params
        return True

    @property
    def planned(self) -> int:
        """Frames (from 0) the plan covers, its predicted frames included."""
        return 0 if self._plan is None else self._plan_first + len(self._plan)

    def commit(self, upto: int) -> np.ndarray:
        """Settle frames up to ``upto`` (exclusive) from the plan: their (n, 3, 3) views."""
        params = []
        for t in range(self.settled, upto):
            if self._plan is not None and self._plan_first <= t < self.planned:
                p = self._plan[t - self._plan_first]
            else:  # beyond the plan, or before the first: hold the last settled transform
                p = self._tail[-1] if self._tail else self.model.identity
                self.held += 1
            params.append(p)
        if not params:
            return np.zeros((0, 3, 3))
        self.settled = upto
        self._tail = (self._tail + params)[-CARRIED:]
        start = max(0, upto - CARRIED)
        del self._motion[:start - self._start]
        self._start = start
        return self.model.matrices(np.array(params)) @ self._zoom

    def settle(self, final: bool = False) -> np.ndarray:
        """(n, 3, 3) views of the frames settled by this call: ``step`` frames for each window
        that sees ``lookahead`` frames beyond them (none until a window is full; with ``final``
        every frame pushed)."""
        views: list[np.ndarray] = []
        while self.settled < self.frames and (final or self.frames - self.settled >= self.horizon.frames):
            window = self.pose(final)
            assert window is not None
            self.adopt(window, self.solve(window))
            views.append(self.commit(self.frames if final else self.settled + self.horizon.step))
        return np.concatenate(views) if views else np.zeros((0, 3, 3))
