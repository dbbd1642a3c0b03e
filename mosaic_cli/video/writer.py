"""Streaming H.264 writer (imageio-ffmpeg), atomic, optionally carrying a source's audio."""

from __future__ import annotations

import contextlib
import os
import re
import subprocess
import tempfile
from pathlib import Path

import imageio_ffmpeg
import numpy as np

from mosaic_cli.atomic import check_writable, give_default_permissions
from mosaic_cli.errors import BadInput, ProcessingError

PRESETS = ("ultrafast", "superfast", "veryfast", "faster", "fast", "medium", "slow", "slower", "veryslow")
# Audio codecs an mp4/mov container takes as they are; anything else is re-encoded to AAC.
MP4_AUDIO = {"aac", "mp3", "ac3", "eac3", "alac"}
AUDIO_STREAM = re.compile(r"Stream #\S+.*?: Audio: (\w+)")


def even_size(size: tuple[int, int]) -> tuple[int, int]:
    """yuv420p needs even dimensions: odd ones grow by one (the last row/column is repeated)."""
    return (size[0] + size[0] % 2, size[1] + size[1] % 2)


def audio_stream_codec(path: str | os.PathLike) -> str | None:
    """The codec of the first audio stream of ``path`` (None when it has none or is unreadable)."""
    try:
        run = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-nostdin", "-i", str(path)],
                             capture_output=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    match = AUDIO_STREAM.search(run.stderr.decode("utf-8", "replace"))
    return match.group(1) if match else None


class VideoWriter:
    """Write RGB uint8 frames (h, w, 3) to an H.264 yuv420p file.

    The file appears under its final name only after :meth:`close` succeeds; :meth:`abort`
    (or an exception inside a ``with`` block) removes the partial file.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        size: tuple[int, int],
        fps: float,
        crf: int = 18,
        preset: str = "medium",
        audio_from: str | os.PathLike | None = None,
        audio_codec: str | None = None,
        pix_fmt_in: str = "rgb24",
    ):
        if not 0 <= crf <= 51:
            raise BadInput(f"--crf must be in 0..51, got {crf}")
        if preset not in PRESETS:
            raise BadInput(f"--preset must be one of {', '.join(PRESETS)}, got {preset!r}")
        if fps <= 0:
            raise BadInput(f"frame rate must be positive, got {fps}")
        self.path = check_writable(path)
        self.size = (int(size[0]), int(size[1]))
        self.out_size = even_size(self.size)
        # "yuv420p": frames are the planes as written by ffmpeg, (h * 3 // 2, w), even sizes only;
        # saves the RGB conversions when the frames were decoded as yuv420p too.
        if pix_fmt_in not in ("rgb24", "yuv420p") or (pix_fmt_in == "yuv420p" and self.out_size != self.size):
            raise ValueError(f"pix_fmt_in must be rgb24, or yuv420p with an even size; got {pix_fmt_in} at {self.size}")
        self.pix_fmt_in = pix_fmt_in
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.stem}.", suffix=f".part{self.path.suffix or '.mp4'}", dir=self.path.parent)
        os.close(fd)
        self._tmp = Path(tmp)
        audio_kwargs = {}
        extra_params: list[str] = []
        source_audio = audio_stream_codec(audio_from) if audio_from is not None else None
        if source_audio is not None:
            audio_kwargs = {"audio_path": str(audio_from), "audio_codec": audio_codec or self._audio_codec_for(source_audio)}
            # The video may be shorter than the source (a --max-frames run): end with it.
            extra_params = ["-shortest"]
        self._gen = imageio_ffmpeg.write_frames(
            str(self._tmp),
            self.out_size,
            fps=fps,
            codec="libx264",
            pix_fmt_in=pix_fmt_in,
            pix_fmt_out="yuv420p",
            quality=None,
            macro_block_size=1,
            output_params=["-crf", str(crf), "-preset", preset, "-movflags", "+faststart", *extra_params],
            ffmpeg_log_level="error",
            **audio_kwargs,
        )
        self._gen.send(None)
        self.frames_written = 0

    def _audio_codec_for(self, source_codec: str) -> str:
        """Copy the source's audio where the container takes it as it is, else AAC."""
        if self.path.suffix.lower() == ".mkv" or source_codec in MP4_AUDIO:
            return "copy"
        return "aac"

    def write(self, frame: np.ndarray) -> None:
        if self.pix_fmt_in == "yuv420p":
            if frame.shape != (self.size[1] * 3 // 2, self.size[0]):
                raise ProcessingError(f"yuv420p frame of shape {frame.shape} written to a {self.size[0]}x{self.size[1]} video")
            self._gen.send(np.ascontiguousarray(frame, dtype=np.uint8))
            self.frames_written += 1
            return
        if frame.shape[:2] != (self.size[1], self.size[0]):
            raise ProcessingError(f"frame of size {frame.shape[1]}x{frame.shape[0]} written to a {self.size[0]}x{self.size[1]} video")
        if frame.ndim == 2:
            frame = np.repeat(frame[:, :, None], 3, axis=2)
        if self.out_size != self.size:
            frame = np.pad(frame, ((0, self.out_size[1] - self.size[1]), (0, self.out_size[0] - self.size[0]), (0, 0)), mode="edge")
        self._gen.send(np.ascontiguousarray(frame, dtype=np.uint8))
        self.frames_written += 1

    def close(self) -> Path:
        """Finish encoding and move the file into place."""
        try:
            self._gen.close()
        except Exception as exc:
            self.abort()
            raise ProcessingError(f"{self.path}: encoding failed ({str(exc).splitlines()[0]})") from exc
        if self.frames_written == 0:
            self.abort()
            raise ProcessingError(f"{self.path}: no frames to write")
        give_default_permissions(self._tmp)
        os.replace(self._tmp, self.path)
        return self.path

    def abort(self) -> None:
        with contextlib.suppress(Exception):
            self._gen.close()
        with contextlib.suppress(FileNotFoundError):
            self._tmp.unlink()

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
