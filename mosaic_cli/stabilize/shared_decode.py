"""``stabilize``'s one decode of its input, shared by the tracking pass and the render.

The input is decoded once, at full resolution and as the render reads it (yuv420p planes, or
RGB: :func:`~.render.render_yuv`), on a thread of its own (:class:`SharedDecode`).  Each frame
goes into a ring, where the tracking pass reads it reduced to what it estimates from (gray at
the estimator's input width: :func:`tracking_gray`) and the render reads it whole once its
warp is known; a frame leaves the ring once both have read it.

**The reduced frame.**  The tracking's decode of old (and ``mosaic track``'s) had ffmpeg scale
the luma plane with swscale's area filter; here the luma plane is area-averaged by OpenCV and
stretched from the limited range to the full one (:func:`~mosaic_cli.video.decode.gray_at`, as
``stitch``'s scan does).  At full size the two are equal, bit for bit (BT.601 video); scaled,
they differ by one grey level on about 30% of the pixels, never more (a 1280x720 ``mosaic
simulate -p shaky`` flight at 640 and 320 px), which moves the default estimator's pairwise
homographies by 0.03 px at the corners (median; 0.16 px at most) and its error against the
simulator's truth not at all.  Pixels equal to ``track``'s would need a second output of
ffmpeg's own scaler beside the full-size one (docs/measurements/stabilize.md says why not).

**The ring's bound.**  The render waits for frame t's warp, which the path settles only once
the tracking has told it the pairs up to the end of the L1 window that settles t
(:class:`~.smoothing.L1Planner`, window ``W``, ``overlap``): the first window settles frames
[0, W - overlap) once frames [0, W) are tracked; each later one ends W - overlap - CARRIED
frames after the one before and settles up to ``overlap`` frames before its end, so from the
frame the render waits for to the last frame the path needs for it there are at most W frames
(W - CARRIED after the first window).  Besides, an estimator may hold frames back before it
tells their pairs (a learned one runs ``chunk`` pairs at a time and tells them a chunk late:
up to 2 chunk - 1 frames), a
failed pair waits for the next success (:class:`~.stream.FailedPairFill`), and with
``--rolling-shutter auto`` the render's first frame waits for the probe's first
``AUTO_PROBE_FRAMES`` frames.  :func:`ring_frames` adds these up (``FAILED_RUN`` failed pairs in
a row); a ring over ``RING_BYTES`` is not kept (two decodes from the start).

**Never a deadlock.**  The decode waits for room in the ring (memory bounded), the tracking for
the decode, the render for the tracking.  A ring too small for what the path needs (a run of
failed pairs longer than ``FAILED_RUN``, ``--smoothing gaussian``, whose views all settle at the
end) would close that circle: the render waits for a warp
(:meth:`~.stream.PathFeed.starved`) and the tracking, its mask settled, for a frame the decode
has no room for.  Then the decode stops keeping frames for the render from that frame on, and
goes on for the tracking alone (``READ_AHEAD`` frames ahead of it at most); the render reads the
rest from a second decode of the file started at that frame (``open_video(start=k)``), the two
decodes of old.  With ``--smoothing gaussian`` that second decode starts at the first frame.

**The overlays.**  While the overlay detection may still change the mask
(:mod:`mosaic_cli.overlay.speculate`), the tracking's pairs are held back, so the render holds
its first frame and nothing leaves the ring: a tracking pass that starts again from the first
frame (an overlay found) reads the ring again from its first frame.  A tracking pass that waits
for a frame meanwhile looks at the detection (``Gate.poll``), so that its held pairs go on, or
the restart comes, as soon as the detection ends; the ring does not grow while it waits.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Generator, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from mosaic_cli.estimators import Estimator
from mosaic_cli.estimators.rolling import AUTO_PROBE_FRAMES
from mosaic_cli.overlay.speculate import Gate
from mosaic_cli.stabilize.smoothing import GaussianSmoother, L1Smoother
from mosaic_cli.stabilize.stream import WAIT_SLICE, Cancelled
from mosaic_cli.video import VideoInfo, open_video
from mosaic_cli.video.decode import ImageFilter, YuvFrame, gray_at, yuv420p_bytes
from mosaic_cli.video.info import scaled_size
from mosaic_cli.video.stream import VideoStream

FAILED_RUN = 15  # failed pairs in a row the ring has room for (half a second at 30 fps)
# The ring's frames together, at most; a path that needs more decodes twice from the start (the
# render its own decode), as before the ring.  One decode paid at 1280x720 (a 166-frame ring of
# 230 MB: `stabilize` 19.0 s against 20.3 s, 1200 frames) and lost at 3840x2160 (2.1 GB: 40.3-45.1 s
# against 36.7-37.0 s decoding twice, 300 frames; docs/measurements/speed.md); 1920x1080 (516 MB) is
# under the bound, unmeasured.
RING_BYTES = 512 << 20
_ENDED = object()  # (SharedDecode._ready: the decode ended before the frame asked for)
READ_AHEAD = 4  # frames decoded for the tracking alone, ahead of it, once the render reads a decode of its own


def ring_frames(smoother: L1Smoother | GaussianSmoother, estimator: Estimator, frame_bytes: int, rolling: bool = False) -> int:
    """The frames the ring holds at most (see the module docstring): 0 for a smoother with no
    windows; else the L1 window, the frames ``estimator`` may hold back (a learned one's chunk
    and the chunk it tells late, less one), ``FAILED_RUN``, and with ``rolling`` (the rolling-shutter probe) at least
    ``AUTO_PROBE_FRAMES``; 0 (no ring: the render decodes on its own from the first frame) where
    they would take more than ``RING_BYTES``."""
    if not isinstance(smoother, L1Smoother):
        return 0
    held = estimator.frames_held(lookahead=True)  # (the tracking is a file's pass: track_video's lookahead)
    frames = smoother.window + held + FAILED_RUN
    if rolling:  # the render's first frame waits for the probe's frames (and their first pair)
        frames = max(frames, AUTO_PROBE_FRAMES, held + 2)
    return frames if frames * frame_bytes <= RING_BYTES else 0


def frame_bytes(info: VideoInfo, yuv: bool) -> int:
    """The bytes of one decoded frame: yuv420p planes or RGB, at the source size."""
    w, h = info.source_size
    return yuv420p_bytes((w, h)) if yuv else w * h * 3


def tracking_gray(frame: np.ndarray, source_size: tuple[int, int], size: tuple[int, int], yuv: bool) -> np.ndarray:
    """The tracking's frame (h, w) uint8 gray of ``size`` from a decoded frame of ``source_size``:
    yuv420p planes (``yuv``) or RGB, through its luma plane where it has one (:func:`gray_at`)."""
    if yuv:  # (a YuvFrame stands for the RGB frame, gray_at reads its luma plane)
        return gray_at(YuvFrame(frame.reshape(-1), source_size), size)  # type: ignore[arg-type]
    return gray_at(frame, size)


class SharedDecode:
    """The input decoded once for the tracking (:meth:`tracking`, one view per tracking attempt)
    and the render (:meth:`render_frames`), through a ring of at most ``capacity`` frames (see the
    module docstring).  ``starved()``: whether the render waits for a warp the tracking has not
    given (:meth:`~.stream.PathFeed.starved`).  :meth:`start` starts the decoding thread,
    :meth:`stop` ends it (and wakes whoever waits on it: :class:`~.stream.Cancelled`).

    ``lens``: the frames through this filter as they are decoded (``--lens``); ``undistort``
    (``--keep-lens``, with no ``lens``): the tracking's frames alone, the render's left as the
    lens saw them.  ``peak``: the most frames the ring held at once; ``second_decode_from``: the
    frame from which the render read a decode of its own (None: it read every frame from the ring)."""

    def __init__(self, video: str | Path, info: VideoInfo, yuv: bool, width: int, capacity: int, starved: Callable[[], bool],
                 undistort: Callable[[np.ndarray], np.ndarray] | None = None, lens: ImageFilter | None = None):
        if undistort is not None and lens is not None:
            raise ValueError("undistort reads the frames as the lens saw them: not with a lens filter on the decode")
        self.video, self.info, self.yuv, self.width, self.capacity = video, info, yuv, width, int(capacity)
        # stabilize --keep-lens: the frames decoded as the lens sees them (the render's), and the
        # tracking's luma plane (or RGB frame) undistorted at full size before it is reduced, as
        # the decode's own --lens filter would have (the same reduced frames, bit for bit)
        self.undistort = undistort
        self.lens = lens  # --lens: the filter the frames are decoded through (None with ``undistort``)
        self._starved = starved
        self.tracking_size = scaled_size(info.source_size, width)
        self._frames: dict[int, np.ndarray] = {}  # by index: those the render or the tracking has still to read
        self._decoded = 0  # frames decoded so far
        self._rendered = 0  # the render's next frame
        self._tracked = 0  # the tracking's next frame
        # The tracking's mask has settled (its gate, as the tracking last looked; False between
        # attempts): from then on its pairs reach the path as soon as they are estimated.
        self._settled = False
        self._spill: int | None = 0 if self.capacity <= 0 else None  # second_decode_from
        self._ended = self._stopped = False
        self._halt = False  # the decoding thread is to end (the tracking decodes again from the first frame)
        self._error: BaseException | None = None
        self._decode_error: str | None = None  # the decoder's complaint, once it has ended
        self.peak = 0
        self._changed = threading.Condition()
        self._thread = threading.Thread(target=self._run, name="mosaic-decode", daemon=True)

    @property
    def second_decode_from(self) -> int | None:
        return self._spill

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        """End the decoding (its decoder closed) and wake both readers."""
        with self._changed:
            self._stopped = True
            self._changed.notify_all()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join()

    # -- the decoding thread -----------------------------------------------------------------

    def _run(self) -> None:
        try:
            with open_video(self.video, yuv420p=self.yuv, info=self.info, lens=self.lens) as stream:
                for frame in stream:
                    if not self._put(frame):
                        return
            self._decode_error = stream.decode_error
        except BaseException as exc:  # noqa: BLE001 - raised to both readers when they reach it
            self._error = exc
        finally:
            with self._changed:
                self._ended = True
                self._changed.notify_all()

    def _put(self, frame: np.ndarray) -> bool:
        """Keep the next frame once there is room (False: stopped)."""
        with self._changed:
            while not self._room():
                if self._stopped or self._halt:
                    return False
                if self._spill is None and self._tracking_starved() and self._starved():
                    # The circle the module docstring describes: the render reads a decode of its own from here on.
                    self._spill = self._decoded
                    self._changed.notify_all()
                    continue
                self._changed.wait(WAIT_SLICE)
            if self._stopped or self._halt:
                return False
            self._frames[self._decoded] = frame
            self._decoded += 1
            self.peak = max(self.peak, len(self._frames))
            self._changed.notify_all()
            return True

    def _room(self) -> bool:
        if self._spill is None:
            return len(self._frames) < self.capacity
        return self._decoded - max(self._tracked, self._spill) < READ_AHEAD

    def _drop(self, k: int) -> None:
        """Forget frame ``k`` once neither reader needs it (called with the lock held)."""
        for_render = self._rendered <= k and (self._spill is None or k < self._spill)
        if not for_render and self._tracked > k:
            self._frames.pop(k, None)
            self._changed.notify_all()

    # -- the tracking's side -----------------------------------------------------------------

    def tracking(self, gate: Gate) -> VideoStream:
        """A tracking attempt's frames from the first, as ``open_video(video, width, gray=True)``
        gives them (``track_video``'s ``source``)."""
        with self._changed:
            # The render holds its first frame until the mask has settled (module docstring), so
            # a tracking pass that starts again finds the ring as the first one did.
            if self._rendered > 0:
                raise RuntimeError("a tracking pass started again after the render began")
            again = self._decoded > 0 and 0 not in self._frames
        if again:  # none kept for the render (--smoothing gaussian): decoded again from the first frame
            if self._spill != 0:
                raise RuntimeError("the ring lost frames the render has still to read")
            self._decode_again()
        with self._changed:
            self._tracked = 0

        def frames() -> Generator[np.ndarray]:
            yield from self._tracking_frames(gate)
            view.decode_error = self._decode_error  # (the decode's end accounted for again, as open_video's is)

        reduced = frames()
        view = VideoStream(replace(self.info, size=self.tracking_size), reduced, reduced.close)
        return view

    def _decode_again(self) -> None:
        """Stop the decoding thread and start another from the first frame (the ring empty)."""
        with self._changed:
            self._halt = True
            self._changed.notify_all()
        self._thread.join()
        with self._changed:
            self._frames.clear()
            self._decoded, self._ended, self._error, self._decode_error, self._halt = 0, False, None, None, False
        self._thread = threading.Thread(target=self._run, name="mosaic-decode", daemon=True)
        self._thread.start()

    def _tracking_frames(self, gate: Gate) -> Iterator[np.ndarray]:
        k = 0
        try:
            while True:
                with self._changed:
                    self._settled = gate.settled
                    frame = self._ready(k)
                    if frame is None:
                        self._changed.wait(WAIT_SLICE)
                if frame is _ENDED:
                    return
                if frame is None:
                    if not gate.settled:
                        gate.poll()  # the detection may have ended: the held pairs go on (or MaskChanged)
                    continue
                yield tracking_gray(self._seen(frame), self.info.source_size, self.tracking_size, self.yuv)
                with self._changed:  # (asked for the next: every pair of the frames before is told)
                    k = self._tracked = k + 1
                    self._drop(k - 1)
        finally:
            with self._changed:
                self._settled = False

    def _seen(self, frame: np.ndarray) -> np.ndarray:
        """The frame as the tracking reads it: through ``undistort`` where it is set (a yuv420p
        frame's luma plane alone: all that :func:`tracking_gray` reads)."""
        if self.undistort is None:
            return frame
        if self.yuv:
            w, h = self.info.source_size
            return self.undistort(frame.reshape(-1)[:w * h].reshape(h, w))
        return self.undistort(np.asarray(frame))

    def _ready(self, k: int) -> Any:
        """Frame ``k`` if it is decoded; ``_ENDED`` if the decode ended before it (its error
        raised); None while it is to come (called with the lock held)."""
        if k < self._decoded:
            return self._frames[k]
        if self._ended:
            if self._error is not None:
                raise self._error
            return _ENDED
        if self._stopped:
            raise Cancelled
        return None

    def _tracking_starved(self) -> bool:
        """Whether the tracking, its mask settled, has told every pair it can from the frames
        decoded and asks for the next (called with the lock held)."""
        return self._settled and self._tracked == self._decoded

    # -- the render's side -------------------------------------------------------------------

    def render_frames(self) -> Iterator[np.ndarray]:
        """Every frame, in order, at full size: from the ring, then (where the ring fell short)
        from a decode of the render's own, started at the first frame the ring did not keep."""
        t = 0
        while True:
            frame: Any = None
            with self._changed:
                while self._spill is None or t < self._spill:
                    frame = self._ready(t)
                    if frame is not None:
                        break
                    self._changed.wait(WAIT_SLICE)
            if frame is _ENDED:
                return
            if frame is None:
                break
            yield frame
            with self._changed:
                t = self._rendered = t + 1
                self._drop(t - 1)
        with open_video(self.video, yuv420p=self.yuv, info=self.info, start=t, lens=self.lens) as stream:
            yield from stream


__all__ = ["FAILED_RUN", "READ_AHEAD", "RING_BYTES", "SharedDecode", "frame_bytes", "ring_frames", "tracking_gray"]
