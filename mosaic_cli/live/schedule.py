"""The live stabiliser's schedule (``stabilize --latency``, :mod:`.stabilize`): what its stages
share, under one condition variable: the frames in flight, the path, each frame's deadline, and
the recent timings the lookahead adapts to (the module doc of :mod:`.stabilize` says how)."""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mosaic_cli.live.timeline import Timeline
from mosaic_cli.stabilize.crop import output_warps
from mosaic_cli.stabilize.online import MIN_LOOKAHEAD, OnlineL1Path, Window

LIVE_CHUNK = 4  # a learned estimator's frame pairs per batch: its answer comes 3 frames late at most
# Kept at the end of every frame's budget for x264 (zerolatency: it holds no frame back) and the
# muxer, beyond the warping and hand-over that are measured.
ENCODE_RESERVE = 0.05
# A live stream may come faster than its frame rate for a while and still be live: the decoder
# hands over what it held while it probed the stream (half a second), a network bursts.  Up to
# this many times its rate, a frame's budget counts from its arrival; faster, the stream is a file
# piped in, and its frames' budgets start at this pace (the decode stage then holds them back at
# the tracker's pace: :func:`mosaic_cli.live.stabilize._decode`).
BURST_PACE = 2.0
RECENT = 60  # the adaptive figures are the 90th percentile of this many recent samples
# A gated correction (tilt) that leaves more than this share of RECENT frames at their deadline,
# counted after the first KEEP_UP_AFTER frames, is planned as a similarity from then on.
LATE_SHARE = 0.1
KEEP_UP_AFTER = 90
STAGES = ("arrived", "taken", "estimated", "settled", "render", "handed")


class Recent:
    """The last ``RECENT`` values of a duration; its percentiles steer the schedule."""

    def __init__(self, size: int = RECENT):
        self._values: deque[float] = deque(maxlen=size)

    def add(self, value: float) -> None:
        self._values.append(value)

    @property
    def count(self) -> int:
        return len(self._values)

    def percentile(self, q: float = 90) -> float:
        return float(np.percentile(self._values, q)) if self._values else 0.0


@dataclass
class _Frame:
    pixels: np.ndarray
    arrived: float  # off the decoder
    start: float  # its deadline counts from here (:meth:`LiveSchedule.add_frame`)
    warp: np.ndarray | None = None
    late: bool = False  # settled at its deadline


class Abandoned(RuntimeError):
    """Another stage failed, or the run was abandoned: this stage stops."""


class LiveSchedule:
    """What the stages share, under one condition variable: the frames in flight (arrived and
    not yet rendered), the path, the deadlines and the recent timings the lookahead adapts to.

    ``realtime`` False (a file): no deadlines and the horizon's lookahead.  ``capacity``: frames
    in flight at most; the decoding stage waits beyond it (back pressure, never a dropped frame).
    ``clock`` is ``time.monotonic``, or a test's."""

    def __init__(self, path: OnlineL1Path, size: tuple[int, int], fps: float, latency: float, realtime: bool,
                 capacity: int, clock: Callable[[], float] = time.monotonic, timeline: Timeline | None = None,
                 render_guess: float = 0.0):
        self.path = path
        self.size = size
        self.fps = fps
        self.latency = latency
        self.realtime = realtime
        self.capacity = max(capacity, 2 * path.horizon.frames + LIVE_CHUNK)
        self.clock = clock
        self.timeline = timeline or Timeline(STAGES)
        self.cond = threading.Condition()
        self._frames: deque[_Frame] = deque()  # the frames in flight, in order: the first is frame ``rendered``
        self._untracked: deque[float] = deque()  # when the frames with no motion yet were taken
        self.rendered = 0  # frames taken by the renderer
        self._last_start: float | None = None  # the last frame's (add_frame)
        self.tracked_all = False
        self.planned_all = False
        self.failed: BaseException | None = None
        self.warps: list[np.ndarray] = []  # of the settled frames, in order
        self.late = 0
        self.solves = 0
        self.stale = 0
        self.lookahead_min = path.horizon.lookahead
        self.solve_seconds = Recent()
        self.lateness: list[bool] = []  # whether each frame rendered was settled at its deadline
        self.simplified_at: int | None = None  # the frame from which a gated model (tilt) was planned as a similarity
        self.track_lag = Recent()  # taken -> motion known
        self.render_seconds = Recent()  # taken by the renderer -> handed to the encoder
        self.render_guess = render_guess  # what a render takes until one has been timed

    # -- decode (the main thread) ---------------------------------------------------------
    def add_frame(self, pixels: np.ndarray, arrived: float) -> float:
        """A frame off the decoder at ``arrived``; returns when its budget starts: when it
        arrived, or where it came sooner than :data:`BURST_PACE` times the frame rate after the
        one before (a file piped in), at that pace.  (A file read in one pass: when taken.)"""
        with self.cond:
            while len(self._frames) >= self.capacity:
                self._wait()
            taken = self.clock()
            start = taken
            if self.realtime:
                start = arrived if self._last_start is None else max(arrived, self._last_start + 1.0 / (BURST_PACE * self.fps))
                self._last_start = start
            self._frames.append(_Frame(pixels, arrived, start))
            self._untracked.append(taken)
            self.cond.notify_all()
            return start

    # -- track ----------------------------------------------------------------------------
    def add_motion(self, pairwise: np.ndarray | None = None, confidence: float = 1.0) -> None:
        """The next frame's motion from the previous one (None for the first frame)."""
        with self.cond:
            self.path.push(pairwise, confidence)
            now = self.clock()
            self.track_lag.add(now - self._untracked.popleft())
            self.timeline.stamp("estimated", now)
            self.cond.notify_all()

    def end_motion(self) -> None:
        """Every frame's motion has been pushed: the stream is over."""
        with self.cond:
            self.tracked_all = True
            self.cond.notify_all()

    # -- plan -----------------------------------------------------------------------------
    def lookahead(self) -> int:
        """Frames a view waits for beyond its own, so that it normally settles before its
        deadline: a frame settles about (lookahead + step - 1) frames after it arrived, plus
        the tracker's lag and a solve."""
        horizon = self.path.horizon
        if not self.realtime:
            return horizon.lookahead
        # The typical times (medians): a stall now and then is the deadlines' business, and
        # shortening every view's lookahead for it would cost more steadiness than it saves.
        spare = self.latency - self.reserve() - self.track_lag.percentile(50) - self.solve_seconds.percentile(50)
        frames = math.floor(spare * self.fps) - (horizon.step - 1)
        return max(MIN_LOOKAHEAD, min(horizon.lookahead, frames))

    def next_window(self) -> tuple[Window, bool] | None:
        """The next window to solve, and whether it is the final one; None when all is settled."""
        with self.cond:
            while True:
                path = self.path
                final = self.tracked_all
                if final and path.settled >= path.frames:
                    self.planned_all = True
                    self.cond.notify_all()
                    return None
                if final or path.frames - path.settled >= path.horizon.step + self.lookahead():
                    window = path.pose(final)
                    assert window is not None  # frames > settled
                    return window, final
                self._wait()

    def solved(self, window: Window, params: np.ndarray, final: bool, seconds: float) -> None:
        with self.cond:
            self.solves += 1
            self.solve_seconds.add(seconds)
            if not self.path.adopt(window, params):
                self.stale += 1
                self.cond.notify_all()
                return
            lookahead = 0 if final else self.lookahead()
            if not final:
                self.lookahead_min = min(self.lookahead_min, lookahead)
            self._commit(window.frames - lookahead)

    def _commit(self, upto: int) -> None:
        first = self.path.settled
        if upto <= first:
            return
        warps = output_warps(self.path.commit(upto), self.size)
        for k, warp in enumerate(warps, start=first - self.rendered):
            self._frames[k].warp = warp
        self.warps += list(warps)
        self.timeline.stamp("settled", self.clock(), frames=len(warps))
        self.cond.notify_all()

    # -- render ---------------------------------------------------------------------------
    def reserve(self) -> float:
        """Seconds kept at the end of a frame's budget: warping and hand-over, then encoding."""
        return self.render_time() + ENCODE_RESERVE

    def render_time(self) -> float:
        """What warping a frame and handing it over takes: lately (90th percentile), or the
        guess until a frame has been rendered."""
        return self.render_seconds.percentile() if self.render_seconds.count else self.render_guess

    def deadline(self, frame: _Frame) -> float:
        return frame.start + self.latency - self.reserve()

    def _start_by(self) -> list[float]:
        """When the renderer must begin each frame in flight (0: the next to render) for it to
        leave on time: it renders them one at a time, so frame k starts k renders before its own
        deadline.  A burst of frames due together (a sender's first seconds, a stall upstream)
        is then begun early enough that its last frame is on time, not only its first."""
        render = self.render_time()
        return [self.deadline(frame) - k * render for k, frame in enumerate(self._frames)]

    def next_frame(self) -> _Frame | None:
        """The next frame to render, with its warp; None when every frame has been.  A live
        frame whose deadline has come is settled from the last plan (see the module doc)."""
        with self.cond:
            while True:
                if self._frames and self._frames[0].warp is not None:
                    self.rendered += 1
                    self._keep_up(self._frames[0].late)
                    self.cond.notify_all()
                    return self._frames.popleft()
                if not self._frames and self.planned_all:
                    return None
                if self._frames and self.realtime:
                    now, start_by = self.clock(), self._start_by()
                    if due := [k for k, start in enumerate(start_by) if start <= now]:
                        self._settle_late(due[-1] + 1)  # (and those before it, whose turn comes first)
                        continue
                    self._wait(min(start_by) - now)
                else:
                    self._wait()

    def _settle_late(self, count: int) -> None:
        """Settle the next ``count`` frames, whose turn has come (:meth:`_start_by`), from the plan
        (the next frame to render is the first unsettled one).  A solve under way is joined to
        them when it ends."""
        for k in range(count):
            self._frames[k].late = True
        self.late += count
        self._commit(self.path.settled + count)

    def _keep_up(self, late: bool) -> None:
        """Whether the correction keeps up: where more than :data:`LATE_SHARE` of the last
        :data:`RECENT` frames after the first :data:`KEEP_UP_AFTER` (the start: the network's
        load, the solver's first calls) left at their deadline, a gated model (`tilt`) is
        planned as a similarity from then on, its programs a third the size
        (:attr:`OnlineL1Path.similar_only`)."""
        self.lateness.append(late)
        # (the start's lateness, the network's load, is not the correction's)
        if (self.simplified_at is None and self.path.model.gated and len(self.lateness) >= KEEP_UP_AFTER + RECENT
                and sum(self.lateness[-RECENT:]) > LATE_SHARE * RECENT):
            self.path.similar_only = True
            self.simplified_at = self.rendered

    def rendered_one(self, seconds: float) -> None:
        with self.cond:
            self.render_seconds.add(seconds)

    # -- failures -------------------------------------------------------------------------
    def fail(self, exc: BaseException) -> None:
        with self.cond:
            if self.failed is None:
                self.failed = exc
            self.cond.notify_all()

    def _wait(self, timeout: float | None = None) -> None:
        if self.failed is not None:
            raise Abandoned()
        self.cond.wait(timeout)
        if self.failed is not None:
            raise Abandoned()
