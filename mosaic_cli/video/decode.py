"""Decoding: the bundled ffmpeg (imageio-ffmpeg's binary) on a pipe, a process of its own that
decodes the next frame while mosaic works on this one (docs/developer/video.md has the measured
rates), or, where there is no ffmpeg binary, libav in this process through PyAV
(:mod:`.backend` picks).  :func:`open_video` streams a file's (or an image folder's) frames;
:func:`Decoder` gives the decoder under it and under :func:`frames_at` and :func:`frame_at`
(picked frames, a frame at a time): an :class:`FfmpegDecoder` or a :class:`PyAVDecoder`."""

from __future__ import annotations

import contextlib
import fcntl
import queue
import re
import subprocess
import tempfile
import threading
from collections.abc import Callable, Iterator, Sequence
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


def _checked_size(info: VideoInfo, pixels: str, size: tuple[int, int] | None) -> tuple[int, int]:
    """The (w, h) of the frames a decoder yields, refusing what neither backend can give."""
    if pixels not in PIXELS:
        raise ValueError(f"pixels must be one of {', '.join(PIXELS)}, got {pixels}")
    size = size or info.source_size
    if pixels == "yuv420p" and (size != info.source_size or size[0] % 2 or size[1] % 2):
        raise ValueError(f"yuv420p frames are read at the source size, even only; got {size}")
    return size


def _select_filter(select: str | None, start: int | None, picks: Sequence[int] | None,
                   near_times: Sequence[float] | None) -> str | None:
    """ffmpeg's select filter for a request made with the structured arguments the PyAV decoder
    takes too (so both backends get the same request): ``start``, the frames from the
    ``start``-th decoded on; ``picks``, the decoded frames of those numbers; ``near_times``
    (seconds from the first frame), for each time the first frame at or after it, unless the
    frame picked before it already came at or after that time.  ``select``: a filter of the
    caller's own (ffmpeg only), when none of these is given."""
    if sum(x is not None for x in (select, start, picks, near_times)) > 1:
        raise ValueError("give one of select, start, picks, near_times")
    if start:
        return f"select=gte(n\\,{int(start)})"
    if picks is not None:
        return "select='" + "+".join(f"eq(n\\,{int(k)})" for k in picks) + "'"
    if near_times is not None:
        # A frame is picked when it is the first at or after a time: the frame picked before it
        # came earlier than that time (or there was none).
        return "select='" + "+".join(f"gte(t-start_t\\,{T:.6f})*(isnan(prev_selected_t)+lt(prev_selected_t-start_t\\,{T:.6f}))"
                                     for T in near_times) + "'"
    return select


class FfmpegDecoder:
    """One ffmpeg process decoding a file's video stream to raw frames on its standard output.

    Iterate for the frames (each a new writable array); :attr:`error` then holds ffmpeg's first
    complaint, if it made one.  Close (or use as a context manager) to stop it early.  Which
    frames: all, or one request of ``start``, ``picks``, ``near_times`` (:func:`_select_filter`)
    or ``select`` (a select filter of the caller's own); ``seek`` (seconds) starts at the first
    frame at or after it; ``frames`` stops after that many."""

    def __init__(self, info: VideoInfo, pixels: str = "rgb", size: tuple[int, int] | None = None,
                 select: str | None = None, seek: float | None = None, frames: int | None = None, references_only: bool = False,
                 lazy_rgb: bool = False, *, start: int | None = None, picks: Sequence[int] | None = None,
                 near_times: Sequence[float] | None = None):
        self.size = _checked_size(info, pixels, size)
        select = _select_filter(select, start, picks, near_times)
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

    def __enter__(self) -> FfmpegDecoder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class PyAVDecoder:
    """libav decoding the file's video stream in this process (PyAV), for machines without an
    ffmpeg binary: the same constructor and frames as :class:`FfmpegDecoder`.

    Iterate for the frames (each a new writable array, turned upright as ffmpeg turns them);
    :attr:`error` then holds libav's first complaint (an error that stopped decoding), if any.
    Close (or use as a context manager) to stop early.  ``select`` (an ffmpeg filter string) is
    refused: requests come as ``start``, ``picks`` or ``near_times`` (:func:`_select_filter`
    says what each means)."""

    def __init__(self, info: VideoInfo, pixels: str = "rgb", size: tuple[int, int] | None = None,
                 select: str | None = None, seek: float | None = None, frames: int | None = None, references_only: bool = False,
                 lazy_rgb: bool = False, *, start: int | None = None, picks: Sequence[int] | None = None,
                 near_times: Sequence[float] | None = None):
        import av  # PyAV, loaded with the first video decoded by it

        self.size = _checked_size(info, pixels, size)
        _select_filter(select, start, picks, near_times)  # (one request at most)
        if select is not None:
            raise ValueError("the PyAV decoder takes start, picks or near_times, not an ffmpeg select filter")
        self.info, self.pixels = info, pixels
        self.shape = frame_shape(pixels, self.size)
        self._to_rgb = pixels == "rgb" and rgb_converted_here(info, self.size)
        self._lazy = lazy_rgb and self._to_rgb
        self._turns = (-(info.rotation // 90)) % 4  # np.rot90's counter-clockwise quarter turns
        w, h = self.size
        self._decoded_size = (h, w) if self._turns % 2 else (w, h)  # (w, h) before the turn
        self._start, self._picks = int(start or 0), (set(int(k) for k in picks) if picks is not None else None)
        self._near = [float(f"{T:.6f}") for T in near_times] if near_times is not None else None  # as ffmpeg is told them
        self._seek = float(f"{seek:.4f}") if seek is not None else None
        self._frames = int(frames) if frames is not None else None
        self._ahead: ReadAhead | None = None
        self.error: str | None = None
        try:
            self._container = av.open(info.path, metadata_errors="replace")
        except (av.error.FFmpegError, OSError, ValueError) as exc:
            raise BadInput(f"{info.path}: cannot decode ({_libav_reason(exc)})") from None
        try:
            if info.stream_index is not None:
                self._stream = self._container.streams[info.stream_index]
            else:
                self._stream = self._container.streams.video[0]
            # Frame threads: several frames decode at once (H.264 at 720p: about twice the rate).
            self._stream.thread_type = "AUTO"
            if references_only:  # frames no other frame refers to are not decoded at all
                self._stream.codec_context.skip_frame = "NONREF"
        except (IndexError, av.error.FFmpegError) as exc:
            self._container.close()
            raise BadInput(f"{info.path}: cannot decode its video stream ({_libav_reason(exc)})") from None

    def __iter__(self) -> Iterator[np.ndarray]:
        # Decoded on a thread of its own, a few frames ahead of the reader: the ffmpeg decoder's
        # process decodes the next frames while mosaic works on this one, and so does this.
        self._ahead = ReadAhead(self._decoded(), READ_AHEAD)
        try:
            yield from self._ahead
        finally:
            self._ahead.stop()

    def _decoded(self) -> Iterator[np.ndarray]:
        import av

        container, stream = self._container, self._stream
        # ffmpeg's timeline: -ss counts from the file's start time; select's t - start_t from the
        # first frame that reaches the filter.
        origin = container.start_time / av.time_base if container.start_time is not None else 0.0
        half_tick = float(stream.time_base) / 2 if stream.time_base else 1e-6
        fps = self.info.fps if self.info.fps > 0 else 30.0
        n, yielded, first_t, prev_picked = -1, 0, None, None
        try:
            if self._seek is not None:  # to the keyframe before; the frames before the time are dropped below
                container.seek(int(round((origin + self._seek) * av.time_base)), backward=True)
            for frame in container.decode(stream):
                t = frame.time
                if self._seek is not None and t is not None and t - origin < self._seek - half_tick:
                    continue
                n += 1
                if t is None:
                    t = n / fps
                if first_t is None:
                    first_t = t
                if not self._wanted(n, t - first_t, prev_picked):
                    continue
                prev_picked = t - first_t
                yield self._pixels(frame)
                yielded += 1
                if self._frames is not None and yielded >= self._frames:
                    break
        except av.error.FFmpegError as exc:
            self.error = _libav_reason(exc)

    def _wanted(self, n: int, t: float, prev: float | None) -> bool:
        """Whether the ``n``-th frame (0 first), ``t`` seconds after the first, is yielded."""
        if n < self._start:
            return False
        if self._picks is not None:
            return n in self._picks
        if self._near is not None:
            return any(t >= T and (prev is None or prev < T) for T in self._near)
        return True

    def _pixels(self, frame) -> np.ndarray:
        """The frame as the ffmpeg decoder pipes it: gray (h, w) and downscaled RGB by swscale's
        area filter, yuv420p planes as decoded (converted to RGB here where ffmpeg's are)."""
        w, h = self._decoded_size
        if self.pixels == "gray":
            return self._upright(_writable(frame.to_ndarray(width=w, height=h, format="gray", interpolation="AREA")))
        if self.pixels == "yuv420p" or self._to_rgb:
            if self._to_rgb and not is_bt601_limited(self.info):
                # TO_BT601: the matrix and range OpenCV's conversion assumes.
                frame = frame.reformat(format="yuv420p", dst_colorspace="ITU601", dst_color_range="MPEG")
            elif frame.format.name != "yuv420p":
                frame = frame.reformat(format="yuv420p")
            flat = self._upright_planes(_yuv420p_flat(frame))
            if not self._to_rgb:
                return flat.reshape(self.shape)
            if self._lazy:
                return YuvFrame(flat, self.size)  # type: ignore[return-value]  (it stands for the RGB frame)
            return rgb_from_yuv420p(flat, self.size)
        interpolation = "AREA" if (w, h) != (frame.width, frame.height) else None
        return self._upright(_writable(frame.to_ndarray(width=w, height=h, format="rgb24", interpolation=interpolation)))

    def _upright(self, image: np.ndarray) -> np.ndarray:
        """``image`` (h, w[, 3]) turned as the display matrix asks (ffmpeg's autorotate)."""
        return np.ascontiguousarray(np.rot90(image, self._turns)) if self._turns else image

    def _upright_planes(self, flat: np.ndarray) -> np.ndarray:
        """yuv420p bytes (:func:`yuv420p_bytes`) with each plane turned upright."""
        if not self._turns:
            return flat
        w, h = self._decoded_size
        cw, ch = (w + 1) // 2, (h + 1) // 2
        luma, chroma = flat[:w * h].reshape(h, w), flat[w * h:].reshape(2, ch, cw)
        return np.concatenate([np.rot90(luma, self._turns).reshape(-1), np.rot90(chroma, self._turns, axes=(1, 2)).reshape(-1)])

    def close(self) -> None:
        if self._ahead is not None:  # the decoding thread ends before its container closes
            self._ahead.stop()
        if self._container is not None:
            self._container.close()
            self._container = None

    def __enter__(self) -> PyAVDecoder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


READ_AHEAD = 4  # frames the PyAV decoder's thread may decode before they are read (a 4K RGB frame: 25 MB)


class ReadAhead:
    """The items of ``source`` (an iterator) made on a thread of its own, at most ``depth`` of them
    ahead of the reader; an error raised making them is raised to the reader, in its turn.
    :meth:`stop` ends the thread (and closes ``source``) whether or not it was read to the end."""

    _END = object()

    def __init__(self, source: Iterator, depth: int):
        self._queue: queue.Queue = queue.Queue(max(1, depth))
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(source,), name="mosaic-decode", daemon=True)
        self._thread.start()

    def _run(self, source: Iterator) -> None:
        try:
            for item in source:
                if not self._put(item):
                    return
        except BaseException as exc:  # noqa: BLE001 - handed to the reader, who raises it
            self._error = exc
        finally:
            close = getattr(source, "close", None)
            if close is not None:
                close()
            self._put(self._END)

    def _put(self, item: object) -> bool:
        """Queue ``item``, waiting for room; False once stopped."""
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def __iter__(self) -> Iterator:
        while True:
            item = self._queue.get()
            if item is self._END:
                if self._error is not None:
                    raise self._error
                return
            yield item

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join()


def _writable(image: np.ndarray) -> np.ndarray:
    """``image`` itself when the caller may change it (a frame of its own), else a copy."""
    return image if image.flags.writeable and image.flags.c_contiguous else image.copy()


def _yuv420p_flat(frame) -> np.ndarray:
    """The bytes of a yuv420p ``frame`` as ffmpeg's rawvideo writes them (:func:`yuv420p_bytes`:
    each plane's rows without libav's line padding), a new array."""
    w, h = frame.width, frame.height
    cw, ch = (w + 1) // 2, (h + 1) // 2
    flat = np.empty(w * h + 2 * cw * ch, np.uint8)
    offset = 0
    for plane, (pw, ph) in zip(frame.planes, ((w, h), (cw, ch), (cw, ch))):
        rows = np.frombuffer(plane, np.uint8)[:plane.line_size * ph].reshape(ph, plane.line_size)
        flat[offset:offset + pw * ph].reshape(ph, pw)[:] = rows[:, :pw]
        offset += pw * ph
    return flat


def _libav_reason(exc: BaseException) -> str:
    """libav's words for an error PyAV raised, without its errno prefix."""
    return getattr(exc, "strerror", None) or str(exc) or type(exc).__name__


def Decoder(info: VideoInfo, pixels: str = "rgb", size: tuple[int, int] | None = None, **request) -> FfmpegDecoder | PyAVDecoder:
    """The decoder of the backend :func:`~mosaic_cli.video.backend.video_backend` picks: an
    :class:`FfmpegDecoder` or a :class:`PyAVDecoder`, which take the same arguments."""
    from mosaic_cli.video.backend import video_backend

    kind = PyAVDecoder if video_backend() == "pyav" else FfmpegDecoder
    return kind(info, pixels, size, **request)


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


# --lens: each input's frames seen through a filter (the lens's undistortion), keyed by the
# input's resolved path and set for the length of a command (:func:`seen_through`).  Every
# reader of that input (the estimator's pass, the probes, the stitch's scan, the stabiliser's
# render) then sees the same undistorted frames, remapped once as they are decoded; its outputs
# (a stabilised video measured afterwards) are left alone.
_SEEN_THROUGH: dict[str, Callable[[np.ndarray], np.ndarray]] = {}


@contextlib.contextmanager
def seen_through(path: str | Path, image_filter: Callable[[np.ndarray], np.ndarray] | None) -> Iterator[None]:
    """While inside, the frames :func:`open_video` and :func:`frames_at` read from ``path`` are
    ``image_filter(plane)`` of each decoded image (h, w) or (h, w, C), keeping its size; yuv420p
    frames are filtered plane by plane.  None: nothing changes."""
    key = str(Path(path).resolve())
    if image_filter is None:
        yield
        return
    _SEEN_THROUGH[key] = image_filter
    try:
        yield
    finally:
        _SEEN_THROUGH.pop(key, None)


def image_filter_for(path: str | Path) -> Callable[[np.ndarray], np.ndarray] | None:
    """The filter :func:`seen_through` set for ``path`` (a file, or a live source's name as
    given), None where there is none."""
    return _SEEN_THROUGH.get(str(Path(path).resolve())) if _SEEN_THROUGH else None


def filter_frame(frame, size: tuple[int, int], yuv420p: bool, image_filter: Callable[[np.ndarray], np.ndarray]):
    """One decoded frame of ``size`` through ``image_filter``: an RGB or gray image whole, a
    yuv420p frame (or a :class:`YuvFrame`) plane by plane."""
    def planes(flat: np.ndarray) -> np.ndarray:
        w, h = size
        cw, ch = (w + 1) // 2, (h + 1) // 2
        flat = np.asarray(flat).reshape(-1)
        out = np.empty_like(flat)
        out[:w * h] = image_filter(flat[:w * h].reshape(h, w)).reshape(-1)
        for k in range(2):
            at = w * h + k * cw * ch
            out[at:at + cw * ch] = image_filter(flat[at:at + cw * ch].reshape(ch, cw)).reshape(-1)
        return out

    if isinstance(frame, YuvFrame):
        return YuvFrame(planes(frame._flat), frame.size)
    if yuv420p:
        return planes(frame).reshape(frame.shape)
    return image_filter(np.asarray(frame))


def _filtered(path: str | Path, frames: Iterator, size: tuple[int, int], yuv420p: bool) -> Iterator:
    """``frames`` through the filter set for ``path`` (:func:`seen_through`), if any."""
    image_filter = image_filter_for(path)
    if image_filter is None:
        return frames
    return (filter_frame(frame, size, yuv420p, image_filter) for frame in frames)


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
    raw: bool = False,
) -> VideoStream:
    """Open ``path`` (a video file or a folder of numbered images) as a stream of frames.

    ``width`` downscales inside the decoder (aspect kept); ``gray`` yields (h, w) uint8 frames
    instead of RGB; ``yuv420p`` (video files of even size, no ``width``) the planes as ffmpeg
    decodes them, (h * 3 // 2, w), with no conversion; ``fps`` overrides the frame rate of an
    image folder; ``start`` skips frames.  ``info``: the file's :func:`probe`, when the caller
    has it (else it is probed here).  ``lazy_rgb``: full-size RGB frames that are converted here
    come as :class:`YuvFrame`, converted only when their pixels are asked for.  ``raw``: the
    frames as decoded, not through the filter :func:`seen_through` set for ``path``
    (``stabilize --keep-lens`` renders the lens's own frames).
    """
    p = Path(path)
    if p.is_dir():
        if yuv420p:
            raise ValueError("yuv420p frames are read from video files only")
        stream = open_folder(p, width, fps, gray)
        if start:
            stream._frames = (f for k, f in enumerate(stream._frames) if k >= start)
        if not raw:
            stream._frames = _filtered(p, stream._frames, stream.info.size, False)
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
        yield from (iter(decoder) if raw else _filtered(p, iter(decoder), size, yuv420p))
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
        # Each index's time less a quarter frame: its frame's time, whatever the rounding.
        request: dict = {"near_times": [(int(k) - 0.25) / fps for k in indices], "references_only": True}
    else:
        request = {"picks": [int(k) for k in indices]}
    with Decoder(info, "rgb", scaled_size(info.source_size, width), **request) as decoder:
        yield from _filtered(info.path, iter(decoder), scaled_size(info.source_size, width), False)


def frame_at(info: VideoInfo, seconds: float, width: int | None = None, near: bool = False) -> np.ndarray | None:
    """The first RGB frame at or after ``seconds`` (ffmpeg seeks to the keyframe before it and
    decodes from there), None when there is none; ``near``: the first reference frame, the
    others not decoded on the way (as :func:`frames_at`)."""
    references_only = near and info.video_codec in REFERENCE_SKIPPING_CODECS
    with Decoder(info, "rgb", scaled_size(info.source_size, width), seek=seconds, frames=1, references_only=references_only) as decoder:
        return next(iter(decoder), None)
