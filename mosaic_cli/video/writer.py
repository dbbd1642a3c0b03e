"""Streaming H.264 writer (the ffmpeg of imageio-ffmpeg, or libav in this process through PyAV
where there is no ffmpeg binary: :mod:`.backend`), atomic, optionally carrying a source's audio."""

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
from mosaic_cli.video.backend import video_backend
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
        self._pyav: _PyAVEncoder | None = None
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
                if video_backend() == "pyav":
                    self._pyav = _PyAVEncoder(self._tmp, self.path, self.out_size, fps, crf, preset, audio, audio_seconds, self.metadata)
                else:
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
        if self._pyav is not None:
            try:
                self._pyav.write(np.ascontiguousarray(frame, dtype=np.uint8), self.pix_fmt_in)
            except ProcessingError:
                self.abort()
                raise
            self.frames_written += 1
            return
        try:
            self._encoder.stdin.write(np.ascontiguousarray(frame, dtype=np.uint8).data)
        except OSError:  # the encoder is gone
            self.abort()
            raise ProcessingError(f"{self.path}: encoding failed ({self._complaint()})") from None
        self.frames_written += 1

    def close(self) -> Path:
        """Finish encoding and move the file into place (or, whatever stops that, remove it)."""
        try:
            if self._pyav is not None:
                self._pyav.close()
            else:
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
        if self._log is not None:
            self._log.close()
        return self.path

    def abort(self) -> None:
        """Stop the encoder, wait until it has exited (it could still create the file), remove the file."""
        if self._pyav is not None:
            self._pyav.abort()
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


_DEFAULT_LAYOUTS = {1: "mono", 2: "stereo", 3: "2.1", 4: "4.0", 5: "5.0", 6: "5.1", 7: "6.1", 8: "7.1"}


class _PyAVEncoder:
    """The ffmpeg command of :meth:`VideoWriter._start_encoder` done in this process with PyAV,
    for machines without an ffmpeg binary: libx264, yuv420p, the same CRF, preset, frame rate,
    ``+faststart`` and tags, and the source's first audio stream copied (or encoded, ``audio``'s
    codec) and cut at ``audio_seconds``, its packets interleaved with the video's as they come.
    Errors are :class:`ProcessingError` naming ``name`` (the final path)."""

    def __init__(self, tmp: Path, name: Path, size: tuple[int, int], fps: float, crf: int, preset: str,
                 audio: tuple[str, str] | None, audio_seconds: float | None, metadata: dict[str, str]):
        import av  # PyAV, loaded with the first video written by it

        self._av, self._name = av, name
        self._out = self._source = None
        self._audio_stream = self._audio_in = self._packets = None
        self._held: tuple[float, list] | None = None  # an audio packet read past the video's time
        try:
            self._out = av.open(str(tmp), "w", options={"movflags": "+faststart"})
            self._rate = Fraction(fps).limit_denominator()
            self._video = self._out.add_stream("libx264", rate=self._rate, options={"crf": str(crf), "preset": preset})
            self._video.width, self._video.height = size
            self._video.pix_fmt = "yuv420p"
            self._video.codec_context.time_base = 1 / self._rate
            for key, value in metadata.items():
                self._out.metadata[key] = value
            if audio is not None:
                self._open_audio(audio[0], audio[1], audio_seconds)
        except (av.error.FFmpegError, OSError, ValueError, IndexError) as exc:
            self.abort()
            raise self._failure(exc) from None
        self._frames = 0

    def _failure(self, exc: BaseException) -> ProcessingError:
        return ProcessingError(f"{self._name}: encoding failed ({getattr(exc, 'strerror', None) or exc})")

    def _open_audio(self, source: str, codec: str, seconds: float | None) -> None:
        av = self._av
        self._source = av.open(source, metadata_errors="replace")
        self._audio_in = self._source.streams.audio[0]
        if codec == "copy":
            self._audio_stream = self._out.add_stream_from_template(self._audio_in)
        else:
            self._audio_stream = self._out.add_stream(codec, rate=self._audio_in.codec_context.sample_rate)
            layout = self._audio_in.codec_context.layout
            # A layout of channels in no known order ("1 channels", pcm in mkv) does not open
            # the AAC encoder: ffmpeg's default layout for that many channels instead.
            if layout.name.endswith("channels"):
                layout = _DEFAULT_LAYOUTS.get(layout.nb_channels, layout)
            self._audio_stream.layout = layout
        # ffmpeg's timeline: the input's timestamps less its start time, cut at -t from there.
        origin = self._source.start_time / av.time_base if self._source.start_time is not None else 0.0
        self._packets = self._audio_packets(codec == "copy", origin, seconds)

    def _audio_packets(self, copy: bool, origin: float, until: float | None):
        """(seconds from the source's start, the output packets) of each audio packet read, in order."""
        stream, out = self._audio_in, self._audio_stream
        shift = int(round(origin / stream.time_base)) if stream.time_base else 0
        for packet in self._source.demux(stream):
            stamp = packet.pts if packet.pts is not None else packet.dts
            if stamp is None:  # the demuxer's empty packet at the end
                continue
            t = float(stamp * stream.time_base) - origin
            if until is not None and t >= until:
                break
            if copy:
                packet.pts = None if packet.pts is None else packet.pts - shift
                packet.dts = None if packet.dts is None else packet.dts - shift
                packet.stream = out
                yield t, [packet]
            else:
                packets = []
                for frame in packet.decode():
                    frame.pts = None  # the encoder counts its samples from zero
                    packets += out.encode(frame)
                yield t, packets
        if not copy:
            yield float("inf"), out.encode(None)

    def _mux_audio(self, until: float) -> None:
        """Mux the audio read so far up to ``until`` seconds (everything: ``inf``)."""
        if self._packets is None:
            return
        while True:
            if self._held is None:
                self._held = next(self._packets, None)
                if self._held is None:
                    self._packets = None
                    return
            if self._held[0] > until:
                return
            self._out.mux(self._held[1])
            self._held = None

    def write(self, frame: np.ndarray, pix_fmt: str) -> None:
        """One frame: RGB (h, w, 3) or yuv420p planes (h * 3 // 2, w), at the even size."""
        av = self._av
        try:
            picture = av.VideoFrame.from_ndarray(frame, format=pix_fmt)
            if pix_fmt != "yuv420p":  # as ffmpeg converts its rawvideo input (swscale's bicubic)
                picture = picture.reformat(format="yuv420p", interpolation="BICUBIC")
            picture.pts, picture.time_base = self._frames, 1 / self._rate
            self._out.mux(self._video.encode(picture))
            self._frames += 1
            self._mux_audio(float(self._frames / self._rate))
        except (av.error.FFmpegError, OSError, ValueError) as exc:
            raise self._failure(exc) from None

    def close(self) -> None:
        """Flush the encoder, the rest of the audio and the trailer."""
        av = self._av
        try:
            self._out.mux(self._video.encode(None))
            self._mux_audio(float("inf"))
            self._out.close()
            self._out = None
        except (av.error.FFmpegError, OSError, ValueError) as exc:
            raise self._failure(exc) from None
        finally:
            self._close_source()

    def abort(self) -> None:
        """Close the files without finishing them (the caller removes the partial file)."""
        self._close_source()
        if self._out is not None:
            with contextlib.suppress(Exception):  # (writing a trailer to a file about to go)
                self._out.close()
            self._out = None

    def _close_source(self) -> None:
        if self._source is not None:
            self._source.close()
            self._source = None
