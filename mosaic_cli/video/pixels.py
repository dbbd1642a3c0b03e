"""Pixel formats: the layouts a decoder yields (``rgb``, ``gray``, ``yuv420p``), their shapes and
bytes, and the frames converted in this process from yuv420p (:class:`LumaRGB`, :class:`YuvFrame`)
with their gray copies made from the luma plane (:func:`gray_at`).  Both decoders
(:mod:`.ffmpeg_decoder`, :mod:`.pyav_decoder`) and a live stream (``live/source.py``) hand out
these."""

from __future__ import annotations

import numpy as np

from mosaic_cli.video.info import VideoInfo

PIXELS = ("rgb", "gray", "yuv420p")


# Full-size RGB frames of 8-bit 4:2:0 streams are piped as yuv420p, half the bytes of RGB, and
# converted here; ffmpeg first brings any other colour matrix or range to BT.601 limited range,
# the one OpenCV's conversion assumes (a no-op on untagged and BT.601 video).
CONVERTED_HERE = ("yuv420p", "yuvj420p")
TO_BT601 = "scale=out_color_matrix=bt601:out_range=tv"


def rgb_converted_here(info: VideoInfo, size: tuple[int, int]) -> bool:
    """Whether RGB frames of ``size`` are decoded as yuv420p and converted in this process
    (:func:`rgb_from_yuv420p`): at full size, from an 8-bit 4:2:0 stream.  The pipe then
    carries half the bytes; the pixels are ffmpeg's own conversion's within a few levels
    (docs/developer/video.md).  Other layouts (4:4:4: no chroma lost) and downscaled reads keep
    ffmpeg's conversion."""
    return size == info.source_size and info.pixel_format in CONVERTED_HERE


def is_bt601_limited(info: VideoInfo) -> bool:
    """Whether the stream is already what :data:`TO_BT601` makes (untagged counts: ffmpeg reads
    it so), when the filter, a no-op there, would only cost a copy of each frame."""
    return info.pixel_format == "yuv420p" and info.color_matrix in (2, 5, 6) and info.color_range in (0, 1)


def yuv420p_bytes(size: tuple[int, int]) -> int:
    """The bytes of one yuv420p frame of ``size`` (w, h) as ffmpeg writes it: the luma plane,
    then two chroma planes of ceil(w/2) x ceil(h/2)."""
    w, h = size
    return w * h + 2 * ((w + 1) // 2) * ((h + 1) // 2)


class LumaRGB(np.ndarray):
    """An RGB frame (h, w, 3) converted in this process from yuv420p, with its luma plane (h, w)
    kept beside it as ``luma``, so that a small gray copy costs a resize of that plane instead of
    a conversion of the whole frame (:func:`gray_at`), and each size is made once however many
    stages ask for it (``grays``).  Anything made from it (a slice, a copy, arithmetic) is a
    frame without ``luma``."""

    luma: np.ndarray | None
    grays: dict[tuple[int, int], np.ndarray]

    def __array_finalize__(self, obj) -> None:
        self.luma = None
        self.grays = {}


class YuvFrame:
    """A full-size frame decoded as BT.601 limited-range yuv420p and kept so, standing for its RGB
    frame (h, w, 3) where only some frames' pixels are ever needed (``stitch`` keeps its
    keyframes' alone): every gray copy is resized from its luma plane (:func:`gray_at`, each size
    once), and the RGB frame is converted once, when its pixels are first asked for
    (``np.asarray(frame)``), as :func:`rgb_from_yuv420p` converts it.  Read with
    ``open_video(..., lazy_rgb=True)``."""

    __slots__ = ("_flat", "size", "luma", "grays", "_rgb")
    ndim = 3
    dtype = np.dtype(np.uint8)

    def __init__(self, flat: np.ndarray, size: tuple[int, int]):
        w, h = size
        self._flat, self.size = flat, size
        self.luma = flat[:w * h].reshape(h, w)
        self.grays: dict[tuple[int, int], np.ndarray] = {}
        self._rgb: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        return (self.size[1], self.size[0], 3)

    @property
    def rgb(self) -> np.ndarray:
        """The RGB frame, converted on the first call (a plain array: slices and copies of it
        carry no luma plane)."""
        if self._rgb is None:
            self._rgb = np.asarray(rgb_from_yuv420p(self._flat, self.size))
        return self._rgb

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        """The RGB frame itself (``np.asarray``), or a copy where one is asked for (``np.array``,
        another dtype): the converted frame is shared, never handed out to be changed."""
        rgb = self.rgb
        if dtype is not None and np.dtype(dtype) != rgb.dtype:
            return rgb.astype(dtype)
        return rgb.copy() if copy else rgb


# BT.601's RGB -> gray undoes its YUV -> RGB (the chroma terms cancel): the gray of a converted
# frame is its luma stretched from the limited range 16-235 to 0-255 (but where a channel clipped).
_LIMITED_TO_FULL = np.clip(np.round((np.arange(256) - 16) * 255.0 / 219.0), 0, 255).astype(np.uint8)


def rgb_from_yuv420p(flat: np.ndarray, size: tuple[int, int]) -> LumaRGB:
    """The RGB frame (h, w, 3) of a BT.601 limited-range yuv420p frame ``flat`` (its bytes, as
    :func:`yuv420p_bytes` counts them), keeping its luma plane (a view of ``flat``).  An odd
    width or height is converted with the luma padded by its last column or row (the chroma
    planes already cover it), then cut back."""
    import cv2

    w, h = size
    W, H = w + w % 2, h + h % 2
    luma = flat[:w * h].reshape(h, w)
    if (W, H) == (w, h):
        planes = flat.reshape(H * 3 // 2, W)
    else:
        planes = np.empty((H * 3 // 2, W), np.uint8)
        planes[:H] = cv2.copyMakeBorder(luma, 0, H - h, 0, W - w, cv2.BORDER_REPLICATE)
        planes[H:].reshape(-1)[:] = flat[w * h:]
    rgb = cv2.cvtColor(planes, cv2.COLOR_YUV2RGB_I420)
    if (W, H) != (w, h):
        rgb = np.ascontiguousarray(rgb[:h, :w])
    frame = rgb.view(LumaRGB)
    frame.luma = luma
    return frame


def gray_at(frame: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(h, w) uint8 gray of an RGB (h, w, 3) or gray ``frame``, resized to ``size`` (w, h) with
    area averaging.  A :class:`LumaRGB` or :class:`YuvFrame` frame is resized from its luma plane
    instead of being converted whole (on BT.601 video, exactly ffmpeg's own gray at full size),
    once per size: the same read-only array for each call."""
    import cv2

    luma = getattr(frame, "luma", None)
    if luma is not None:
        grays = frame.grays  # type: ignore[attr-defined]  (a LumaRGB or a YuvFrame)
        size = (int(size[0]), int(size[1]))
        gray = grays.get(size)
        if gray is None:  # stitch's estimator and its frame quality both ask for the working size
            small = luma if (luma.shape[1], luma.shape[0]) == size else cv2.resize(luma, size, interpolation=cv2.INTER_AREA)
            gray = cv2.LUT(small, _LIMITED_TO_FULL)
            gray.flags.writeable = False  # shared by every stage that asks: none may change it
            grays[size] = gray
        return gray
    gray = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)
    return gray if (gray.shape[1], gray.shape[0]) == size else cv2.resize(gray, size, interpolation=cv2.INTER_AREA)


def frame_shape(pixels: str, size: tuple[int, int]) -> tuple[int, ...]:
    """The array shape of one frame of ``size`` (w, h): gray (h, w), rgb (h, w, 3), yuv420p
    the three planes one after the other, (h * 3 // 2, w)."""
    w, h = size
    return {"gray": (h, w), "rgb": (h, w, 3), "yuv420p": (h * 3 // 2, w)}[pixels]


def checked_size(info: VideoInfo, pixels: str, size: tuple[int, int] | None) -> tuple[int, int]:
    """The (w, h) of the frames a decoder yields, refusing what neither backend can give."""
    if pixels not in PIXELS:
        raise ValueError(f"pixels must be one of {', '.join(PIXELS)}, got {pixels}")
    size = size or info.source_size
    if pixels == "yuv420p" and (size != info.source_size or size[0] % 2 or size[1] % 2):
        raise ValueError(f"yuv420p frames are read at the source size, even only; got {size}")
    return size
