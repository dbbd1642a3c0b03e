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
from mosaic_cli.video.decode import REFERENCE_SKIPPING_CODECS
from mosaic_cli.video.reader import Decoder, folder_images, frame_at, frames_at, read_image_rgb, scaled_size

# What a picked frame costs, in frames decoded: a clip is sampled at its keyframes where they
# lie as close together as the picks (one frame decoded each, no decoder to start), else the
# cheaper of decoding it once, piping only the picked frames, and one seek per picked frame
# (a decoder start, worth about this many frames, then the frames from the keyframe before it).
# CHANGELOG.md (speed, 2026-11-27) has the costs.
SEEK_START_FRAMES = 30
DECODE_ALL_BELOW = 1000  # frames: with no keyframe index, a clip this short is decoded once
# One pass decodes only the frames others refer to (H.264, HEVC), and each pick becomes the first
# of those at or after it (0-1 frames later on x264 clips): 58-65% of a full decode's CPU.
# Only where the picks lie at least NEAR_SPACING frames apart: closer ones would share reference
# frames (x264 puts up to 3 B-frames between them), and so short a clip decodes fast anyway.
REFERENCE_DECODE_SHARE = 0.6
NEAR_SPACING = 8


class VideoSamples:
    """About ``count`` RGB frames spread evenly over ``video`` (a file or an image folder),
    ``width`` wide, read anew on each iteration and yielded one at a time (the same frames each
    time), so that :func:`detect_overlays` holds one frame at full width, never all of them.
    Short clips are decoded once per iteration, piping only the picked frames (H.264 and HEVC:
    the first reference frame at or after each, the others not decoded); long ones are
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
            return frames_at(info, self._picks, width, near=_far_apart(self._picks))
        picks = _picked(total, count)
        keys = keyframe_indices(info)
        if keys is None:
            seek = total > DECODE_ALL_BELOW
        else:
            at_keys = _nearest_keyframes(picks, keys, total / max(1, len(picks)))
            if at_keys is not None:
                return _keyframes_at(info, at_keys, width)
            share = _decoding_share(picks, info)
            seek = _seeking_cost(picks, keys, share) < share * float(picks[-1] + 1)  # against one pass up to the last pick
        if seek:
            return _sample_by_seeking(count, width, info)
        return frames_at(info, picks, width, near=_far_apart(picks))  # one decoder pass, the picked frames piped


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


def keyframe_indices(info: VideoInfo) -> list[int] | None:
    """The frame indices of the video's keyframes, read from its packets (demuxed, not decoded);
    None when libav cannot read them."""
    import av  # PyAV, loaded with the first video probed

    fps = info.fps if info.fps > 0 else 30.0
    try:
        with av.open(info.path, metadata_errors="replace") as container:
            video = container.streams[info.stream_index]
            times = [(float(packet.pts * video.time_base), packet.is_keyframe)
                     for packet in container.demux(video) if packet.pts is not None and packet.size]
    except (av.error.FFmpegError, OSError, ValueError, IndexError):
        return None
    if not times:
        return None
    first = min(t for t, _ in times)
    return sorted({int(round((t - first) * fps)) for t, key in times if key})


def _nearest_keyframes(picks: np.ndarray, keys: list[int], spacing: float) -> list[int] | None:
    """For each pick the nearest keyframe, when every pick has one within the picks' spacing
    and nine in ten of them are different keyframes (the samples stay about as many and as
    evenly spread); else None."""
    keyed = np.asarray(keys)
    nearest = keyed[np.abs(keyed[None, :] - picks[:, None]).argmin(axis=1)]
    distinct = sorted(set(nearest.tolist()))
    if np.abs(nearest - picks).max() > spacing or len(distinct) < 0.9 * len(picks):
        return None
    return distinct


def _far_apart(picks) -> bool:
    return len(picks) < 2 or float(np.min(np.diff(picks))) >= NEAR_SPACING


def _decoding_share(picks: np.ndarray, info: VideoInfo) -> float:
    """What decoding a frame on the way to the picks costs, against a full decode's."""
    return REFERENCE_DECODE_SHARE if info.video_codec in REFERENCE_SKIPPING_CODECS and _far_apart(picks) else 1.0


def _seeking_cost(picks: np.ndarray, keys: list[int], share: float = 1.0) -> float:
    """Frames decoded (a decoder start counted as :data:`SEEK_START_FRAMES`) sampling by seeking,
    each frame on the way counted as ``share`` of one."""
    keyed = np.asarray(keys)
    before = keyed[np.clip(np.searchsorted(keyed, picks, side="right") - 1, 0, None)]
    return float(share * np.sum(picks - before + 1) + SEEK_START_FRAMES * len(picks))


def _keyframes_at(info: VideoInfo, indices: list[int], width: int) -> Iterator[np.ndarray]:
    """The keyframes at ``indices``, upright, ``width`` wide: a seek and one frame decoded each,
    in this process."""
    import av  # PyAV, loaded with the first video probed

    fps = info.fps if info.fps > 0 else 30.0
    size = scaled_size(info.source_size, width)
    turn = {90: cv2.ROTATE_90_CLOCKWISE, 180: cv2.ROTATE_180, 270: cv2.ROTATE_90_COUNTERCLOCKWISE}.get(info.rotation)
    with av.open(info.path, metadata_errors="replace") as container:
        video = container.streams[info.stream_index]
        start = None
        for index in indices:
            if start is None:
                container.seek(0, stream=video)
                start = next(container.decode(video)).time or 0.0
            container.seek(int((start + index / fps) / video.time_base), stream=video, backward=True)
            frame = next(container.decode(video), None)
            if frame is None:
                continue
            rgb = frame.to_ndarray(format="rgb24")
            if turn is not None:
                rgb = cv2.rotate(rgb, turn)
            yield cv2.resize(rgb, size, interpolation=cv2.INTER_AREA) if size != (rgb.shape[1], rgb.shape[0]) else rgb


def _sample_by_seeking(count: int, width: int, info: VideoInfo) -> Iterator[np.ndarray]:
    """One decoder start per picked frame, seeking to it: each decodes from the keyframe
    before it, so the cost is bounded by ``count`` keyframe intervals however long the clip."""
    fps = info.fps if info.fps > 0 else 30.0
    picks = _picked(info.frame_count, count)
    near = _far_apart(picks)
    for index in picks:
        # A seek past the last decodable frame (the container's duration can run a little
        # long) steps back a frame or two.
        for back in (0, 1, 2):
            frame = frame_at(info, max(0.0, (index - back - 0.25) / fps), width, near=near)  # the first (reference) frame at or after
            if frame is not None:
                yield frame
                break


__all__ = ["DECODE_ALL_BELOW", "SEEK_START_FRAMES", "VideoSamples", "keyframe_indices", "sample_frames", "sample_width"]
