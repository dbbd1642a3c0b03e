"""What a video holds, known before decoding it: :class:`VideoInfo`, with its other streams as
:class:`StreamMeta`; :func:`scaled_size`.  Its frames, read one at a time, are a
:class:`~.stream.VideoStream`."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class StreamMeta:
    """A stream of the file other than the video read (audio, subtitles, data)."""

    index: int  # in the file, as ffmpeg's -map 0:INDEX counts
    kind: str  # "audio", "subtitle", "data", "attachment", "video"
    codec: str  # libav's codec name ("aac", "mov_text", "klv", "bin_data", ...; "none" when unknown)
    tag: str = ""  # the container's codec tag (fourcc), e.g. "KLVA"


@dataclass(frozen=True)
class VideoInfo:
    """What is known about a video before decoding it.

    ``size`` is the (w, h) of the frames the reader yields (after rotation and any downscale);
    ``source_size`` the (w, h) at full resolution after rotation, which is the resolution every
    homography mosaic reports is expressed in.  ``frame_count`` is the container's count (the
    smaller of its frame count and its duration times the rate: an edit list may leave frames
    out) or an estimate from the duration (None when unknown).  ``rotation`` is the clockwise
    turn (0, 90, 180, 270) the file asks for on display; frames are always yielded upright."""

    path: str
    size: tuple[int, int]
    source_size: tuple[int, int]
    fps: float
    frame_count: int | None
    duration: float
    rotation: int = 0
    audio_codec: str | None = None
    is_image_folder: bool = False
    damage: str | None = None  # libav's complaint when the end of the file does not decode
    stream_index: int | None = None  # of the video stream read, in the file
    streams: tuple[StreamMeta, ...] = ()  # the file's other streams, in file order
    video_codec: str | None = None  # libav's name of the video stream's codec ("h264", "hevc", ...)
    # The first decoded frame's pixel format ("yuv420p", ...) and libav's codes of its colour
    # matrix (AVColorSpace: 1 BT.709, 2 unspecified, 5 and 6 BT.601) and range (AVColorRange:
    # 0 unspecified, 1 limited, 2 full); None where not known (image folders).
    pixel_format: str | None = None
    color_matrix: int | None = None
    color_range: int | None = None

    @property
    def has_audio(self) -> bool:
        return self.audio_codec is not None


def scaled_size(size: tuple[int, int], width: int | None) -> tuple[int, int]:
    """(w, h) resized to ``width`` keeping the aspect ratio, height rounded to the nearest pixel
    (the same rule as the estimators' working size, so frames need no second resize).
    ``None`` or a larger width keeps ``size``."""
    w, h = size
    if width is None or width >= w:
        return (w, h)
    return (int(width), max(1, int(round(h * width / w))))
