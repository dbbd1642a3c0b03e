"""The frames overlay detection looks at: about ``count`` of them spread evenly over a clip
or an image folder, read one at a time (:class:`VideoSamples`), at the width
:func:`sample_width` picks."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.overlay.detect import OverlayOptions
from mosaic_cli.video import VideoInfo, probe
from mosaic_cli.video.reader import Decoder, folder_images, frame_at, frames_at, read_image_rgb, scaled_size

# Up to this many frames a clip is decoded once, keeping only the sampled frames; longer ones
# are sampled by seeking (a decoder start and the frames from the last keyframe each: at most
# ``samples`` keyframe intervals decoded, however long the clip).  docs/measurements/stitch.md has the costs.
DECODE_ALL_BELOW = 1000


class VideoSamples:
    """About ``count`` RGB frames spread evenly over ``video`` (a file or an image folder),
    ``width`` wide, read anew on each iteration and yielded one at a time (the same frames each
    time), so that :func:`detect_overlays` holds one frame at full width, never all of them.
    Short clips are decoded once per iteration, piping only the picked frames; long ones are
    sampled by seeking, so the cost does not grow with the clip's length; a folder's images
    are read only when picked, one at a time."""

    def __init__(self, video: str | Path, count: int, width: int, info: VideoInfo | None = None):
        self.video, self.count, self.width = video, count, width
        self.info = info or probe(video)
        self._picks: list[int] | None = None  # a clip of unknown length: its picked frames, once counted

    def __iter__(self) -> Iterator[np.ndarray]:
        info, count, width = self.info, self.count, self.width
        total = info.frame_count
        if info.is_image_folder:
            return _sample_folder(Path(self.video), count, width)
        if total is None or info.duration <= 0:
            if self._picks is None:
                self._picks = _picked_by_decoding(_count_frames(info), count)
            return frames_at(info, self._picks, width)
        if total <= DECODE_ALL_BELOW:
            return frames_at(info, _picked(total, count), width)  # one decoder pass, the picked frames piped
        return _sample_by_seeking(count, width, info)


def sample_frames(video: str | Path, count: int, width: int, info: VideoInfo | None = None) -> list[np.ndarray]:
    """The frames of :class:`VideoSamples`, all held (tests and benchmarks: :func:`frame_mask`
    reads them twice instead, one at a time).  A folder of photos of several sizes gives none
    (the reader refuses it anyway)."""
    frames = list(VideoSamples(video, count, width, info))
    return frames if len({f.shape for f in frames}) <= 1 else []


def sample_width(source_size: tuple[int, int], options: OverlayOptions | None = None) -> int:
    """The width the detector's samples are read at: the source's, scaled down to at most
    ``trace_pixels`` pixels (a portrait 1080x1920 clip: 720 wide), never below ``width``."""
    o = options or OverlayOptions()
    w, h = source_size
    fit = int(w * min(1.0, float(np.sqrt(o.trace_pixels / max(1, w * h)))))
    return min(w, max(fit, o.width))


def _picked(total: int, count: int) -> np.ndarray:
    return np.unique(np.linspace(0, max(0, total - 1), min(count, total)).round().astype(int))


def _sample_folder(folder: Path, count: int, width: int) -> Iterator[np.ndarray]:
    """The picked images, each read at its own size, scaled to ``width`` and yielded before the
    next is read (a folder of 4000x2250 photos holds one of them at a time)."""
    files = folder_images(folder)
    for k in _picked(len(files), count):
        image = read_image_rgb(files[k])
        size = scaled_size((image.shape[1], image.shape[0]), width)
        yield cv2.resize(image, size, interpolation=cv2.INTER_AREA) if size[0] != image.shape[1] else image


def _count_frames(info: VideoInfo) -> int:
    """The frames of a clip whose container does not say, counted by decoding it (tiny, gray)."""
    with Decoder(info, "gray", scaled_size(info.source_size, 16)) as decoder:
        return sum(1 for _ in decoder)


def _picked_by_decoding(total: int, count: int) -> list[int]:
    """The frames an even spread over ``total`` keeps when it is chosen while decoding, without
    knowing the total: every ``step``-th frame, every other kept one dropped (and the step
    doubled) whenever twice ``count`` are held; then ``count`` of those evenly."""
    kept: list[int] = []
    step = 1
    for k in range(total):
        if k % step == 0:
            kept.append(k)
            if len(kept) >= 2 * count:
                kept, step = kept[::2], step * 2
    return kept[:: max(1, len(kept) // count)][:count]


def _sample_by_seeking(count: int, width: int, info: VideoInfo) -> Iterator[np.ndarray]:
    """One decoder start per picked frame, seeking to it: each decodes from the keyframe
    before it, so the cost is bounded by ``count`` keyframe intervals however long the clip."""
    fps = info.fps if info.fps > 0 else 30.0
    for index in _picked(info.frame_count, count):
        # A seek past the last decodable frame (the container's duration can run a little
        # long) steps back a frame or two.
        for back in (0, 1, 2):
            frame = frame_at(info, max(0.0, (index - back - 0.25) / fps), width)  # the first frame at or after
            if frame is not None:
                yield frame
                break


__all__ = ["DECODE_ALL_BELOW", "VideoSamples", "sample_frames", "sample_width"]
