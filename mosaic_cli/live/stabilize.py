"""``stabilize --latency``: one pass, each frame out at most ``latency`` seconds after it came in.

Stages, each in a thread of its own, with the shared state in a :class:`~.schedule.LiveSchedule`:

1. decode   one ffmpeg, yuv420p at full size (:class:`~mosaic_cli.live.source.LiveStream`); the
            main thread takes each frame as it comes and makes the estimator's gray image;
2. track    the estimator on the gray images: the camera motion, pushed into the path;
3. plan     the lookahead-bounded L1 path (:mod:`mosaic_cli.stabilize.online`), solved in the
            background: each solve settles the frames it sees ``lookahead`` frames beyond;
4. render   warp each settled frame and hand it to the encoder: a file (atomic, at the end),
            standard output or a URL (MPEG-TS, :mod:`.output`).

**Deadlines** (live sources).  A frame is due at the encoder ``latency`` seconds after it
arrived off the decoder, less a reserve for warping and encoding (what they took lately); the
renderer takes one frame at a time, so a burst of frames due together (the decoder hands over
what it held while probing the stream) is begun early enough for its last frame.  A frame that
is not settled by then, because a solve ran late or the tracker fell behind, leaves with the
best path known: the last plan's view of it, predicted frames included, or past that plan's end
the last settled transform held.  Warping and encoding therefore never wait for the solver or
the tracker, and no frame is dropped.  The lookahead adapts: it shrinks (down to
``MIN_LOOKAHEAD``) while tracking and solving take longer, so that frames normally settle
before their deadline, and grows back to the horizon's when they are quick again.  A stream
faster than twice its frame rate, such as a file piped in, has its frames' budgets start at that
pace and is taken at the tracker's pace (a short queue), rather than sent on unsteadied.  A file
read in one pass has no deadlines.

**The busiest seconds** are the first: the network loads in a process of its own (below the
stages in the CPU's queue) while ORB tracks, and a `tilt` correction is planned as a similarity
until the network has taken over.  The solver is imported as the stream opens, and the
interpreter hands its lock over every half millisecond while the stages run.

Latency is measured per frame from its arrival off the decoder to its hand-over to the encoder;
:attr:`LiveStabilizeResult.timeline` has every stage's time stamps (``python -m benchmarks live``).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput, warn
from mosaic_cli.estimators import Estimator, make_estimator, plan_estimator
from mosaic_cli.live.bridge import Bridged
from mosaic_cli.live.loading import built_beside, trained_width
from mosaic_cli.live.network_process import NetworkProcess
from mosaic_cli.live.output import StreamWriter, is_stream_output
from mosaic_cli.live.schedule import LIVE_CHUNK, Abandoned, LiveSchedule
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
from mosaic_cli.progress import stream_progress
from mosaic_cli.stabilize.crop import parse_crop
from mosaic_cli.stabilize.online import Horizon, OnlineL1Path
from mosaic_cli.stabilize.path import motion_model
from mosaic_cli.stabilize.pipeline import PRESET, WORK_WIDTH, StabilizeOptions, write_warps
from mosaic_cli.stabilize.render import parse_border, warp_yuv
from mosaic_cli.stabilize.smoothing import load_solver
from mosaic_cli.video import VideoInfo, VideoWriter, probe
from mosaic_cli.video.lens_filter import ImageFilter
from mosaic_cli.video.reader import scaled_size
from mosaic_cli.video.writer import OUTPUT_SUFFIXES

DEFAULT_LATENCY = 1.0
# The interpreter's switch interval while the stages run (Python's default: 5 ms).  A solve holds
# the interpreter for tens of milliseconds; at 5 ms every other stage waited that long each time
# it came back from OpenCV or a pipe, and the tracker fell behind the stream for seconds.
STAGE_SWITCH_INTERVAL = 0.0005
TRACK_QUEUE = 2 * LIVE_CHUNK  # gray images waiting for the tracker: two of a learned estimator's batches
HOLD_POLL = 0.01  # seconds between looks at the tracker's queue while the decode stage waits for it


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
                   compare: str | None = None, show_progress: bool = True, *, lens: ImageFilter | None = None) -> LiveStabilizeResult:
    """Stabilise ``source`` (live, or a file read in one pass) into ``out`` within
    ``options.latency`` seconds (:data:`DEFAULT_LATENCY` when None).  ``lens``: each frame
    through this filter as it arrives (``--lens``: the undistorted view is written), the mask
    carried into the undistorted frame."""
    file_info = check_live_request(source, out, options, warps_out, compare)  # a file's probe; None for a live input
    latency = options.latency if options.latency is not None else DEFAULT_LATENCY
    model = motion_model(options.model)
    crop = parse_crop(options.crop)
    border = parse_border(options.border if options.border is not None else ("replicate" if crop is None else "black"))
    live = file_info is None
    notes: list[str] = []
    # Loading a network takes seconds.  A file's: before its stream opens, so that no frame
    # waits for it.  A live input's: in a process of its own (:mod:`.network_process`), beside
    # the opening, so that the socket listens (and a sender may connect) at once and the
    # stream's threads never wait on torch's import; ORB tracks the frames that come meanwhile.
    estimator = _estimator(options) if _learned(options) and not live else None
    network, loading = _network_beside(options) if _learned(options) and live else (None, None)
    masked = None
    horizon: Horizon | None = None  # a file's rate is known now (a classical estimator, made later, answers at once)
    if file_info is not None:
        horizon = Horizon.for_latency(latency, file_info.fps, _delay(estimator))  # too short a latency fails first
        # A file's overlays are found as offline (it is there whole); a live input has only --mask.
        masked = frame_mask(source, options.mask, file_info, show_progress, lens)
    # The solver is imported once the decoder listens, while it waits for the sender and the
    # stream's header: not before (the socket would open later), nor at the first window, in the
    # middle of the first frames (see load_solver).
    with _ended(network, loading), LiveStream(source, "yuv420p", timeout=options.timeout, quiet=not show_progress,
                                              live=live, info=file_info, on_started=_solver_beside, lens=lens) as stream:
        info = stream.info
        size, fps = info.source_size, info.fps
        if masked is None:
            masked = live_mask(options.mask, size, show_progress, lens)
        tracker, width, delay = _tracker(options, estimator, loading, masked.use, size)
        if horizon is None:
            horizon = Horizon.for_latency(latency, fps, estimator_delay=delay)
        if info.has_audio:
            _say(notes, f"{source_name(source)}: the audio ({info.audio_codec}) is not carried by a --latency run", show_progress)
        frame_bytes = size[0] * size[1] * 3 // 2
        schedule = LiveSchedule(OnlineL1Path(model, size, crop, horizon), size, fps, latency, live,
                                capacity=QUEUE_BYTES // frame_bytes, render_guess=_render_guess(size, border))
        writer = _encoder(out, size, fps, options, notes, show_progress)
        start = time.monotonic()
        latencies = _run_stages(stream, schedule, tracker, writer, size, scaled_size(size, width), border, show_progress)
        frames_in = stream.frames_read
    warps_array = np.array(schedule.warps).reshape(-1, 3, 3)
    if warps_out is not None:
        write_warps(warps_out, warps_array, size)
    pairs_by = _pairs_by(tracker, frames_in)
    _closing_notes(notes, schedule, tracker, frames_in, options.model, show_progress)
    if live:
        _warn_missed(latencies, latency, size, fps)
    return LiveStabilizeResult(frames_in, len(latencies), size, fps, horizon, np.array(latencies),
                               stream.ended_by if live else None, warps_array, time.monotonic() - start, notes,
                               schedule.late, schedule.path.held, schedule.solves, schedule.stale,
                               schedule.lookahead_min, schedule.timeline, schedule.path.rejoined, schedule.simplified_at,
                               np.array(schedule.lateness, bool), pairs_by)


def _say(notes: list[str], text: str, show_progress: bool) -> None:
    """One of the run's notes: kept in its result, and said at once unless quiet."""
    notes.append(text)
    if show_progress:
        note(notes[-1])


def _tracker(options: StabilizeOptions, estimator: Estimator | None, loading: concurrent.futures.Future | None,
             use: np.ndarray | None, size: tuple[int, int]) -> tuple[Estimator | Bridged, int, int]:
    """The tracking stage's estimator, the width of its gray images and the frames it answers
    late at most: the network (``estimator``, made already, or ``loading``), or where it still
    loads (a live input), ORB until it has (:class:`~.bridge.Bridged`)."""
    if loading is not None and not loading.done() and (width := trained_width(options.estimator, options.weights)) is not None:
        # The network still loads: ORB tracks the frames that come meanwhile, at its width.
        return Bridged(loading, width, use, size), width, LIVE_CHUNK - 1
    estimator = estimator or (loading.result() if loading is not None else _estimator(options))
    estimator.set_mask(use)
    estimator.reset(size)
    return estimator, estimator.input_width, _delay(estimator)


def _encoder(out: str, size: tuple[int, int], fps: float, options: StabilizeOptions, notes: list[str],
             show_progress: bool) -> StreamWriter | VideoWriter:
    """The render stage's encoder: a stream (standard output, a URL) or a file, with x264's
    preset for the pixel rate where none was given (:func:`live_preset`)."""
    preset = options.preset or live_preset(size, fps)
    if options.preset is None and preset != PRESET:
        _say(notes, f"{size[0]}x{size[1]} at {fps:g} fps is encoded with x264's {preset} preset, a third of "
                    f"{PRESET}'s CPU, to keep the deadlines (--preset to choose)", show_progress)
    return (StreamWriter(out, size, fps, options.crf, preset) if is_stream_output(out)
            else VideoWriter(out, size, fps, crf=options.crf, preset=preset, pix_fmt_in="yuv420p"))


def _run_stages(stream: LiveStream, schedule: LiveSchedule, tracker: Estimator | Bridged, writer: StreamWriter | VideoWriter,
                size: tuple[int, int], gray_size: tuple[int, int], border: str, show_progress: bool) -> list[float]:
    """The four stages, to the stream's end: decode on this thread (:func:`_decode`), track, plan
    and render each on a thread of its own; the encoder closed at the end (aborted on a failure,
    whose error is raised here).  Each frame's latency, in order."""
    timeline = schedule.timeline
    # Gray images the tracker has yet to take: a short queue while the frames come early (a file
    # piped in, held back as by a slow consumer rather than leaving unsteadied), any length for
    # frames that are due (_put).
    inbox: queue.Queue = queue.Queue()
    latencies: list[float] = []
    stages = [threading.Thread(target=_stage, args=(schedule, job), daemon=True, name=f"stabilize-{name}")
              for name, job in (("track", lambda: _track(schedule, tracker, inbox)),
                                ("plan", lambda: _plan(schedule)),
                                ("render", lambda: _render(schedule, writer, size, border, latencies)))]
    timeline.watch_gc()
    interval = sys.getswitchinterval()
    sys.setswitchinterval(STAGE_SWITCH_INTERVAL)
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
            _decode(stream, schedule, inbox, size, gray_size, show)
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
        sys.setswitchinterval(interval)
    writer.close()
    return latencies


def _pairs_by(tracker: Estimator | Bridged, frames_in: int) -> dict[str, int]:
    """The frame pairs each estimator made (ORB's while the network loaded), those that made any."""
    pairs = max(0, frames_in - 1)
    if isinstance(tracker, Bridged):
        pairs_by = {"orb": tracker.orb_pairs, tracker.name: pairs - tracker.orb_pairs}
    else:
        pairs_by = {tracker.name: pairs}
    return {name: n for name, n in pairs_by.items() if n}


def _closing_notes(notes: list[str], schedule: LiveSchedule, tracker: Estimator | Bridged, frames_in: int, model: str,
                   show_progress: bool) -> None:
    """What the run says once over: ORB's share, a correction that could not keep up, the frames
    that left at their deadline."""
    pairs = max(0, frames_in - 1)
    if isinstance(tracker, Bridged) and tracker.orb_pairs:
        meanwhile = f" (--model {model} planned as a similarity meanwhile)" if schedule.path.model.gated else ""
        _say(notes, f"{tracker.orb_pairs} of {pairs} frame pairs were tracked by ORB while the network loaded{meanwhile}",
             show_progress)
    if schedule.simplified_at is not None:
        _say(notes, f"--model {model} could not keep up live from frame {schedule.simplified_at} on "
                    f"(frames left at their deadline): its similarity part alone was planned from there", show_progress)
    if schedule.late:
        _say(notes, f"{schedule.late} of {frames_in} frames left at their deadline on the path planned so far "
                    f"({schedule.path.held} of them past its end, moving with the camera): tracking or solving ran late",
             show_progress)


def _warn_missed(latencies: list[float], latency: float, size: tuple[int, int], fps: float) -> None:
    """One warning line where a live run's 95th percentile latency missed ``--latency``."""
    bound = latency + 1.0 / fps  # a frame's own interval on top: it is whole only once its last packet came
    if latencies and (p95 := float(np.percentile(latencies, 95))) > bound:
        late_frames = int(np.count_nonzero(np.array(latencies) > bound))
        warn(f"--latency {latency:g} s missed: p95 {p95:.2f} s, {late_frames} of {len(latencies)} frames later than "
             f"{bound:.2f} s (the latest {max(latencies):.2f} s); this machine could not keep up with "
             f"{size[0]}x{size[1]} at {fps:g} fps: a longer --latency, or a smaller input, would")


_END = object()


def _stage(schedule: LiveSchedule, job: Callable[[], None]) -> None:
    try:
        job()
    except Abandoned:
        pass
    except BaseException as exc:  # handed to the main thread
        schedule.fail(exc)


def _put(schedule: LiveSchedule, inbox: queue.Queue, item: object, start: float | None = None) -> None:
    """Queue ``item`` for the tracker.  While :data:`TRACK_QUEUE` images wait already, the decode
    stage waits with it (a stream faster than the tracker is taken at the tracker's pace), but a
    live frame only until its budget starts (``start``): a frame that is due is not kept from the
    renderer's deadlines by a tracker that fell behind (the network loading beside it), unless
    the tracker is as many frames behind as may be in flight (memory stays bounded)."""
    while True:
        now = schedule.clock()
        due = start is not None and now >= start
        if inbox.qsize() < (schedule.capacity if due else TRACK_QUEUE):
            break
        if schedule.failed is not None:
            raise schedule.failed
        time.sleep(HOLD_POLL if start is None or due else min(HOLD_POLL, start - now))
    inbox.put(item)


def _decode(stream: LiveStream, schedule: LiveSchedule, inbox: queue.Queue, size: tuple[int, int], gray_size: tuple[int, int],
            show: Callable[[], None]) -> None:
    """The decode stage, on the calling thread: each frame taken off the stream into the
    schedule, its gray image (``gray_size``) queued for the tracker; the end queued last."""
    timeline = schedule.timeline
    for arrival in stream.arrivals():
        timeline.stamp("arrived", arrival.time)
        timeline.stamp("taken")
        cpu = time.thread_time()
        gray = gray_of_yuv(arrival.frame, size, gray_size)
        timeline.add_cpu("gray", time.thread_time() - cpu)
        start = schedule.add_frame(arrival.frame, arrival.time)
        _put(schedule, inbox, gray, start if schedule.realtime else None)
        show()
    _put(schedule, inbox, _END, -float("inf"))  # (the end is due at once)


def _track(schedule: LiveSchedule, estimator: Estimator | Bridged, inbox: queue.Queue) -> None:
    first = True
    # While the network loads beside the stream, the machine is at its busiest: a gated model
    # (tilt) is planned as a similarity meanwhile, a third of the solver's work.
    bridging = isinstance(estimator, Bridged) and schedule.path.model.gated
    if bridging:
        schedule.path.similar_only = True
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
        if bridging and estimator.loaded:
            bridging = False
            schedule.path.similar_only = schedule.simplified_at is not None
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


def _solver_beside() -> None:
    threading.Thread(target=load_solver, name="mosaic-solver", daemon=True).start()


def _render_guess(size: tuple[int, int], border: str) -> float:
    """What rendering a frame will take, until the first is timed: twice a blank frame's warp
    (the hand-over to the encoder copies it again), so that a first burst of frames is begun
    early enough."""
    blank = np.zeros((size[1] * 3 // 2, size[0]), np.uint8)
    warp_yuv(blank, np.eye(3), size, border)  # (the first call sets OpenCV up)
    clock = time.perf_counter()
    warp_yuv(blank, np.eye(3), size, border)
    return 2 * (time.perf_counter() - clock)


def _estimator(options: StabilizeOptions) -> Estimator:
    """``--work-width`` as given (a classical estimator never works wider than the video)."""
    return make_estimator(**_build(options))


def _network_beside(options: StabilizeOptions) -> tuple[NetworkProcess, concurrent.futures.Future]:
    """The network of a live run, started in a child process (checked here first: a mistake is
    said before the stream opens), and the wait until it has loaded."""
    build = _build(options)
    plan_estimator(**build)
    network = NetworkProcess(build, wait=False)
    return network, built_beside(network.wait_loaded, in_this_process=False)


@contextlib.contextmanager
def _ended(network: NetworkProcess | None, loading: concurrent.futures.Future | None) -> Iterator[None]:
    """On the way out, the network's process ended (killed while it still loads: the end of a
    short stream does not wait for torch's import in another process) and its wait joined."""
    try:
        yield
    finally:
        if network is not None and loading is not None:
            network.close()
            concurrent.futures.wait([loading])


def _build(options: StabilizeOptions) -> dict:
    """:func:`~mosaic_cli.estimators.make_estimator`'s arguments for ``options``."""
    return {"name": options.estimator, "work_width": options.work_width, "weights": options.weights,
            "device": options.device, "default_width": WORK_WIDTH, **({"chunk": LIVE_CHUNK} if _learned(options) else {})}


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
