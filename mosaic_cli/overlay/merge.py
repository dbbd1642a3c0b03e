"""The use mask of a video (uint8, full resolution, 255 = ground to use): the user's ``--mask``
file merged with the overlays detected in it (:func:`frame_mask`), or, for a live input, the
file's alone (:func:`live_mask`); and ``--mask``'s options.

While the overlays are looked for, the mask is a :class:`PendingMask` (:func:`frame_mask_pending`):
what is known of it at once (the file's) and, in a thread of its own, the detection; tracking
starts with the former and settles on the latter (:mod:`mosaic_cli.overlay.speculate`)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.geometry.lens import Undistortion
from mosaic_cli.mask import load_mask
from mosaic_cli.overlay.detect import Detection, OverlayOptions, detect_overlays
from mosaic_cli.overlay.samples import VideoSamples, sample_width
from mosaic_cli.progress import note
from mosaic_cli.video import VideoInfo, probe
from mosaic_cli.video.lens_filter import ImageFilter

T = TypeVar("T")

# Said once for a live input (stdin, a URL): frames cannot be sampled ahead of the stream.
LIVE_DETECTION_SKIPPED = "overlay detection is skipped for a live input (it samples frames ahead of the stream)"


@dataclass
class MaskOptions:
    """``--mask FILE`` (white = use) and ``--overlay-detect/--no-overlay-detect``."""

    file: str | Path | None = None
    detect: bool = True
    # The file's black areas are grown by this many px: H.264 smears an overlay's colour
    # beyond its edge (chroma at half resolution; up to 1.9 px on the simulator's flights).
    file_margin: int = 2
    overlay: OverlayOptions = field(default_factory=OverlayOptions)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """The ``--mask`` path (what the image holds is read against the video: :func:`load_mask`)."""
        if self.file is not None:
            p = Path(self.file)
            if not p.exists():
                raise BadInput(f"--mask {p}: no such file")
            if p.is_dir():
                raise BadInput(f"--mask {p}: is a folder, not an image")
        if self.file_margin < 0:
            raise BadInput(f"the --mask margin must be 0 or more pixels, got {self.file_margin}")


@dataclass
class FrameMask:
    use: np.ndarray | None  # (h, w) uint8 at the source size, 255 = use; None: use everything
    detection: Detection | None = None
    from_file: bool = False
    seconds: float = 0.0

    @property
    def excluded(self) -> float:
        return 0.0 if self.use is None else float(np.count_nonzero(self.use == 0)) / self.use.size

    def describe(self) -> str:
        """One line for the user: what is kept out of estimation and the panorama, and why."""
        if self.use is None:
            return ""
        what = []
        if self.detection is not None and self.detection.use is not None:
            found = []
            if self.detection.static_fraction > 0:
                found.append("static overlays")
            if self.detection.letterbox.any:
                found.append("letterbox bars")
            what.append(" and ".join(found) + " detected")
        if self.from_file:
            what.append("--mask")
        return f"{100 * self.excluded:.1f}% of the frame masked ({', '.join(what)})"

    def to_json(self) -> dict:
        d = self.detection
        return {
            "excluded": round(self.excluded, 4),
            "from_file": self.from_file,
            "detected": None if d is None else {
                "static_fraction": round(d.static_fraction, 4),
                "letterbox": [d.letterbox.top, d.letterbox.bottom, d.letterbox.left, d.letterbox.right],
                "rejected_as_hovering": d.rejected,
                "samples": d.samples,
                "too_few_frames": d.too_few,
            },
            "seconds": round(self.seconds, 3),
        }


def check_mask_file(mask: MaskOptions, info: VideoInfo | None) -> None:
    """A bad ``--mask`` image fails before any work (a network's weights, a decode), against the
    input's probe ``info``; a live input (None: no probe) has its mask checked when its first
    frame gives the size."""
    if mask.file is None or info is None:
        return
    load_mask(mask.file, info.source_size)


def frame_mask(video: str | Path, options: MaskOptions | None = None, info: VideoInfo | None = None,
               show_progress: bool = False, lens: ImageFilter | None = None) -> FrameMask:
    """The merged use mask of ``video``: the ``--mask`` file's, and the detector's unless off.
    The video and the file are checked before any frame is decoded or progress shown.  ``lens``:
    ``--lens``'s filter on ``video``'s frames, the mask then the undistorted frame's (the file's
    and the detector's both carried into it: :func:`_file_mask`, :func:`_detected`)."""
    options = options or MaskOptions()
    clock = time.perf_counter()
    info = info or probe(video)
    return _detected(video, options, info, _file_mask(options, info.source_size, lens), show_progress, clock, lens=lens)


def _detected(video: str | Path, options: MaskOptions, info: VideoInfo, use: np.ndarray | None, show_progress: bool,
              clock: float, stop: threading.Event | None = None, lens: ImageFilter | None = None) -> FrameMask:
    """``use`` (the file's mask, or None) merged with the overlays detected in ``video`` unless
    detection is off; its ``seconds`` counted from ``clock``.  ``stop``, once set, ends the
    detection at its next frame with :class:`DetectionStopped`.

    The overlays are looked for in the frames as decoded, where they were burned in: sharp,
    and still from frame to frame.  Where ``lens`` undistorts the frames, the mask found is
    carried into the undistorted frame as a ``--mask`` file's is: looked for in the undistorted
    frames instead, a logo in a corner (stretched, resampled) left 12% of its pixels unmasked
    on a simulated 960x540 flight with k1 -0.10, every one masked this way."""
    detection = None
    if options.detect:
        width = sample_width(info.source_size, options.overlay)
        samples: Iterable[np.ndarray] = VideoSamples(video, options.overlay.samples, width, info)
        if stop is not None:
            samples = _Stoppable(samples, stop)
        if show_progress:
            from mosaic_cli.progress import progress_task

            with progress_task("overlays", None, unit="fr/s") as advance:
                detection = detect_overlays(samples, info.source_size, options.overlay)
                advance(detection.samples, status=f"{100 * detection.excluded:.1f}% masked")  # frames sampled
        else:
            detection = detect_overlays(samples, info.source_size, options.overlay)
        if detection.use is not None:
            found = lens.mask(detection.use) if isinstance(lens, Undistortion) else detection.use
            use = found if use is None else np.minimum(use, found)
    return FrameMask(use, detection, options.file is not None, time.perf_counter() - clock)


class DetectionStopped(Exception):
    """The detection was stopped (:meth:`PendingMask.cancel`): its result is not wanted."""


class _Stoppable:
    """``samples`` (read anew on each iteration, as :class:`VideoSamples`), ending with
    :class:`DetectionStopped` before the next frame once ``stop`` is set: the decoder is closed
    there and then, not after the detection's last frame."""

    def __init__(self, samples: Iterable[np.ndarray], stop: threading.Event):
        self.samples, self.stop = samples, stop

    def __iter__(self) -> Iterator[np.ndarray]:
        frames = iter(self.samples)
        try:
            while not self.stop.is_set():
                try:
                    frame = next(frames)
                except StopIteration:
                    return
                yield frame
            raise DetectionStopped("overlay detection stopped")
        finally:
            close = getattr(frames, "close", None)
            if close is not None:
                close()  # a generator's decoder (an ffmpeg process) ends now


def live_mask(options: MaskOptions | None, full_size: tuple[int, int], show_progress: bool = True,
              lens: ImageFilter | None = None) -> FrameMask:
    """The use mask of a live input: the ``--mask`` file's only (in the undistorted frame's
    pixels where ``lens``, ``--lens``'s filter, undistorts the input's frames).  Detection
    samples frames spread over the whole clip before the first is estimated, which a stream does
    not have; when it was asked for (the default), one line says it is skipped."""
    options = options or MaskOptions()
    clock = time.perf_counter()
    if options.detect and show_progress:
        note(LIVE_DETECTION_SKIPPED + ("; --mask applies" if options.file is not None else "; use --mask to exclude overlays"))
    return FrameMask(_file_mask(options, full_size, lens), None, options.file is not None, time.perf_counter() - clock)


def _file_mask(options: MaskOptions, full_size: tuple[int, int], lens: ImageFilter | None = None) -> np.ndarray | None:
    """The ``--mask`` file's use mask at ``full_size``, its black areas grown by the margin; where
    ``lens`` (``--lens``'s filter) undistorts the frames, carried from the distorted frame's
    pixels, which it is drawn in, into the undistorted frame's (the margin grown first: H.264's
    smear is the distorted frame's)."""
    use = load_mask(options.file, full_size) if options.file is not None else None
    if use is not None and options.file_margin > 0:
        r = options.file_margin
        use = cv2.erode(use, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)),
                        borderType=cv2.BORDER_CONSTANT, borderValue=255)
    if use is not None and isinstance(lens, Undistortion):
        use = lens.mask(use)
    return use


class PendingMask:
    """A video's use mask while its overlays are still being looked for (:func:`frame_mask_pending`).

    ``known``: the mask so far, (h, w) uint8 at the source size or None: the ``--mask`` file's,
    which the final one can only add to.  :meth:`done` says whether the detection has ended;
    :meth:`result` waits for it and gives the merged :class:`FrameMask` (or raises the
    detection's error).  :meth:`cancel` stops a detection whose result is no longer wanted (the
    run failed); :meth:`close` (also the context manager's exit) stops it and joins its thread,
    so that no decoder outlives the command.  Thread-safe: the tracking may wait on it in a
    thread of its own while the caller cancels it."""

    def __init__(self, known: np.ndarray | None, settled: FrameMask | None = None):
        self.known = known
        self._future: Future[FrameMask] = Future()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if settled is not None:
            self._future.set_result(settled)

    @classmethod
    def settled(cls, mask: FrameMask) -> PendingMask:
        """A mask known from the start (detection off, or the caller's own): done at once."""
        return cls(mask.use, mask)

    def start(self, detect: Callable[[threading.Event], FrameMask]) -> None:
        """Run ``detect(stop)`` in a thread of its own; its result or error is :meth:`result`'s."""
        def run() -> None:
            try:
                self._future.set_result(detect(self._stop))
            except BaseException as exc:  # handed to whoever waits on result()
                self._future.set_exception(exc)

        self._thread = threading.Thread(target=run, name="mosaic-overlays", daemon=True)
        self._thread.start()

    def done(self) -> bool:
        return self._future.done()

    def result(self) -> FrameMask:
        """The merged mask, once the detection has ended; its error if it failed."""
        return self._future.result()

    def cancel(self) -> None:
        """Stop the detection at its next frame (:class:`DetectionStopped` for whoever waits);
        nothing if it has ended."""
        self._stop.set()

    def close(self) -> None:
        """Stop the detection if it still runs, and wait for its thread to end."""
        self.cancel()
        if self._thread is not None:
            self._thread.join()

    def __enter__(self) -> PendingMask:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def frame_mask_pending(build: Callable[[], T], video: str | Path, options: MaskOptions | None = None,
                       info: VideoInfo | None = None, show_progress: bool = False,
                       lens: ImageFilter | None = None) -> tuple[PendingMask, T]:
    """:func:`frame_mask` as a :class:`PendingMask`, and ``build()``: the detection runs in a
    thread of its own (its frames decoded by ffmpeg in a process of its own) while ``build``
    (torch's import, the weights, the int8 network: a second or two) runs in the caller's; this
    returns once ``build`` has, the detection maybe still going (the caller closes the mask:
    ``with pending:``).  The ``--mask`` file is read first, in the caller's thread: a bad one
    fails before any other work.  An error of the build is raised once the detection has ended,
    and the detection's own error first, as :func:`frame_mask_while` always did.  With a
    progress bar, run inside :func:`mosaic_cli.progress.progress_group` when other bars will
    show while the detection runs (rich shows one display at a time).  ``lens``: as :func:`frame_mask`'s."""
    options = options or MaskOptions()
    clock = time.perf_counter()
    info = info or probe(video)
    known = _file_mask(options, info.source_size, lens)
    if not options.detect:
        pending = PendingMask.settled(FrameMask(known, None, options.file is not None, time.perf_counter() - clock))
    else:
        pending = PendingMask(known)
        pending.start(lambda stop: _detected(video, options, info, known, show_progress, clock, stop, lens))
    try:
        built = build()
    except Exception:
        with pending:
            pending.result()  # the detection's error first (chained to the build's)
        raise
    except BaseException:  # Ctrl-C: the detection is not waited for
        pending.close()
        raise
    return pending, built


def frame_mask_while(build: Callable[[], T], video: str | Path, options: MaskOptions | None = None,
                     info: VideoInfo | None = None, show_progress: bool = False,
                     lens: ImageFilter | None = None) -> tuple[FrameMask, T]:
    """:func:`frame_mask`, and ``build()`` at the same time (:func:`frame_mask_pending`), both
    waited for: for a caller that needs the mask before its first frame (JSON Lines written as
    the pairs are estimated).  An error of either is raised once both have ended."""
    pending, built = frame_mask_pending(build, video, options, info, show_progress, lens)
    with pending:
        return pending.result(), built


__all__ = ["LIVE_DETECTION_SKIPPED", "DetectionStopped", "FrameMask", "MaskOptions", "PendingMask", "frame_mask", "frame_mask_pending",
           "frame_mask_while", "live_mask"]
