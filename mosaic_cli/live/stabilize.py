"""``stabilize --latency``: one pass, each frame out at most ``latency`` seconds after it came in.

Stages, each in a thread of its own, with the shared state in a :class:`LiveSchedule`:

1. decode   one ffmpeg, yuv420p at full size (:class:`~mosaic_cli.live.source.LiveStream`); the
            main thread takes each frame as it comes and makes the estimator's gray image;
2. track    the estimator on the gray images: the camera motion, pushed into the path;
3. plan     the lookahead-bounded L1 path (:mod:`mosaic_cli.stabilize.online`), solved in the
            background: each solve settles the frames it sees ``lookahead`` frames beyond;
4. render   warp each settled frame and hand it to the encoder: a file (atomic, at the end),
            standard output or a URL (MPEG-TS, :mod:`.output`).

**Deadlines** (live sources).  A frame is due at the encoder ``latency`` seconds after it was
taken off the decoder's queue (when it arrived, unless mosaic is behind the stream), less a
reserve for warping and encoding (what they took lately).  A frame that is not settled by then,
because a solve ran late or the tracker stalled, leaves with the best path known: the last
plan's view of it, predicted frames included, or past that plan's end the last settled
transform held.  Warping and encoding therefore never wait for the solver, and no frame is
dropped.  The lookahead adapts: it shrinks (down to ``MIN_LOOKAHEAD``) while tracking and
solving take longer, so that frames normally settle before their deadline, and grows back to
the horizon's when they are quick again.  Frames are taken at the tracker's pace (a short
queue): a stream faster than real time, such as a file piped in, is held back as before rather
than sent on unsteadied.  A file read in one pass has no deadlines.

Latency is measured per frame from its arrival off the decoder to its hand-over to the encoder;
:attr:`LiveStabilizeResult.timeline` has every stage's time stamps (``python -m benchmarks live``).
"""

from __future__ import annotations

import concurrent.futures
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput, warn
from mosaic_cli.estimators import Estimator, make_estimator
from mosaic_cli.live.loading import begin, built_beside, trained_width, waited_for
from mosaic_cli.live.output import StreamWriter, is_stream_output
from mosaic_cli.live.progress import stream_progress
from mosaic_cli.live.source import (
    QUEUE_BYTES,
    LiveStream,
    gray_of_yuv,
    is_live_source,
    note,
    source_name,
)
from mosaic_cli.live.timeline import Timeline
from mosaic_cli.overlay import check_mask_file, frame_mask, live_mask
from mosaic_cli.stabilize.crop import output_warps, parse_crop
from mosaic_cli.stabilize.online import MIN_LOOKAHEAD, Horizon, OnlineL1Path, Window
from mosaic_cli.stabilize.path import motion_model
from mosaic_cli.stabilize.pipeline import PRESET, WORK_WIDTH, StabilizeOptions, write_warps
from mosaic_cli.stabilize.render import parse_border, warp_yuv
from mosaic_cli.video import VideoInfo, VideoWriter, probe
from mosaic_cli.video.reader import scaled_size
from mosaic_cli.video.writer import OUTPUT_SUFFIXES

DEFAULT_LATENCY = 1.0
LIVE_CHUNK = 4  # a learned estimator's frame pairs per batch: its answer comes 3 frames late at most
# Kept at the end of every frame's budget for x264 (zerolatency: it holds no frame back) and the
# muxer, beyond the warping and hand-over that are measured.
ENCODE_RESERVE = 0.05
TRACK_QUEUE = 2 * LIVE_CHUNK  # gray images waiting for the tracker: two of a learned estimator's batches
RECENT = 60  # the adaptive figures are the 90th percentile of this many recent samples
# A gated correction (tilt) that leaves more than this share of RECENT frames at their deadline,
# counted after the first KEEP_UP_AFTER frames, is planned as a similarity from then on.
LATE_SHARE = 0.1
KEEP_UP_AFTER = 90
STAGES = ("arrived", "taken", "estimated", "settled", "render", "handed")


@dataclass
class LiveStabilizeResult:
    frames_in: int
    frames_out: int
    size: tuple[int, int]
    fps: float
    horizon: Horizon
    latencies: np.ndarray  # seconds, per frame: arrival -> handed to the encoder
    ended_by: str | None
    warps: np.ndarray
    seconds: float
    notes: list[str] = field(default_factory=list)
    late: int = 0  # frames settled at their deadline, before a window saw their lookahead
    held: int = 0  # of which beyond the last plan: the last settled transform held
    solves: int = 0
    stale: int = 0  # solves not used: frames settled at their deadline went past their end
    lookahead_min: int = 0  # the shortest lookahead the adaptation chose
    timeline: Timeline | None = None
    rejoined: int = 0  # plans joined to frames settled at their deadline while they were solved
    simplified_at: int | None = None  # the frame from which `tilt` was planned as a similarity (it could not keep up)
    lateness: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # per frame rendered: settled at its deadline
    pairs_by: dict[str, int] = field(default_factory=dict)  # frame pairs each estimator made ("orb" while the network loaded)

    def latency(self, q: float) -> float:
        return float(np.percentile(self.latencies, q)) if len(self.latencies) else 0.0


def is_live_request(source: str, out: str, options: StabilizeOptions) -> bool:
    """Stabilised in one pass: asked for (``--latency``), or the input or the output is live."""
    return options.latency is not None or is_live_source(source) or is_stream_output(out)


class Recent:
    """The last ``RECENT`` values of a duration; its percentiles steer the schedule."""

    def __init__(self, size: int = RECENT):
        self._values: deque[float] = deque(maxlen=size)

    def add(self, value: float) -> None:
        self._values.append(value)

    def percentile(self, q: float = 90) -> float:
        return float(np.percentile(self._values, q)) if self._values else 0.0


@dataclass
class _Frame:
    pixels: np.ndarray
    arrived: float  # off the decoder
    taken: float  # by the stabiliser: its deadline counts from here
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
                 capacity: int, clock: Callable[[], float] = time.monotonic, timeline: Timeline | None = None):
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

    # -- decode (the main thread) ---------------------------------------------------------
    def add_frame(self, pixels: np.ndarray, arrived: float) -> None:
        with self.cond:
            while len(self._frames) >= self.capacity:
                self._wait()
            taken = self.clock()
            self._frames.append(_Frame(pixels, arrived, taken))
            self._untracked.append(taken)
            self.cond.notify_all()

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
        return self.render_seconds.percentile() + ENCODE_RESERVE

    def deadline(self, frame: _Frame) -> float:
        return frame.taken + self.latency - self.reserve()

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
                    now = self.clock()
                    due = self.deadline(self._frames[0])
                    if now >= due:
                        self._settle_late(now)
                        continue
                    self._wait(due - now)
                else:
                    self._wait()

    def _settle_late(self, now: float) -> None:
        """Settle the frames whose deadline has come from the plan (the next frame to render
        is the first unsettled one).  A solve under way is joined to them when it ends."""
        count = 1
        while count < len(self._frames) and self.deadline(self._frames[count]) <= now:
            count += 1
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


def check_live_request(source: str, out: str, options: StabilizeOptions, warps_out: str | None,
                       compare: str | None) -> VideoInfo | None:
    """The checks of a one-pass run that the options cannot make alone; returns a file's probe
    (None for a live input)."""
    if compare is not None:
        raise BadInput("--compare is not available with --latency or a live input")
    if options.smoothing.lower() != "l1":
        raise BadInput("--latency plans an L1 path: --smoothing gaussian needs the whole video")
    if not is_stream_output(out) and Path(out).suffix.lower() not in OUTPUT_SUFFIXES:
        raise BadInput(f"output {out} must end in one of {', '.join(OUTPUT_SUFFIXES)}, or be - or a URL")
    if warps_out is not None and Path(warps_out).suffix.lower() != ".json":
        raise BadInput(f"--warps {warps_out} must end in .json")
    if not is_live_source(source):
        info = probe(source)  # the file checks of every command: missing, empty, damaged
        check_mask_file(options.mask, info)
        return info
    return None


def stabilize_live(source: str, out: str, options: StabilizeOptions, warps_out: str | None = None,
                   compare: str | None = None, show_progress: bool = True) -> LiveStabilizeResult:
    """Stabilise ``source`` (live, or a file read in one pass) into ``out`` within
    ``options.latency`` seconds (:data:`DEFAULT_LATENCY` when None)."""
    file_info = check_live_request(source, out, options, warps_out, compare)  # a file's probe; None for a live input
    latency = options.latency if options.latency is not None else DEFAULT_LATENCY
    model = motion_model(options.model)
    crop = parse_crop(options.crop)
    border = parse_border(options.border if options.border is not None else ("replicate" if crop is None else "black"))
    live = file_info is None
    notes: list[str] = []
    # Loading a network takes seconds.  A file's: before its stream opens, so that no frame
    # waits for it.  A live input's: beside the opening, so that the socket listens (and a
    # sender may connect) at once; the frames that come meanwhile queue, and their deadlines
    # start as they are taken.
    estimator = _estimator(options) if _learned(options) and not live else None
    loading = built_beside(lambda: _estimator(options), after_start=True) if _learned(options) and live else None
    masked = None
    horizon: Horizon | None = None  # a file's rate is known now (a classical estimator, made later, answers at once)
    if file_info is not None:
        horizon = Horizon.for_latency(latency, file_info.fps, _delay(estimator))  # too short a latency fails first
        # A file's overlays are found as offline (it is there whole); a live input has only --mask.
        masked = frame_mask(source, options.mask, file_info, show_progress)
    with waited_for(loading), LiveStream(source, "yuv420p", timeout=options.timeout, quiet=not show_progress, live=live,
                                         info=file_info, on_started=lambda: begin(loading)) as stream:
        info = stream.info
        size, fps = info.source_size, info.fps
        if masked is None:
            masked = live_mask(options.mask, size, show_progress, source=source)
        tracker: Estimator | Bridged
        if loading is not None and not loading.done() and (width := trained_width(options.estimator, options.weights)) is not None:
            # The network still loads: ORB tracks the frames that come meanwhile, at its width.
            tracker = Bridged(loading, width, masked.use, size)
            delay = LIVE_CHUNK - 1
        else:
            estimator = estimator or (loading.result() if loading is not None else _estimator(options))
            estimator.set_mask(masked.use)
            estimator.reset(size)
            tracker, width, delay = estimator, estimator.input_width, _delay(estimator)
        if horizon is None:
            horizon = Horizon.for_latency(latency, fps, estimator_delay=delay)
        gray_size = scaled_size(size, width)
        if info.has_audio:
            notes.append(f"{source_name(source)}: the audio ({info.audio_codec}) is not carried by a --latency run")
            if show_progress:
                note(notes[-1])
        frame_bytes = size[0] * size[1] * 3 // 2
        schedule = LiveSchedule(OnlineL1Path(model, size, crop, horizon), size, fps, latency, live,
                                capacity=QUEUE_BYTES // frame_bytes)
        timeline = schedule.timeline
        preset = options.preset or live_preset(size, fps)
        if options.preset is None and preset != PRESET:
            notes.append(f"{size[0]}x{size[1]} at {fps:g} fps is encoded with x264's {preset} preset, a third of "
                         f"{PRESET}'s CPU, to keep the deadlines (--preset to choose)")
            if show_progress:
                note(notes[-1])
        writer = (StreamWriter(out, size, fps, options.crf, preset) if is_stream_output(out)
                  else VideoWriter(out, size, fps, crf=options.crf, preset=preset, pix_fmt_in="yuv420p"))
        # Gray images the tracker has yet to take: a short queue, so that frames are taken (and
        # their deadlines start) at the tracker's pace.  A stream faster than real time (a file
        # piped in) is then held back, as by a slow consumer, rather than leaving unsteadied.
        inbox: queue.Queue = queue.Queue(maxsize=TRACK_QUEUE)
        latencies: list[float] = []
        start = time.monotonic()
        stages = [threading.Thread(target=_stage, args=(schedule, job), daemon=True, name=f"stabilize-{name}")
                  for name, job in (("track", lambda: _track(schedule, tracker, inbox)),
                                    ("plan", lambda: _plan(schedule)),
                                    ("render", lambda: _render(schedule, writer, size, border, latencies)))]
        timeline.watch_gc()
        try:
            with stream_progress("stabilize (live)", disable=not show_progress) as advance:
                shown = 0

                def show() -> None:
                    nonlocal shown
                    done = schedule.rendered
                    if done > shown:
                        advance(done - shown)
                        shown = done

                for thread in stages:
                    thread.start()
                for arrival in stream.arrivals():
                    timeline.stamp("arrived", arrival.time)
                    timeline.stamp("taken")
                    cpu = time.thread_time()
                    gray = gray_of_yuv(arrival.frame, size, gray_size)
                    timeline.add_cpu("gray", time.thread_time() - cpu)
                    schedule.add_frame(arrival.frame, arrival.time)
                    _put(schedule, inbox, gray)
                    show()
                _put(schedule, inbox, _END)
                for thread in stages:
                    while thread.is_alive():
                        thread.join(0.1)
                        show()
                if schedule.failed is not None:
                    raise schedule.failed
        except Abandoned:  # a stage failed while this thread waited on it: its error
            writer.abort()
            assert schedule.failed is not None
            raise schedule.failed from None
        except BaseException as exc:
            schedule.fail(exc)
            writer.abort()
            raise
        finally:
            timeline.unwatch_gc()
        writer.close()
        frames_in = stream.frames_read
    warps_array = np.array(schedule.warps).reshape(-1, 3, 3)
    if warps_out is not None:
        write_warps(warps_out, warps_array, size)
    pairs = max(0, frames_in - 1)
    if isinstance(tracker, Bridged):
        pairs_by = {"orb": tracker.orb_pairs, tracker.name: pairs - tracker.orb_pairs}
    else:
        pairs_by = {tracker.name: pairs}
    pairs_by = {name: n for name, n in pairs_by.items() if n}
    if isinstance(tracker, Bridged) and tracker.orb_pairs:
        notes.append(f"{tracker.orb_pairs} of {pairs} frame pairs were tracked by ORB while the network loaded")
        if show_progress:
            note(notes[-1])
    if schedule.simplified_at is not None:
        notes.append(f"--model {options.model} could not keep up live from frame {schedule.simplified_at} on "
                     f"(frames left at their deadline): its similarity part alone was planned from there")
        if show_progress:
            note(notes[-1])
    if schedule.late:
        notes.append(f"{schedule.late} of {frames_in} frames left at their deadline on the path planned so far "
                     f"({schedule.path.held} of them past its end, moving with the camera): tracking or solving ran late")
        if show_progress:
            note(notes[-1])
    bound = latency + 1.0 / fps  # a frame's own interval on top: it is whole only once its last packet came
    if live and latencies and (p95 := float(np.percentile(latencies, 95))) > bound:
        late_frames = int(np.count_nonzero(np.array(latencies) > bound))
        warn(f"--latency {latency:g} s missed: p95 {p95:.2f} s, {late_frames} of {len(latencies)} frames later than "
             f"{bound:.2f} s (the latest {max(latencies):.2f} s); this machine could not keep up with "
             f"{size[0]}x{size[1]} at {fps:g} fps: a longer --latency, or a smaller input, would")
    return LiveStabilizeResult(frames_in, len(latencies), size, fps, horizon, np.array(latencies),
                               stream.ended_by if live else None, warps_array, time.monotonic() - start, notes,
                               schedule.late, schedule.path.held, schedule.solves, schedule.stale,
                               schedule.lookahead_min, timeline, schedule.path.rejoined, schedule.simplified_at,
                               np.array(schedule.lateness, bool), pairs_by)


_END = object()


def _stage(schedule: LiveSchedule, job: Callable[[], None]) -> None:
    try:
        job()
    except Abandoned:
        pass
    except BaseException as exc:  # handed to the main thread
        schedule.fail(exc)


def _put(schedule: LiveSchedule, inbox: queue.Queue, item: object) -> None:
    while True:
        if schedule.failed is not None:
            raise schedule.failed
        try:
            inbox.put(item, timeout=0.1)
            return
        except queue.Full:
            continue


def _track(schedule: LiveSchedule, estimator: Estimator | Bridged, inbox: queue.Queue) -> None:
    first = True
    while True:
        try:
            gray = inbox.get(timeout=0.1)
        except queue.Empty:
            if schedule.failed is not None:
                return
            continue
        if gray is _END:
            break
        if first:
            schedule.add_motion()
            first = False
        cpu = time.thread_time()
        estimates = estimator.feed(gray)
        schedule.timeline.add_cpu("estimator", time.thread_time() - cpu)
        for estimate in estimates:
            schedule.add_motion(estimate.H, estimate.confidence)
    for estimate in estimator.finish():
        schedule.add_motion(estimate.H, estimate.confidence)
    schedule.end_motion()


def _plan(schedule: LiveSchedule) -> None:
    while (job := schedule.next_window()) is not None:
        window, final = job
        clock, cpu = time.monotonic(), time.thread_time()
        params = schedule.path.solve(window)  # no lock held: tracking and rendering go on
        schedule.timeline.add_cpu("solve", time.thread_time() - cpu)
        schedule.solved(window, params, final, time.monotonic() - clock)


def _render(schedule: LiveSchedule, writer: StreamWriter | VideoWriter, size: tuple[int, int], border: str, latencies: list[float]) -> None:
    timeline = schedule.timeline
    while (frame := schedule.next_frame()) is not None:
        assert frame.warp is not None
        clock, cpu = time.monotonic(), time.thread_time()
        timeline.stamp("render", clock)
        warped = warp_yuv(frame.pixels, frame.warp, size, border)
        cpu2 = time.thread_time()
        writer.write(warped)
        handed = time.monotonic()
        timeline.add_cpu("warp", cpu2 - cpu)
        timeline.add_cpu("hand-over", time.thread_time() - cpu2)
        timeline.stamp("handed", handed)
        schedule.rendered_one(handed - clock)
        latencies.append(handed - frame.arrived)


def _estimator(options: StabilizeOptions) -> Estimator:
    """``--work-width`` as given (a classical estimator never works wider than the video)."""
    return make_estimator(options.estimator, work_width=options.work_width, weights=options.weights, device=options.device,
                          default_width=WORK_WIDTH,
                          **({"chunk": LIVE_CHUNK} if _learned(options) else {}))


class Bridged:
    """The network once it has loaded (``loading``), and ORB until then, on the same gray images
    (``width`` wide): a live stream's first frames, which come while the network loads, are
    tracked as they come instead of waiting for it.  The network starts from the last frame
    ORB saw, so that no pair is lost or estimated twice."""

    def __init__(self, loading: concurrent.futures.Future, width: int, use: np.ndarray | None, size: tuple[int, int]):
        from mosaic_cli.estimators import OrbEstimator

        self.loading, self.use, self.size = loading, use, size
        self.orb = OrbEstimator(width)
        self.orb.set_mask(use)
        self.orb.reset(size)
        self.current: Estimator = self.orb
        self.bridged = 0  # frames ORB took
        self.name = "network"  # the network's name, once it has loaded
        self._last: np.ndarray | None = None

    def feed(self, gray: np.ndarray) -> list:
        handed = []
        if self.current is self.orb and self.loading.done():
            network = self.loading.result()  # (its error, if loading failed: the track stage's)
            network.set_mask(self.use)
            network.reset(self.size)
            self.name = network.name
            handed = self.orb.finish()
            if self._last is not None:
                handed += network.feed(self._last)  # its first frame: no pair yet
            self.current = network
        if self.current is self.orb:
            self.bridged += 1
        self._last = gray
        return handed + self.current.feed(gray)

    def finish(self) -> list:
        return self.current.finish()

    @property
    def orb_pairs(self) -> int:
        """The pairs ORB estimated: those between the frames it took (it holds none back; the
        pair from its last frame to the network's first is the network's)."""
        return max(0, self.bridged - 1)


# The pixel rate (px/s) up to which a live run encodes with the offline preset: x264's veryfast
# costs 23 ms of CPU a 1280x720 frame and 48 ms a 1920x1080 one on this 2-core machine, ultrafast
# 8 and 18 ms, beside 6 and 12 ms of decoding.  A cold 720p30 run (the network loading beside the
# first seconds of the stream) reached p95 2.07 s with veryfast, 1.17-1.18 s with ultrafast
# (docs/measurements/live.md).
LIVE_VERYFAST_PIXEL_RATE = 854 * 480 * 30


def live_preset(size: tuple[int, int], fps: float) -> str:
    """x264's preset for a live run of frames of ``size`` at ``fps`` when --preset was not given."""
    return PRESET if size[0] * size[1] * fps <= LIVE_VERYFAST_PIXEL_RATE else "ultrafast"


def _delay(estimator: Estimator | None) -> int:
    """Frames an estimator answers late at most: a batching one answers a chunk at a time."""
    return max(0, getattr(getattr(estimator, "config", None), "chunk", 1) - 1)


def _learned(options: StabilizeOptions) -> bool:
    from mosaic_cli.estimators import DEFAULT_ESTIMATOR, LEARNED, parse_spec

    name = options.estimator if options.estimator is not None else ("" if options.weights else DEFAULT_ESTIMATOR)
    return options.weights is not None or parse_spec(name)[0] in LEARNED
