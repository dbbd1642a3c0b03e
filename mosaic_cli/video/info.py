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


SAME_SHAPE = 0.01  # images whose aspect ratios differ by less than this are of one shape


# EXIF Orientation (tag 274): how a photo's stored pixels are turned to be shown, as OpenCV reads
# them.  Those that swap its width and height; and the plain turns, in degrees clockwise (the
# others, 2, 4, 5 and 7, also mirror it).
EXIF_ORIENTATION = 0x0112
QUARTER_TURNS = (5, 6, 7, 8)
TURN_DEGREES = {1: 0.0, 3: 180.0, 6: 90.0, 8: 270.0}


def shown_size(stored: tuple[int, int], orientation: int) -> tuple[int, int]:
    """(w, h) of a photo stored ``stored`` (w, h) as shown, its EXIF ``orientation`` applied."""
    return (stored[1], stored[0]) if orientation in QUARTER_TURNS else stored


@dataclass(frozen=True)
class PhotoFit:
    """A photo of another size than its folder's first (another camera), read into the first's
    frame: scaled by ``scale`` (aspect kept) to fit it whole, centred; a photo of another shape
    (4:3 among 16:9, portrait among landscape) leaves the rest of the frame empty.  Its
    homographies are those of that frame; ``box`` (x, y, w, h, frame pixels at the source size)
    is where its pixels lie."""

    index: int  # position in the folder
    name: str
    photo_size: tuple[int, int]  # (w, h) as the photo is displayed (EXIF orientation applied)
    scale: float
    box: tuple[int, int, int, int]

    @staticmethod
    def into(frame: tuple[int, int], photo: tuple[int, int], index: int = 0, name: str = "") -> PhotoFit:
        scale = min(frame[0] / photo[0], frame[1] / photo[1])
        w, h = min(frame[0], max(1, round(photo[0] * scale))), min(frame[1], max(1, round(photo[1] * scale)))
        if abs(photo[0] * frame[1] / (photo[1] * frame[0]) - 1.0) <= SAME_SHAPE:
            w, h = frame  # the frame's shape at another size: resized to fill it
        return PhotoFit(index, name, photo, scale, ((frame[0] - w) // 2, (frame[1] - h) // 2, w, h))

    def fills(self, frame: tuple[int, int]) -> bool:
        return self.box == (0, 0, frame[0], frame[1])

    def region(self, size: tuple[int, int], source_size: tuple[int, int]) -> tuple[slice, slice]:
        """(rows, columns) of a frame read at ``size`` (``source_size`` scaled) that hold the
        photo: the one rounding that places its pixels (video/folders.py) and finds them again."""
        s = size[0] / source_size[0]
        x, y, w, h = self.box
        x0, y0 = round(x * s), round(y * s)
        x1, y1 = min(size[0], max(x0 + 1, round((x + w) * s))), min(size[1], max(y0 + 1, round((y + h) * s)))
        return slice(y0, y1), slice(x0, x1)


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
    # An image folder's photos of another size than its first (another camera), each read into
    # the first's frame: see :class:`PhotoFit`.
    photo_fits: tuple[PhotoFit, ...] = ()

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
