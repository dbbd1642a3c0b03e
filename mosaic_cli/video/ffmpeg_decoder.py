"""The ffmpeg decoder: the bundled ffmpeg (imageio-ffmpeg's binary) on a pipe, a process of its
own that decodes the next frame while mosaic works on this one (docs/developer/video.md has the
measured rates).  :func:`select_filter` turns a request for some frames into ffmpeg's select
filter; the PyAV decoder (:mod:`.pyav_decoder`) takes the same requests."""

from __future__ import annotations

import contextlib
import fcntl
import re
import subprocess
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.video.info import VideoInfo
from mosaic_cli.video.pixels import (
    TO_BT601,
    YuvFrame,
    checked_size,
    frame_shape,
    is_bt601_limited,
    rgb_converted_here,
    rgb_from_yuv420p,
    yuv420p_bytes,
)


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


def select_filter(select: str | None, start: int | None, picks: Sequence[int] | None,
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
    frames: all, or one request of ``start``, ``picks``, ``near_times`` (:func:`select_filter`)
    or ``select`` (a select filter of the caller's own); ``seek`` (seconds) starts at the first
    frame at or after it; ``frames`` stops after that many."""

    def __init__(self, info: VideoInfo, pixels: str = "rgb", size: tuple[int, int] | None = None,
                 select: str | None = None, seek: float | None = None, frames: int | None = None, references_only: bool = False,
                 lazy_rgb: bool = False, *, start: int | None = None, picks: Sequence[int] | None = None,
                 near_times: Sequence[float] | None = None):
        self.size = checked_size(info, pixels, size)
        select = select_filter(select, start, picks, near_times)
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
