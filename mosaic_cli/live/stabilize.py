"""``stabilize --latency``: one pass, each frame out at most ``latency`` seconds after it came in.

Stages, as frames arrive:

1. decode   one ffmpeg, yuv420p at full size (:class:`~mosaic_cli.live.source.LiveStream`);
2. track    the estimator on the Y plane, downscaled to its working width;
3. plan     the lookahead-bounded L1 path (:mod:`mosaic_cli.stabilize.online`): the views of the
            frames whose horizon has arrived;
4. render   (a second thread) warp each settled frame, hand it to the encoder: a file (atomic,
            at the end), standard output or a URL (MPEG-TS, :mod:`.output`).

Latency is measured per frame from its arrival off the decoder to its hand-over to the encoder.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import make_estimator
from mosaic_cli.live.output import StreamWriter, is_stream_output
from mosaic_cli.live.progress import stream_progress
from mosaic_cli.live.source import LiveStream, gray_of_yuv, is_live_source, note, source_name
from mosaic_cli.overlay import frame_mask, live_mask, load_mask
from mosaic_cli.stabilize.crop import output_warps, parse_crop
from mosaic_cli.stabilize.online import Horizon, OnlineL1Path
from mosaic_cli.stabilize.path import motion_model
from mosaic_cli.stabilize.pipeline import VIDEO_SUFFIXES, WORK_WIDTH, StabilizeOptions, write_warps
from mosaic_cli.stabilize.render import parse_border, warp_yuv
from mosaic_cli.stabilize.smoothing import L1Smoother
from mosaic_cli.video import VideoInfo, VideoWriter, probe
from mosaic_cli.video.reader import scaled_size

DEFAULT_LATENCY = 1.0
LIVE_CHUNK = 4  # a learned estimator's frame pairs per batch: its answer comes 3 frames late at most


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
    if not is_stream_output(out) and Path(out).suffix.lower() not in VIDEO_SUFFIXES:
        raise BadInput(f"output {out} must end in one of {', '.join(VIDEO_SUFFIXES)}, or be - or a URL")
    if warps_out is not None and Path(warps_out).suffix.lower() != ".json":
        raise BadInput(f"--warps {warps_out} must end in .json")
    if not is_live_source(source):
        info = probe(source)  # the file checks of every command: missing, empty, damaged
        if options.mask.file is not None:
            load_mask(options.mask.file, info.source_size)  # a bad --mask fails before any work
        return info
    return None


def stabilize_live(source: str, out: str, options: StabilizeOptions, warps_out: str | None = None,
                   compare: str | None = None, show_progress: bool = True) -> LiveStabilizeResult:
    """Stabilise ``source`` (live, or a file read in one pass) into ``out`` within
    ``options.latency`` seconds (:data:`DEFAULT_LATENCY` when None)."""
    probed = check_live_request(source, out, options, warps_out, compare)  # a file's probe; None for a live input
    latency = options.latency if options.latency is not None else DEFAULT_LATENCY
    model = motion_model(options.model)
    crop = parse_crop(options.crop)
    border = parse_border(options.border if options.border is not None else ("replicate" if crop is None else "black"))
    live = is_live_source(source)
    notes: list[str] = []
    with LiveStream(source, "yuv420p", timeout=options.timeout, quiet=not show_progress, live=live, info=probed) as stream:
        info = stream.info
        size, fps = info.source_size, info.fps
        width = options.work_width if options.work_width is not None else min(WORK_WIDTH, size[0])
        estimator = make_estimator(options.estimator, work_width=width, weights=options.weights, device=options.device,
                                   **({"chunk": LIVE_CHUNK} if _learned(options) else {}))
        chunk = getattr(getattr(estimator, "config", None), "chunk", 1)
        horizon = Horizon.for_latency(latency, fps, estimator_delay=max(0, chunk - 1))
        # After the option checks: a file's overlays are found as offline (it is there whole);
        # a live input has only --mask.
        masked = live_mask(options.mask, size, show_progress) if live else frame_mask(source, options.mask, probed, show_progress)
        estimator.set_mask(masked.use)
        path = OnlineL1Path(model, size, crop, horizon, L1Smoother())
        gray_size = scaled_size(size, estimator.input_width)
        if info.has_audio:
            notes.append(f"{source_name(source)}: the audio ({info.audio_codec}) is not carried by a --latency run")
            if show_progress:
                note(notes[-1])
        writer = (StreamWriter(out, size, fps, options.crf, options.preset) if is_stream_output(out)
                  else VideoWriter(out, size, fps, crf=options.crf, preset=options.preset, pix_fmt_in="yuv420p"))
        renderer = _RenderThread(writer, size, border)
        waiting: deque = deque()  # (frame, arrival time) of frames whose view is not settled
        warps: list[np.ndarray] = []
        start = time.monotonic()
        try:
            with stream_progress("stabilize (live)", disable=not show_progress) as advance:
                def hand_over(views: np.ndarray) -> None:
                    for W in output_warps(views, size) if len(views) else ():
                        frame, arrived = waiting.popleft()
                        warps.append(W)
                        renderer.put(frame, W, arrived)
                        advance(1)

                estimator.reset(size)
                for arrival in stream.arrivals():
                    if not waiting and path.frames == 0:
                        path.push()
                    waiting.append((arrival.frame, arrival.time))
                    for estimate in estimator.feed(gray_of_yuv(arrival.frame, size, gray_size)):
                        path.push(estimate.H, estimate.confidence)
                    hand_over(path.settle())
                for estimate in estimator.finish():
                    path.push(estimate.H, estimate.confidence)
                hand_over(path.settle(final=True))
                latencies = renderer.finish()
        except BaseException:
            renderer.abandon()
            writer.abort()
            raise
        writer.close()
        frames_in = stream.frames_read
    warps_array = np.array(warps).reshape(-1, 3, 3)
    if warps_out is not None:
        write_warps(warps_out, warps_array, size)
    return LiveStabilizeResult(frames_in, renderer.written, size, fps, horizon, np.array(latencies),
                               stream.ended_by if live else None, warps_array, time.monotonic() - start, notes)


def _learned(options: StabilizeOptions) -> bool:
    from mosaic_cli.estimators import DEFAULT_ESTIMATOR, LEARNED, parse_spec

    name = options.estimator if options.estimator is not None else ("" if options.weights else DEFAULT_ESTIMATOR)
    return options.weights is not None or parse_spec(name)[0] in LEARNED


_DONE = object()


class _RenderThread:
    """Warps and encodes settled frames in a second thread (OpenCV and the encoder pipe release
    the GIL, so on two cores this overlaps the tracking).  The queue is short: a renderer that
    falls behind holds the main thread back, which shows as latency, never as lost frames."""

    DEPTH = 8

    def __init__(self, writer, size: tuple[int, int], border: str):
        self.writer = writer
        self.size = size
        self.border = border
        self.written = 0
        self.latencies: list[float] = []
        self._queue: queue.Queue = queue.Queue(maxsize=self.DEPTH)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def put(self, frame: np.ndarray, warp: np.ndarray, arrived: float) -> None:
        if self._error is not None:
            raise self._error
        self._queue.put((frame, warp, arrived))

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is _DONE:
                return
            if self._error is not None:
                continue
            frame, warp, arrived = item
            try:
                self.writer.write(warp_yuv(frame, warp, self.size, self.border))
            except BaseException as exc:  # handed to the main thread
                self._error = exc
                continue
            self.latencies.append(time.monotonic() - arrived)
            self.written += 1

    def finish(self) -> list[float]:
        self._queue.put(_DONE)
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self.latencies

    def abandon(self) -> None:
        self._error = self._error or RuntimeError("abandoned")
        try:
            self._queue.put_nowait(_DONE)
        except queue.Full:
            pass
