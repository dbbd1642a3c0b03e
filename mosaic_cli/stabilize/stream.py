"""The camera path planned while the video is still being tracked, so that the render runs beside
the tracking instead of after it.

The tracking pass hands each pair's estimate to a :class:`PathFeed`; the feed turns it into the
camera's motion and plans the path window by window (:class:`~.smoothing.L1Planner`), and the
render asks it for each frame's warp, waiting until the frame's window is solved.  The views are
those a plan of the whole clip gives: a window sees only its own motions and the transforms the
previous one settled.  A smoother with no windows (``gaussian``) settles every view at the end.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np

from mosaic_cli.stabilize.crop import output_warps
from mosaic_cli.stabilize.path import MotionModel, camera_motion
from mosaic_cli.stabilize.smoothing import GaussianSmoother, L1Smoother

WAIT_SLICE = 0.1  # seconds: a waiting render still sees Ctrl-C this often


class Cancelled(Exception):
    """The render stopped (an error, Ctrl-C): the tracking pass ends at its next pair."""


@dataclass
class FailedPairFill:
    """:func:`~.path.fill_failed` for pairs arriving one at a time: a failed pair (confidence 0)
    takes the motion of the nearest successful one, the earlier on a tie, so it waits until the
    next success (or the end) shows which that is."""

    _waiting: list[tuple[int, np.ndarray]] = field(default_factory=list)  # failed pairs: (index, as estimated)
    _last_good: tuple[int, np.ndarray] | None = None
    _count: int = 0

    def push(self, H: np.ndarray, confidence: float) -> list[np.ndarray]:
        """The pairs this one settles, in order (itself included when it succeeded)."""
        t, self._count = self._count, self._count + 1
        if not confidence > 0:
            self._waiting.append((t, H))
            return []
        out = [self._nearest(k, (t, H)) for k, _ in self._waiting] + [H]
        self._waiting, self._last_good = [], (t, H)
        return out

    def finish(self) -> list[np.ndarray]:
        """The failed pairs still waiting: the last success's motion (as estimated when none succeeded)."""
        out = [self._last_good[1] if self._last_good is not None else H for _, H in self._waiting]
        self._waiting = []
        return out

    def _nearest(self, t: int, following: tuple[int, np.ndarray]) -> np.ndarray:
        if self._last_good is not None and t - self._last_good[0] <= following[0] - t:
            return self._last_good[1]
        return following[1]


class PathFeed:
    """Pairs in (the tracking pass's thread), output warps out (the render's), as they settle.

    :meth:`warp` waits for its frame; past the last frame it gives the last warp (a second decode
    that finds a frame more than the first).  An error of the tracking pass reaches the render
    through :meth:`fail`, and the render's end (or failure) stops the tracking through :meth:`cancel`."""

    def __init__(self, size: tuple[int, int], model: MotionModel, smoother: L1Smoother | GaussianSmoother,
                 crop: float | None):
        self.size, self.model, self.smoother, self.crop = size, model, smoother, crop
        self._fill = FailedPairFill()
        self._planner = smoother.planner(size, model, crop) if isinstance(smoother, L1Smoother) else None
        self._motion: list[np.ndarray] = []  # F_{t+1} (normalised, in the model), for --plot and gaussian
        self._views: list[np.ndarray] = []
        self._warps: list[np.ndarray] = []
        self._changed = threading.Condition()
        self._done = False
        self._error: BaseException | None = None
        self._cancelled = False
        self._waiting: int | None = None  # the frame whose warp the render waits for
        self._smooth_seconds = 0.0  # a smoother with no windows: its one solve at the end

    # -- the tracking side -------------------------------------------------------------------

    def add_pair(self, H: np.ndarray, confidence: float) -> None:
        """The next pair's estimate, frame t -> t+1 (full-resolution pixels)."""
        if self._cancelled:
            raise Cancelled
        self._plan(self._fill.push(np.asarray(H, dtype=np.float64), confidence))

    def finish(self) -> None:
        """The last pair is in: settle every remaining view."""
        self._plan(self._fill.finish())
        if self._planner is not None:
            views = self._planner.finish()
        else:
            clock = time.perf_counter()
            motion = np.array(self._motion).reshape(-1, 3, 3)
            views = self.smoother.smooth(motion, self.size, self.model, self.crop)
            self._smooth_seconds = time.perf_counter() - clock
        self._publish(views, done=True)

    def fail(self, error: BaseException) -> None:
        with self._changed:
            self._error, self._done = error, True
            self._changed.notify_all()

    def _plan(self, pairs: list[np.ndarray]) -> None:
        if not pairs:
            return
        # One pair at a time: the motions do not depend on how the pairs arrived.
        motion = np.concatenate([camera_motion(H[None], self.size, self.model) for H in pairs])
        self._motion.extend(motion)
        if self._planner is not None:
            self._publish(self._planner.push(motion))

    def _publish(self, views: np.ndarray, done: bool = False) -> None:
        warps = output_warps(views, self.size) if len(views) else views
        with self._changed:
            self._views.extend(views)
            self._warps.extend(warps)
            self._done = done
            self._changed.notify_all()

    # -- the render side ---------------------------------------------------------------------

    def warp(self, t: int) -> np.ndarray:
        """Frame ``t``'s warp, input pixels -> output pixels, once it is settled."""
        with self._changed:
            self._waiting = t
            try:
                while len(self._warps) <= t and not self._done:
                    self._changed.wait(WAIT_SLICE)
            finally:
                self._waiting = None
            if self._error is not None:
                raise self._error
            return self._warps[min(t, len(self._warps) - 1)]

    def starved(self) -> bool:
        """Whether the render waits for a warp the pairs told so far do not settle: then only
        more frames tracked can settle it (stabilize's shared decode looks for a ring too small
        with this: stabilize/shared_decode.py)."""
        with self._changed:
            return self._waiting is not None and len(self._warps) <= self._waiting and not self._done

    def cancel(self) -> None:
        self._cancelled = True

    # -- when both are done ------------------------------------------------------------------

    @property
    def plan_seconds(self) -> float:
        return self._planner.solve_seconds if self._planner is not None else self._smooth_seconds

    @property
    def warps(self) -> np.ndarray:
        return np.array(self._warps).reshape(-1, 3, 3)

    @property
    def views(self) -> np.ndarray:
        return np.array(self._views).reshape(-1, 3, 3)

    @property
    def motion(self) -> np.ndarray:
        return np.array(self._motion).reshape(-1, 3, 3)


__all__ = ["Cancelled", "FailedPairFill", "PathFeed"]
