"""Decoding, the table of contents: :func:`open_video` streams a file's (or an image folder's)
frames; :func:`Decoder` gives the decoder under it and under :func:`frames_at` and
:func:`frame_at` (picked frames, a frame at a time), of the backend :mod:`.backend` picks.

* :mod:`.pixels`: the pixel formats a decoder yields, the frames converted here from yuv420p
  (:class:`LumaRGB`, :class:`YuvFrame`), :func:`gray_at`;
* :mod:`.ffmpeg_decoder`: :class:`FfmpegDecoder`, the bundled ffmpeg on a pipe (the default);
* :mod:`.pyav_decoder`: :class:`PyAVDecoder`, libav in this process where there is no ffmpeg
  binary, a few frames ahead on a thread (:mod:`.read_ahead`);
* :mod:`.lens_filter`: ``--lens``, the frames seen through the lens's undistortion (``lens=``).

The names of those modules that callers import from here are re-exported."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from mosaic_cli.video.ffmpeg_decoder import FfmpegDecoder
from mosaic_cli.video.folders import open_folder
from mosaic_cli.video.info import VideoInfo, scaled_size
from mosaic_cli.video.lens_filter import ImageFilter, filter_frame, filtered
from mosaic_cli.video.pixels import (
    CONVERTED_HERE,
    PIXELS,
    TO_BT601,
    LumaRGB,
    YuvFrame,
    gray_at,
    rgb_from_yuv420p,
    yuv420p_bytes,
)
from mosaic_cli.video.policy import refuse_damaged
from mosaic_cli.video.probe import probe
from mosaic_cli.video.pyav_decoder import PyAVDecoder
from mosaic_cli.video.read_ahead import ReadAhead
from mosaic_cli.video.stream import VideoStream

__all__ = [
    "CONVERTED_HERE",
    "PIXELS",
    "REFERENCE_SKIPPING_CODECS",
    "TO_BT601",
    "Decoder",
    "FfmpegDecoder",
    "ImageFilter",
    "LumaRGB",
    "PyAVDecoder",
    "ReadAhead",
    "YuvFrame",
    "filter_frame",
    "frame_at",
    "frames_at",
    "gray_at",
    "open_video",
    "rgb_from_yuv420p",
    "yuv420p_bytes",
]

REFERENCE_SKIPPING_CODECS = ("h264", "hevc")  # whose decoders skip unreferenced frames exactly (frames_at)


def Decoder(info: VideoInfo, pixels: str = "rgb", size: tuple[int, int] | None = None, **request) -> FfmpegDecoder | PyAVDecoder:
    """The decoder of the backend :func:`~mosaic_cli.video.backend.video_backend` picks: an
    :class:`FfmpegDecoder` or a :class:`PyAVDecoder`, which take the same arguments."""
    from mosaic_cli.video.backend import video_backend

    kind = PyAVDecoder if video_backend() == "pyav" else FfmpegDecoder
    return kind(info, pixels, size, **request)


def open_video(
    path: str | Path,
    width: int | None = None,
    gray: bool = False,
    fps: float | None = None,
    start: int = 0,
    *,
    yuv420p: bool = False,
    info: VideoInfo | None = None,
    lazy_rgb: bool = False,
    lens: ImageFilter | None = None,
) -> VideoStream:
    """Open ``path`` (a video file or a folder of numbered images) as a stream of frames.

    ``width`` downscales inside the decoder (aspect kept); ``gray`` yields (h, w) uint8 frames
    instead of RGB; ``yuv420p`` (video files of even size, no ``width``) the planes as ffmpeg
    decodes them, (h * 3 // 2, w), with no conversion; ``fps`` overrides the frame rate of an
    image folder; ``start`` skips frames.  ``info``: the file's :func:`probe`, when the caller
    has it (else it is probed here).  ``lazy_rgb``: full-size RGB frames that are converted here
    come as :class:`YuvFrame`, converted only when their pixels are asked for.  ``lens``: each
    frame through this filter (``--lens``: :mod:`.lens_filter`); None: the frames as decoded
    (``stabilize --keep-lens`` renders the lens's own frames).
    """
    p = Path(path)
    if p.is_dir():
        if yuv420p:
            raise ValueError("yuv420p frames are read from video files only")
        stream = open_folder(p, width, fps, gray)
        if start:
            stream._frames = (f for k, f in enumerate(stream._frames) if k >= start)
        stream._frames = filtered(stream._frames, stream.info.size, False, lens)
        return stream
    if info is None:
        info = probe(p)
    else:
        refuse_damaged(info)  # probed before the command's --strict took effect
    pixels = "yuv420p" if yuv420p else "gray" if gray else "rgb"
    size = scaled_size(info.source_size, width)  # (yuv420p: the Decoder refuses a downscale)
    info = replace(info, size=size)
    decoder = Decoder(info, pixels, size, start=int(start) if start else None, lazy_rgb=lazy_rgb)

    def frames() -> Iterator[np.ndarray]:
        yield from filtered(iter(decoder), size, yuv420p, lens)
        stream.decode_error = decoder.error

    stream = VideoStream(info, frames(), decoder.close)
    stream.frames_skipped = int(start)  # (a start past the end reads no frame, and says so)
    return stream


def frames_at(info: VideoInfo, indices: Sequence[int], width: int | None = None, near: bool = False, *,
              lens: ImageFilter | None = None) -> Iterator[np.ndarray]:
    """The RGB frames of ``indices`` (sorted), in one decoder pass that converts and pipes only
    those (ffmpeg's select filter), yielded as they come; fewer when the file ends first.

    ``near``: for each index, the first *reference* frame at or after its time instead, in a pass
    that does not decode the others (H.264 and HEVC: the frames are those of a full decode, bit
    for bit; about half of an x264 clip's frames, 40% less decoding).  Other codecs: exact.
    ``lens``: as :func:`open_video`'s."""
    if len(indices) == 0:
        return
    if near and info.video_codec in REFERENCE_SKIPPING_CODECS:
        fps = info.fps if info.fps > 0 else 30.0
        # Each index's time less a quarter frame: its frame's time, whatever the rounding.
        request: dict = {"near_times": [(int(k) - 0.25) / fps for k in indices], "references_only": True}
    else:
        request = {"picks": [int(k) for k in indices]}
    with Decoder(info, "rgb", scaled_size(info.source_size, width), **request) as decoder:
        yield from filtered(iter(decoder), scaled_size(info.source_size, width), False, lens)


def frame_at(info: VideoInfo, seconds: float, width: int | None = None, near: bool = False) -> np.ndarray | None:
    """The first RGB frame at or after ``seconds`` (ffmpeg seeks to the keyframe before it and
    decodes from there), None when there is none; ``near``: the first reference frame, the
    others not decoded on the way (as :func:`frames_at`)."""
    references_only = near and info.video_codec in REFERENCE_SKIPPING_CODECS
    with Decoder(info, "rgb", scaled_size(info.source_size, width), seek=seconds, frames=1, references_only=references_only) as decoder:
        return next(iter(decoder), None)
