"""The PyAV decoder: libav in this process through PyAV, for machines without an ffmpeg binary
(:mod:`.backend` picks), yielding the frames the ffmpeg decoder (:mod:`.ffmpeg_decoder`) pipes,
decoded a few frames ahead of the reader on a thread of its own (:class:`~.read_ahead.ReadAhead`)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.video.ffmpeg_decoder import select_filter
from mosaic_cli.video.info import VideoInfo
from mosaic_cli.video.pixels import (
    YuvFrame,
    checked_size,
    frame_shape,
    is_bt601_limited,
    rgb_converted_here,
    rgb_from_yuv420p,
)
from mosaic_cli.video.read_ahead import READ_AHEAD, ReadAhead


class PyAVDecoder:
    """libav decoding the file's video stream in this process (PyAV), for machines without an
    ffmpeg binary: the same constructor and frames as :class:`FfmpegDecoder`.

    Iterate for the frames (each a new writable array, turned upright as ffmpeg turns them);
    :attr:`error` then holds libav's first complaint (an error that stopped decoding), if any.
    Close (or use as a context manager) to stop early.  ``select`` (an ffmpeg filter string) is
    refused: requests come as ``start``, ``picks`` or ``near_times`` (:func:`select_filter`
    says what each means)."""

    def __init__(self, info: VideoInfo, pixels: str = "rgb", size: tuple[int, int] | None = None,
                 select: str | None = None, seek: float | None = None, frames: int | None = None, references_only: bool = False,
                 lazy_rgb: bool = False, *, start: int | None = None, picks: Sequence[int] | None = None,
                 near_times: Sequence[float] | None = None):
        import av  # PyAV, loaded with the first video decoded by it

        self.size = checked_size(info, pixels, size)
        select_filter(select, start, picks, near_times)  # (one request at most)
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
