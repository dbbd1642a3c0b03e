"""The use mask of a video (uint8, full resolution, 255 = ground to use): the user's ``--mask``
file merged with the overlays detected in it (:func:`frame_mask`), or, for a live input, the
file's alone (:func:`live_mask`); and ``--mask``'s options."""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.mask import load_mask
from mosaic_cli.overlay.detect import Detection, OverlayOptions, detect_overlays
from mosaic_cli.overlay.samples import VideoSamples, sample_width
from mosaic_cli.progress import note
from mosaic_cli.video import VideoInfo, probe

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


def frame_mask(video: str | Path, options: MaskOptions | None = None, info: VideoInfo | None = None,
               show_progress: bool = False) -> FrameMask:
    """The merged use mask of ``video``: the ``--mask`` file's, and the detector's unless off.
    The video and the file are checked before any frame is decoded or progress shown."""
    options = options or MaskOptions()
    clock = time.perf_counter()
    info = info or probe(video)
    use = _file_mask(options, info.source_size)
    detection = None
    if options.detect:
        width = sample_width(info.source_size, options.overlay)
        if show_progress:
            from mosaic_cli.progress import progress_task

            with progress_task("overlays", None, unit="fr/s") as advance:
                detection = detect_overlays(VideoSamples(video, options.overlay.samples, width, info), info.source_size, options.overlay)
                advance(detection.samples, status=f"{100 * detection.excluded:.1f}% masked")  # frames sampled
        else:
            detection = detect_overlays(VideoSamples(video, options.overlay.samples, width, info), info.source_size, options.overlay)
        if detection.use is not None:
            use = detection.use if use is None else np.minimum(use, detection.use)
    return FrameMask(use, detection, options.file is not None, time.perf_counter() - clock)


def live_mask(options: MaskOptions | None, full_size: tuple[int, int], show_progress: bool = True) -> FrameMask:
    """The use mask of a live input: the ``--mask`` file's only.  Detection samples frames
    spread over the whole clip before the first is estimated, which a stream does not have;
    when it was asked for (the default), one line says it is skipped."""
    options = options or MaskOptions()
    clock = time.perf_counter()
    if options.detect and show_progress:
        note(LIVE_DETECTION_SKIPPED + ("; --mask applies" if options.file is not None else "; use --mask to exclude overlays"))
    return FrameMask(_file_mask(options, full_size), None, options.file is not None, time.perf_counter() - clock)


def _file_mask(options: MaskOptions, full_size: tuple[int, int]) -> np.ndarray | None:
    """The ``--mask`` file's use mask at ``full_size``, its black areas grown by the margin."""
    use = load_mask(options.file, full_size) if options.file is not None else None
    if use is not None and options.file_margin > 0:
        r = options.file_margin
        use = cv2.erode(use, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)),
                        borderType=cv2.BORDER_CONSTANT, borderValue=255)
    return use


def frame_mask_while(build: Callable[[], T], video: str | Path, options: MaskOptions | None = None,
                     info: VideoInfo | None = None, show_progress: bool = False) -> tuple[FrameMask, T]:
    """:func:`frame_mask`, and ``build()`` at the same time in a thread of its own: the
    detector's frames are decoded by ffmpeg in a process of its own, so building the estimator
    (torch's import, the weights, the int8 network: a second or two) costs no time beside it.
    An error of either is raised once both have ended."""
    with ThreadPoolExecutor(1, thread_name_prefix="mosaic-build") as pool:
        built = pool.submit(build)
        mask = frame_mask(video, options, info, show_progress)
        return mask, built.result()


__all__ = ["LIVE_DETECTION_SKIPPED", "FrameMask", "MaskOptions", "frame_mask", "frame_mask_while", "live_mask"]
