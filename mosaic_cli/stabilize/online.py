"""A lookahead-bounded L1 camera path, for video that is still arriving.

The offline :class:`~mosaic_cli.stabilize.smoothing.L1Smoother` already solves its linear
program over overlapping windows whose first transforms are fixed to the previous window's
solution.  Online the same program runs over short windows that end at the newest frame: each
solve settles the next ``step`` frames, planned with ``lookahead`` more frames of the future in
view whose transforms stay free (the window's tail is not held to anything), and the next
window starts from the settled frames' last three transforms.  A frame therefore waits for at
most ``step + lookahead`` frames after its own arrival before its view is known; memory is the
window's motions, whatever the length of the stream.  A live run may also settle a frame
sooner, at its deadline, from the plan it has (:meth:`OnlineL1Path.commit`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.stabilize.crop import zoom_matrix
from mosaic_cli.stabilize.path import MODELS, MotionModel, fit_model, reduce_motion, to_normalized
from mosaic_cli.stabilize.smoothing import CARRIED, L1Smoother, solve_window

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
    def for_latency(cls, latency: float, fps: float, estimator_delay: int = 0) -> Horizon:
        """The longest horizon whose frames fit in ``latency`` seconds at ``fps``, after the
        estimator's own delay (a batching estimator answers a chunk at a time) and a share of
        the budget kept for the work."""
        budget = int(np.floor(latency * fps * (1.0 - WORK_SHARE))) - estimator_delay
        if budget < CARRIED + MIN_LOOKAHEAD:
            need = (CARRIED + MIN_LOOKAHEAD + estimator_delay) / fps / (1.0 - WORK_SHARE)
            raise BadInput(f"--latency {latency:g} s is too short at {fps:g} fps for this estimator: give at least {need:.2f} s")
        # A quarter of the horizon: shorter steps re-plan more often with the future in view
        # (half the horizon left twice the jitter of a quarter: docs/measurements/live.md).
        step = max(CARRIED, budget // 4)
        return cls(step=step, lookahead=budget - step)


@dataclass(frozen=True)
class Window:
    """One linear program of an :class:`OnlineL1Path`, posed by :meth:`~OnlineL1Path.pose` and
    solved by :meth:`~OnlineL1Path.solve`, which touches nothing else: another thread may solve
    it while frames keep arriving."""

    first: int  # the frame its first transform belongs to
    settled: int  # frames settled when it was posed (more may be by the time it is solved)
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
    deadline): see :meth:`commit` for the view it gets.  A window posed before such a commit
    starts from transforms that are no longer the settled ones: :meth:`adopt` joins it to
    them."""

    model: MotionModel
    size: tuple[int, int]
    crop: float | None
    horizon: Horizon
    # The dual simplex solves these short windows in about half the interior point's time, with
    # the same jitter (docs/measurements/live.md).
    options: L1Smoother = field(default_factory=lambda: L1Smoother(method="highs-ds"))
    # Frames beyond the newest planned as if the camera kept its recent mean motion: without
    # them the window's free tail stops following the camera, and the next window bends the
    # path back (see docs/measurements/live.md).  Only the real frames' views are used, except by a commit
    # ahead of the motion (a deadline).
    predicted: int | None = None  # None: as many as the lookahead
    recent: int = 15  # frames whose mean motion is carried on
    # A frame settled past the plan's known motion (a deadline) follows the planned path, and
    # its transform returns by this fraction a frame towards the last planned one (see commit).
    recover: float = 0.15
    rejoin: int = 10  # frames over which a late plan is joined to the frames settled meanwhile

    def __post_init__(self) -> None:
        if self.horizon.step < CARRIED:
            raise ValueError(f"step must be at least {CARRIED}")
        self.frames = 0  # frames pushed
        self.settled = 0  # frames whose view has been committed
        self.held = 0  # frames committed past the plan's end, or before any plan
        self.rejoined = 0  # plans joined to frames settled while they were solved
        self._start = 0  # first frame of the next window
        self._motion: list[np.ndarray] = []  # F_t (t -> t-1) for t > _start
        self._tail: list[np.ndarray] = []  # parameters of the last CARRIED settled frames
        self._plan_first = 0
        self._plan: np.ndarray | None = None  # parameters of frames _plan_first onwards
        self.plan_frames = 0  # frames the plan knew the motion of (it predicted the rest)
        self._plan_motion = np.zeros((0, 3, 3))  # the motion it was solved with, predicted included
        self._last_good: np.ndarray | None = None
        self._zoom = zoom_matrix(1.0 if self.crop is None else self.crop)
        self.similar_only = False  # a gated model planned as a similarity from now on (see solve)

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
            motion = reduce_motion(backward, self.model)
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
        """(n, K) parameters of the window's frames (safe to call from another thread).  Once
        :attr:`similar_only` (a live run whose `tilt` could not keep up), a gated model's window
        is solved as a similarity's, a third of the time, and the perspective terms the settled
        frames carried fade out over ``rejoin`` frames instead of stopping at once."""
        if not (self.similar_only and self.model.gated):
            return solve_window(window.motion, self.model, window.fixed, self.size, self.crop, self.options)
        similar = MODELS["similarity"]
        n_similar = similar.n_params
        fixed = None if window.fixed is None else window.fixed[:, :n_similar]
        params = solve_window(fit_model(window.motion, similar), similar, fixed, self.size, self.crop, self.options)
        params = np.pad(params, ((0, 0), (0, self.model.n_params - n_similar)))
        if window.fixed is not None:
            carried = len(window.fixed)
            params[:carried, n_similar:] = window.fixed[:, n_similar:]
            k = np.arange(1, len(params) - carried + 1)
            fade = np.where(k < self.rejoin, 0.5 * (1 + np.cos(np.pi * k / self.rejoin)), 0.0)
            params[carried:, n_similar:] = fade[:, None] * window.fixed[-1, n_similar:]
        return params

    def adopt(self, window: Window, params: np.ndarray) -> bool:
        """Make a solved window the plan.  When frames were settled while it was solved (a
        deadline), it is joined to them: its transforms are moved to meet the last settled
        one, by an offset that fades out over ``rejoin`` frames (a smooth step, so that the
        path's speed does not jump either).  False, and nothing changes, when the window ends
        before the frames settled since."""
        end = window.first + len(params)
        if window.settled != self.settled:
            last = self.settled - 1
            if last >= end or not self._tail:
                return False
            params = params.copy()
            offset = self._tail[-1] - params[last - window.first]
            k = np.arange(end - last)
            fade = np.where(k < self.rejoin, 0.5 * (1 + np.cos(np.pi * np.minimum(k, self.rejoin) / self.rejoin)), 0.0)
            params[last - window.first:] += fade[:, None] * offset
            self.rejoined += 1
        self._plan_first, self._plan = window.first, params
        self.plan_frames, self._plan_motion = window.frames, window.motion
        return True

    @property
    def planned(self) -> int:
        """Frames (from 0) the plan covers, its predicted frames included."""
        return 0 if self._plan is None else self._plan_first + len(self._plan)

    def commit(self, upto: int) -> np.ndarray:
        """Settle frames up to ``upto`` (exclusive) from the plan: their (n, 3, 3) views.

        A frame the plan knew the motion of gets the plan's transform.  Past that (a deadline
        came first), it follows the plan's *path*, what the output shows, with the camera's
        real motion where it is known by now (see :meth:`_follow_path`).  Past the plan's end,
        or before any plan, a frame keeps the last settled transform (or none): the output
        then moves with the camera."""
        params: list[np.ndarray] = []
        for t in range(self.settled, upto):
            if self._plan is None or not self._plan_first <= t < self.planned:
                p = self._tail[-1] if self._tail else self.model.identity
                self.held += 1
            elif t < self.plan_frames:
                p = self._plan[t - self._plan_first]
            else:
                p = self._follow_path(t, params[-1] if params else self._tail[-1])
            params.append(p)
        if not params:
            return np.zeros((0, 3, 3))
        self.settled = upto
        self._tail = (self._tail + params)[-CARRIED:]
        start = max(0, upto - CARRIED)
        del self._motion[:start - self._start]
        self._start = start
        return self.model.matrices(np.array(params)) @ self._zoom

    def _follow_path(self, t: int, previous: np.ndarray) -> np.ndarray:
        """Parameters for frame ``t`` past the plan's known motion, ``previous`` those of
        frame t - 1.

        The output takes the plan's step from frame t - 1 to t (the path is camera @
        transform), with the camera's real motion F_t when it is known by now rather than the
        plan's prediction.  The transform then returns towards the one of the plan's last
        known frame by ``recover`` a frame, so that the output follows the camera's slow motion
        where the prediction drifts from it (0.15 left the least jitter in simulated stalls of
        the solver: docs/measurements/live.md)."""
        assert self._plan is not None
        first, matrices = self._plan_first, self.model.matrices
        predicted = self._plan_motion[t - 1 - first]
        step = np.linalg.inv(matrices(self._plan[t - 1 - first])) @ predicted @ matrices(self._plan[t - first])
        real = self._motion[t - 1 - self._start] if self._start < t < self.frames else predicted
        followed = self._parameters(np.linalg.inv(real) @ matrices(previous) @ step)
        anchor = self._plan[self.plan_frames - 1 - first]
        return followed + self.recover * (anchor - followed)

    def _parameters(self, M: np.ndarray) -> np.ndarray:
        """The model's parameters of matrix ``M`` (least squares over its entries)."""
        basis = self.model.basis.reshape(self.model.n_params, 9).T
        return np.linalg.lstsq(basis, (M / M[2, 2] - self.model.offset).ravel(), rcond=None)[0]

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
