"""Second pass: decode the input again at full resolution, warp every frame, encode.

Decoding (an ffmpeg pipe), warping (OpenCV) and encoding (an x264 pipe) all release the GIL, so
each runs in its own thread with small bounded queues between them: on two cores the three
overlap instead of taking turns, and at most a handful of frames are in memory.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator

import cv2
import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.progress import progress_task
from mosaic_cli.video import VideoInfo, VideoWriter, open_video

BORDERS = {"black": cv2.BORDER_CONSTANT, "replicate": cv2.BORDER_REPLICATE, "reflect": cv2.BORDER_REFLECT}
COMPARE_PANEL_WIDTH = 960  # wider inputs are shown at half size in --compare videos


def parse_border(name: str) -> str:
    if name.lower() not in BORDERS:
        raise BadInput(f"--border must be one of {', '.join(BORDERS)}, got {name!r}")
    return name.lower()


def warp_frame(frame: np.ndarray, warp: np.ndarray, size: tuple[int, int], border: str = "black") -> np.ndarray:
    """The output frame: ``frame`` resampled so that input pixel x lands on ``warp @ x``."""
    mode = BORDERS[border]
    if abs(warp[2, 0]) < 1e-12 and abs(warp[2, 1]) < 1e-12:
        # An affine warp is worth the faster path (no per-pixel division).
        return cv2.warpAffine(frame, (warp[:2] / warp[2, 2]).astype(np.float64), size, flags=cv2.INTER_LINEAR,
                              borderMode=mode)
    return cv2.warpPerspective(frame, warp, size, flags=cv2.INTER_LINEAR, borderMode=mode)


def side_by_side(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Input and output next to each other (halved when the frames are wide)."""
    h, w = left.shape[:2]
    if w > COMPARE_PANEL_WIDTH:
        size = (w // 2, h // 2)
        left = cv2.resize(left, size, interpolation=cv2.INTER_AREA)
        right = cv2.resize(right, size, interpolation=cv2.INTER_AREA)
    return np.hstack([left, right])


def compare_size(size: tuple[int, int]) -> tuple[int, int]:
    w, h = size
    return (2 * (w // 2), h // 2) if w > COMPARE_PANEL_WIDTH else (2 * w, h)


@dataclass
class Renderer:
    """Options of the output encoding."""

    border: str = "black"
    crf: int = 18
    preset: str = "veryfast"  # x264 'medium' halves throughput on two cores for a few % of bitrate

    def render(self, video: str | Path, out: str | Path, warps: np.ndarray, info: VideoInfo,
               compare: str | Path | None = None, show_progress: bool = True) -> int:
        """Write the stabilised video (and the side-by-side one); returns the frames written.

        Frames beyond ``len(warps)`` (a decoder that finds one more frame the second time)
        reuse the last warp."""
        size = info.source_size
        audio = str(video) if info.has_audio else None
        writers = [VideoWriter(out, size, info.fps, crf=self.crf, preset=self.preset, audio_from=audio)]
        if compare is not None:
            writers.append(VideoWriter(compare, compare_size(size), info.fps, crf=self.crf, preset=self.preset,
                                       audio_from=audio))
        try:
            with open_video(video) as stream, progress_task("stabilize: render", len(warps), disable=not show_progress) as advance:
                def outputs() -> Iterator[tuple[np.ndarray, ...]]:
                    for t, frame in enumerate(_background(stream)):
                        result = warp_frame(frame, warps[min(t, len(warps) - 1)], size, self.border)
                        yield (result, side_by_side(frame, result)) if compare is not None else (result,)

                written = _drain(outputs(), [w.write for w in writers], advance)
            for writer in writers:
                writer.close()
        except BaseException:
            for writer in writers:
                writer.abort()
            raise
        return written


_DONE = object()


def _background(items: Iterable, depth: int = 4) -> Iterator:
    """Iterate ``items`` in a worker thread, ``depth`` items ahead of the consumer."""
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def produce() -> None:
        try:
            for item in items:
                while not stop.is_set():
                    try:
                        q.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            q.put(_DONE)
        except BaseException as exc:  # handed to the consumer, which re-raises it
            q.put(exc)

    worker = threading.Thread(target=produce, daemon=True)
    worker.start()
    try:
        while True:
            item = q.get()
            if item is _DONE:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        worker.join(timeout=5)


def _drain(results: Iterable[tuple[np.ndarray, ...]], sinks: list[Callable[[np.ndarray], None]],
           advance: Callable[[int], None], depth: int = 4) -> int:
    """Feed each element of every result tuple to its sink, one encoder thread per sink."""
    queues = [queue.Queue(maxsize=depth) for _ in sinks]
    errors: list[BaseException] = []

    def consume(q: queue.Queue, sink: Callable[[np.ndarray], None]) -> None:
        while True:
            item = q.get()
            if item is _DONE:
                return
            if errors:
                continue  # keep draining so the producer never blocks
            try:
                sink(item)
            except BaseException as exc:
                errors.append(exc)

    workers = [threading.Thread(target=consume, args=(q, s), daemon=True) for q, s in zip(queues, sinks)]
    for worker in workers:
        worker.start()
    count = 0
    try:
        for result in results:
            if errors:
                break
            for q, frame in zip(queues, result):
                q.put(frame)
            count += 1
            advance(1)
    finally:
        for q in queues:
            q.put(_DONE)
        for worker in workers:
            worker.join()
    if errors:
        raise errors[0]
    return count
