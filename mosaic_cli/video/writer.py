"""Streaming H.264 writer (the ffmpeg of imageio-ffmpeg), atomic, optionally carrying a source's audio."""

from __future__ import annotations

import contextlib
import os
import subprocess
import tempfile
from fractions import Fraction
from pathlib import Path

import numpy as np

from mosaic_cli.atomic import check_writable, give_default_permissions, signals_held, temporary_beside
from mosaic_cli.errors import BadInput, ProcessingError
from mosaic_cli.video.reader import VideoInfo, audio_codec_of, ffmpeg_exe

# The H.264 encoder's ``--preset`` values (libx264's), fastest first.
PRESETS = ("ultrafast", "superfast", "veryfast", "faster", "fast", "medium", "slow", "slower", "veryslow")

# The containers a stabilised video is written in (H.264 with the source's audio).
OUTPUT_SUFFIXES = (".mp4", ".mov", ".m4v", ".mkv")

# Audio codecs an mp4/mov container takes as they are; anything else is re-encoded to AAC.
MP4_AUDIO = {"aac", "mp3", "ac3", "eac3", "alac"}


def check_encoder(crf: int | None, preset: str) -> None:
    """``--crf`` (None: the command's default) and ``--preset`` of the H.264 encoder: the flags'
    bounds, which every command that writes a video (and its options' ``validate()``) applies."""
    if crf is not None and not 0 <= crf <= 51:
        raise BadInput(f"--crf must be in 0..51, got {crf}")
    if preset not in PRESETS:
        raise BadInput(f"--preset must be one of {', '.join(PRESETS)}, got {preset!r}")


def even_size(size: tuple[int, int]) -> tuple[int, int]:
    """yuv420p needs even dimensions: odd ones grow by one (the last row/column is repeated)."""
    return (size[0] + size[0] % 2, size[1] + size[1] % 2)


class VideoWriter:
    """Write RGB uint8 frames (h, w, 3) to an H.264 yuv420p file.

    With ``audio_from`` (a video's :func:`~mosaic_cli.video.reader.probe`, or the path of
    any media file), the first audio stream of that file is carried (cut after ``audio_seconds``
    when given); the video keeps every frame written whatever the audio's length.

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
        audio_from: VideoInfo | str | os.PathLike | None = None,
        audio_codec: str | None = None,
        pix_fmt_in: str = "rgb24",
        audio_seconds: float | None = None,
        metadata: dict[str, str] | None = None,
    ):
        check_encoder(crf, preset)
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
        self._tmp: Path | None = None
        self._encoder: subprocess.Popen | None = None
        self._log = None
        if isinstance(audio_from, VideoInfo):
            source_audio, audio_from = audio_from.audio_codec, audio_from.path
        else:
            source_audio = audio_codec_of(audio_from) if audio_from is not None else None
        audio = None if source_audio is None else (str(audio_from), audio_codec or self._audio_codec_for(source_audio))
        if audio_seconds is not None and audio_seconds <= 0:
            raise ValueError(f"audio_seconds must be positive, got {audio_seconds}")
        self.audio_seconds = audio_seconds
        self.metadata = dict(metadata or {})  # container tags, e.g. {"comment": ...}
        try:  # until the writer is returned, no ``with`` block will remove the file: this one does
            # Signals wait until the file and the encoder are both in hand: a Ctrl-C inside Popen
            # would lose the encoder, which would then make the file again after it was removed.
            with signals_held():
                self._tmp = temporary_beside(self.path, f".part{self.path.suffix or '.mp4'}")
                self._start_encoder(fps, crf, preset, audio)
        except BaseException:
            self.abort()
            raise
        self.frames_written = 0

    def _start_encoder(self, fps: float, crf: int, preset: str, audio: tuple[str, str] | None) -> None:
        """ffmpeg reading raw frames on its stdin, in its own session: the terminal's Ctrl-C
        reaches mosaic alone, which then stops it (it inherits the held signals, and needs none).
        ``audio``: (the file whose first audio stream is carried, the codec: "copy" or one to encode)."""
        w, h = self.out_size
        cmd = [ffmpeg_exe(), "-y", "-hide_banner", "-v", "error",
               "-f", "rawvideo", "-pix_fmt", self.pix_fmt_in, "-s", f"{w}x{h}", "-r", str(Fraction(fps).limit_denominator()),
               "-i", "-"]
        if audio is None:
            cmd += ["-an"]
        else:
            # Never -shortest: it ends the *video* where a slightly shorter audio track ends (a
            # camera's AAC often stops a few hundredths of a second early), losing the last
            # frames.  The audio is cut where the video ends instead, when the caller knows
            # where that is (-t on the audio input: a stream copy keeps whole packets, so it may
            # overhang by one AAC frame, 21 ms at 48 kHz).
            until = ["-t", f"{self.audio_seconds:.6f}"] if self.audio_seconds is not None else []
            cmd += [*until, "-i", audio[0], "-map", "0:v:0", "-map", "1:a:0", "-acodec", audio[1]]
        for key, value in self.metadata.items():
            cmd += ["-metadata", f"{key}={value}"]
        cmd += ["-vcodec", "libx264", "-pix_fmt", "yuv420p", "-crf", str(crf), "-preset", preset,
                "-movflags", "+faststart", str(self._tmp)]
        self._log = tempfile.TemporaryFile()  # ffmpeg's complaints, for the error message
        self._encoder = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=self._log,
                                         start_new_session=True)

    def _audio_codec_for(self, source_codec: str) -> str:
        """Copy the source's audio where the container takes it as it is, else AAC."""
        if self.path.suffix.lower() == ".mkv" or source_codec in MP4_AUDIO:
            return "copy"
        return "aac"

    def write(self, frame: np.ndarray) -> None:
        if self.pix_fmt_in == "yuv420p":
            if frame.shape != (self.size[1] * 3 // 2, self.size[0]):
                raise ProcessingError(f"yuv420p frame of shape {frame.shape} written to a {self.size[0]}x{self.size[1]} video")
        elif frame.shape[:2] != (self.size[1], self.size[0]):
            raise ProcessingError(f"frame of size {frame.shape[1]}x{frame.shape[0]} written to a {self.size[0]}x{self.size[1]} video")
        else:
            if frame.ndim == 2:
                frame = np.repeat(frame[:, :, None], 3, axis=2)
            if self.out_size != self.size:
                frame = np.pad(frame, ((0, self.out_size[1] - self.size[1]), (0, self.out_size[0] - self.size[0]), (0, 0)), mode="edge")
        try:
            self._encoder.stdin.write(np.ascontiguousarray(frame, dtype=np.uint8).data)
        except OSError:  # the encoder is gone
            self.abort()
            raise ProcessingError(f"{self.path}: encoding failed ({self._complaint()})") from None
        self.frames_written += 1

    def close(self) -> Path:
        """Finish encoding and move the file into place (or, whatever stops that, remove it)."""
        try:
            with contextlib.suppress(OSError):
                self._encoder.stdin.close()
            if self._encoder.wait() != 0:
                raise ProcessingError(f"{self.path}: encoding failed ({self._complaint()})")
            if self.frames_written == 0:
                raise ProcessingError(f"{self.path}: no frames to write")
            give_default_permissions(self._tmp)
            os.replace(self._tmp, self.path)
        except BaseException:
            self.abort()
            raise
        self._log.close()
        return self.path

    def abort(self) -> None:
        """Stop the encoder, wait until it has exited (it could still create the file), remove the file."""
        if self._encoder is not None:
            with contextlib.suppress(OSError):
                self._encoder.kill()
            self._encoder.wait()
            with contextlib.suppress(OSError):
                self._encoder.stdin.close()
        if self._log is not None:
            self._log.close()
        if self._tmp is not None:
            with contextlib.suppress(FileNotFoundError):
                self._tmp.unlink()

    def _complaint(self) -> str:
        """ffmpeg's last line on stderr, or its exit status."""
        if self._log is not None and not self._log.closed:
            self._log.seek(0)
            lines = self._log.read().decode("utf-8", "replace").strip().splitlines()
            if lines:
                return lines[-1]
        return f"ffmpeg exited with status {self._encoder.poll() if self._encoder else None}"

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def rewrite_container(path: str | os.PathLike, audio_seconds: float | None = None,
                      metadata: dict[str, str] | None = None) -> None:
    """Rewrite a finished video by stream copy (no re-encoding), its audio cut after
    ``audio_seconds`` and ``metadata`` added to its tags: for what is known only once encoding
    has begun (stabilize's render starts before the tracking pass has counted the frames).
    Atomic: the file is replaced only when the copy succeeded."""
    path = Path(path)
    with signals_held():
        tmp = temporary_beside(path, f".part{path.suffix or '.mp4'}")
    cmd = [ffmpeg_exe(), "-y", "-hide_banner", "-v", "error", "-i", str(path)]
    if audio_seconds is not None:  # the same file again, read only this far, for its audio
        cmd += ["-t", f"{audio_seconds:.6f}", "-i", str(path), "-map", "0:v:0", "-map", "1:a:0?"]
    else:
        cmd += ["-map", "0"]
    for key, value in (metadata or {}).items():
        cmd += ["-metadata", f"{key}={value}"]
    cmd += ["-c", "copy", "-movflags", "+faststart", str(tmp)]
    try:
        done = subprocess.run(cmd, stdin=subprocess.DEVNULL, capture_output=True, start_new_session=True)
        if done.returncode != 0:
            lines = done.stderr.decode("utf-8", "replace").strip().splitlines()
            raise ProcessingError(f"{path}: rewriting failed ({lines[-1] if lines else f'status {done.returncode}'})")
        give_default_permissions(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
