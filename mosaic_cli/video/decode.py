"""Decoding: the bundled ffmpeg (imageio-ffmpeg's binary) on a pipe, a process of its own that
decodes the next frame while mosaic works on this one (docs/developer/video.md has the measured
rates).  :func:`open_video` streams a file's (or an image folder's) frames; :class:`Decoder` is
the one ffmpeg decoder under it and under :func:`frames_at` and :func:`frame_at` (picked frames,
a frame at a time)."""

from __future__ import annotations

import contextlib
import fcntl
import re
import subprocess
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.video.folders import open_folder
from mosaic_cli.video.info import VideoInfo, VideoStream, scaled_size
from mosaic_cli.video.policy import refuse_damaged
from mosaic_cli.video.probe import probe

PIXELS = ("rgb", "gray", "yuv420p")
REFERENCE_SKIPPING_CODECS = ("h264", "hevc")  # whose decoders skip unreferenced frames exactly (frames_at)


def read_into(pipe, view: memoryview) -> int:
    """Fill ``view`` from ``pipe`` (a raw-frame pipe: reads may return less than asked); the
    bytes read, fewer than ``len(view)`` only at the end of the stream."""
    got = 0
    while got < len(view):
        n = pipe.readinto(view[got:])
        if not n:
            break
        got += n
    return got


def ffmpeg_exe() -> str:
    """The ffmpeg binary imageio-ffmpeg ships (or the one ``IMAGEIO_FFMPEG_EXE`` names), looked up
    when a video is first read or written, not when mosaic starts."""
    import imageio_ffmpeg

    return imageio_ffmpeg.get_ffmpeg_exe()


_PIX_FMT = {"rgb": "rgb24", "gray": "gray", "yuv420p": "yuv420p"}


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


class Decoder:
    """One ffmpeg process decoding a file's video stream to raw frames on its standard output.

    Iterate for the frames (each a new writable array); :attr:`error` then holds ffmpeg's first
    complaint, if it made one.  Close (or use as a context manager) to stop it early."""

    def __init__(self, info: VideoInfo, pixels: str = "rgb", size: tuple[int, int] | None = None,
                 select: str | None = None, seek: float | None = None, frames: int | None = None, references_only: bool = False,
                 lazy_rgb: bool = False):
        if pixels not in PIXELS:
            raise ValueError(f"pixels must be one of {', '.join(PIXELS)}, got {pixels}")
        self.size = size or info.source_size
        if pixels == "yuv420p" and (self.size != info.source_size or self.size[0] % 2 or self.size[1] % 2):
            raise ValueError(f"yuv420p frames are read at the source size, even only; got {self.size}")
        self.shape = frame_shape(pixels, self.size)
        self._to_rgb = pixels == "rgb" and rgb_converted_here(info, self.size)
        self._lazy = lazy_rgb and self._to_rgb
        piped = "yuv420p" if self._to_rgb else pixels
        self._piped_bytes = yuv420p_bytes(self.size) if self._to_rgb else int(np.prod(self.shape))
        self.error: str | None = None
        cmd = [ffmpeg_exe(), "-hide_banner", "-nostdin", "-loglevel", "error"]
        if seek is not None:
            cmd += ["-ss", f"{seek:.4f}"]
        if references_only:  # frames no other frame refers to are not decoded at all
            cmd += ["-skip_frame", "noref"]
        stream = f"0:{info.stream_index}" if info.stream_index is not None else "0:v:0"
        cmd += ["-i", info.path, "-map", stream]
        filters = [select] if select else []
        if self._to_rgb and not is_bt601_limited(info):
            filters.append(TO_BT601)
        if self.size != info.source_size:
            filters.append(f"scale={self.size[0]}:{self.size[1]}:flags=area")
        if filters:
            cmd += ["-vf", ",".join(filters)]
        if frames is not None:
            cmd += ["-frames:v", str(int(frames))]
        # Every decoded frame exactly once: ffmpeg's default for a pipe would resample a
        # variable frame rate to a constant one, duplicating and dropping frames.
        cmd += ["-fps_mode", "passthrough", "-f", "rawvideo", "-pix_fmt", _PIX_FMT[piped], "pipe:1"]
        self._log = tempfile.TemporaryFile()  # ffmpeg's complaints
        try:
            # Its own session: the terminal's Ctrl-C reaches mosaic alone, which then stops it.
            self._proc: subprocess.Popen | None = subprocess.Popen(
                cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=self._log, start_new_session=True, bufsize=0)
        except OSError as exc:
            self._log.close()
            raise BadInput(f"{info.path}: cannot start ffmpeg ({exc.strerror})") from None
        _widen_pipe(self._proc.stdout, self._piped_bytes)

    def __iter__(self) -> Iterator[np.ndarray]:
        assert self._proc is not None and self._proc.stdout is not None
        pipe = self._proc.stdout
        nbytes = self._piped_bytes
        got = 0
        while True:
            flat = np.empty(nbytes, np.uint8)
            got = read_into(pipe, memoryview(flat))
            if got < nbytes:
                break
            if self._lazy:
                yield YuvFrame(flat, self.size)  # type: ignore[misc]  (it stands for the RGB frame: see YuvFrame)
            else:
                yield rgb_from_yuv420p(flat, self.size) if self._to_rgb else flat.reshape(self.shape)
        status = self._proc.wait()
        self._log.seek(0)
        lines = [re.sub(r"^(\[[^]]*\] ?)+", "", ln).strip() for ln in self._log.read().decode("utf-8", "replace").splitlines()]
        lines = [ln for ln in lines if ln]
        if lines:
            self.error = lines[0]
        elif status != 0:
            self.error = f"ffmpeg exited with status {status}"
        elif got:
            self.error = "the last frame ends early"

    def close(self) -> None:
        if self._proc is not None:
            if self._proc.poll() is None:
                with contextlib.suppress(OSError):
                    self._proc.kill()
            self._proc.wait()
            if self._proc.stdout is not None:
                self._proc.stdout.close()
            self._proc = None
        self._log.close()

    def __enter__(self) -> Decoder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _widen_pipe(pipe, frame_bytes: int) -> None:
    """A pipe buffer of a whole frame where Linux allows it (up to /proc/sys/fs/pipe-max-size,
    1 MiB by default) rather than 64 KiB: ffmpeg then hands over a 720p gray frame in one write
    instead of 15, each a wait for the reader to be scheduled on a busy machine."""
    setpipe = getattr(fcntl, "F_SETPIPE_SZ", None)
    if setpipe is None or pipe is None:
        return
    try:
        limit = int(Path("/proc/sys/fs/pipe-max-size").read_text())
    except (OSError, ValueError):
        limit = 1 << 20
    with contextlib.suppress(OSError):
        fcntl.fcntl(pipe.fileno(), setpipe, min(max(frame_bytes, 1 << 16), limit))


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
) -> VideoStream:
    """Open ``path`` (a video file or a folder of numbered images) as a stream of frames.

    ``width`` downscales inside the decoder (aspect kept); ``gray`` yields (h, w) uint8 frames
    instead of RGB; ``yuv420p`` (video files of even size, no ``width``) the planes as ffmpeg
    decodes them, (h * 3 // 2, w), with no conversion; ``fps`` overrides the frame rate of an
    image folder; ``start`` skips frames.  ``info``: the file's :func:`probe`, when the caller
    has it (else it is probed here).  ``lazy_rgb``: full-size RGB frames that are converted here
    come as :class:`YuvFrame`, converted only when their pixels are asked for.
    """
    p = Path(path)
    if p.is_dir():
        if yuv420p:
            raise ValueError("yuv420p frames are read from video files only")
        stream = open_folder(p, width, fps, gray)
        if start:
            stream._frames = (f for k, f in enumerate(stream._frames) if k >= start)
        return stream
    if info is None:
        info = probe(p)
    else:
        refuse_damaged(info)  # probed before the command's --strict took effect
    pixels = "yuv420p" if yuv420p else "gray" if gray else "rgb"
    size = scaled_size(info.source_size, width)  # (yuv420p: the Decoder refuses a downscale)
    info = replace(info, size=size)
    decoder = Decoder(info, pixels, size, select=f"select=gte(n\\,{int(start)})" if start else None, lazy_rgb=lazy_rgb)

    def frames() -> Iterator[np.ndarray]:
        yield from decoder
        stream.decode_error = decoder.error

    stream = VideoStream(info, frames(), decoder.close)
    stream.frames_skipped = int(start)  # (a start past the end reads no frame, and says so)
    return stream


def frames_at(info: VideoInfo, indices: Sequence[int], width: int | None = None, near: bool = False) -> Iterator[np.ndarray]:
    """The RGB frames of ``indices`` (sorted), in one decoder pass that converts and pipes only
    those (ffmpeg's select filter), yielded as they come; fewer when the file ends first.

    ``near``: for each index, the first *reference* frame at or after its time instead, in a pass
    that does not decode the others (H.264 and HEVC: the frames are those of a full decode, bit
    for bit; about half of an x264 clip's frames, 40% less decoding).  Other codecs: exact."""
    if len(indices) == 0:
        return
    if near and info.video_codec in REFERENCE_SKIPPING_CODECS:
        fps = info.fps if info.fps > 0 else 30.0
        # A frame is picked when it is the first at or after an index's time: the frame picked
        # before it came earlier than that time (or there was none).
        times = [f"{(int(k) - 0.25) / fps:.6f}" for k in indices]
        picks = "+".join(f"gte(t-start_t\\,{T})*(isnan(prev_selected_t)+lt(prev_selected_t-start_t\\,{T}))" for T in times)
        references_only = True
    else:
        picks, references_only = "+".join(f"eq(n\\,{int(k)})" for k in indices), False
    with Decoder(info, "rgb", scaled_size(info.source_size, width), select=f"select='{picks}'", references_only=references_only) as decoder:
        yield from decoder


def frame_at(info: VideoInfo, seconds: float, width: int | None = None, near: bool = False) -> np.ndarray | None:
    """The first RGB frame at or after ``seconds`` (ffmpeg seeks to the keyframe before it and
    decodes from there), None when there is none; ``near``: the first reference frame, the
    others not decoded on the way (as :func:`frames_at`)."""
    references_only = near and info.video_codec in REFERENCE_SKIPPING_CODECS
    with Decoder(info, "rgb", scaled_size(info.source_size, width), seek=seconds, frames=1, references_only=references_only) as decoder:
        return next(iter(decoder), None)
