"""Every video file mosaic reads goes through here: :func:`probe` says what a file holds,
:func:`open_video` streams its frames (or a folder of numbered images' frames), one at a time.

Probing opens the file in-process with PyAV (libav's own structures: the exact rates, the
display matrix, every stream and its codec), once per command: the :class:`VideoInfo` is passed
down to whatever reads the file next, so nothing probes it again.  Decoding runs the bundled
ffmpeg (imageio-ffmpeg's binary) on a pipe: a process of its own decodes the next frame while
mosaic works on this one (docs/developer/video.md has the measured rates of both ways)."""

from __future__ import annotations

import contextlib
import fcntl
import re
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.errors import BadInput

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp"}
DEFAULT_FOLDER_FPS = 30.0
PIXELS = ("rgb", "gray", "yuv420p")


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


class VideoStream:
    """An iterable, closeable stream of frames; use as a context manager."""

    def __init__(self, info: VideoInfo, frames: Iterator[np.ndarray], closer=None):
        self.info = info
        self._frames = frames
        self._closer = closer
        self.frames_read = 0
        self.frames_skipped = 0  # by ``start``: decoded, not yielded
        self.decode_error: str | None = None  # set when the decoder stopped with an error
        self.shortfall: Shortfall | None = None  # set when read to the end and short of the count

    def __iter__(self) -> Iterator[np.ndarray]:
        for frame in self._frames:
            self.frames_read += 1
            yield frame
        if self.frames_read == 0:
            why = f" ({self.decode_error})" if self.decode_error else ""
            raise BadInput(f"{self.info.path}: no decodable frames{why}")
        self.shortfall = account_for_frames(self.info, self.frames_skipped + self.frames_read, self.decode_error)

    def close(self) -> None:
        if self._closer is not None:
            self._closer()
            self._closer = None

    def __enter__(self) -> VideoStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --- A folder of numbered images -------------------------------------------------------------


def _natural_key(path: Path) -> list:
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", path.name)]


def folder_images(folder: Path) -> list[Path]:
    """The images of ``folder`` in natural order (frame_2 before frame_10)."""
    return sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()), key=_natural_key)


def read_image_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise BadInput(f"{path}: not an image OpenCV can read")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _open_folder(folder: Path, width: int | None, fps: float | None, gray: bool) -> VideoStream:
    files = folder_images(folder)
    if not files:
        raise BadInput(f"{folder}: folder holds no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
    first = read_image_rgb(files[0])
    source_size = (first.shape[1], first.shape[0])
    size = scaled_size(source_size, width)
    rate = fps or DEFAULT_FOLDER_FPS
    info = VideoInfo(str(folder), size, source_size, rate, len(files), len(files) / rate, is_image_folder=True)

    def frames() -> Iterator[np.ndarray]:
        for k, path in enumerate(files):
            img = first if k == 0 else read_image_rgb(path)
            if (img.shape[1], img.shape[0]) != source_size:
                raise BadInput(f"{path}: size {img.shape[1]}x{img.shape[0]} differs from the first image's {source_size[0]}x{source_size[1]}")
            if size != source_size:
                img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
            yield cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if gray else img

    return VideoStream(info, frames())


# --- Probing: what a file holds, read once ---------------------------------------------------

# The end of the file is decoded from this long before it, to catch a truncated file before any work.
TAIL_SECONDS = 0.5
# What libav says when the data ends before the container says it should.
DAMAGE_SIGNS = ("partial file", "ended prematurely", "invalid data", "invalid nal", "corrupt", "truncat", "error while decoding")


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


def probe(path: str | Path) -> VideoInfo:
    """What a video file or image folder holds, with user-facing errors for bad input.

    A command probes its input once and passes the result down (``info=`` of the readers)."""
    p = Path(path)
    if not p.exists():
        raise BadInput(f"{p}: no such file or folder")
    if p.is_dir():
        with _open_folder(p, None, None, False) as stream:
            return stream.info
    if p.stat().st_size == 0:
        raise BadInput(f"{p}: file is empty")
    import av  # PyAV, loaded with the first video probed (start-up, image folders need none)

    try:
        container = av.open(str(p), metadata_errors="replace")
    except (av.error.FFmpegError, OSError, ValueError) as exc:
        raise BadInput(f"{p}: not a video ffmpeg can read") from exc
    with container:
        info = _probe_container(p, container)
    refuse_damaged(info)
    return info


def refuse_damaged(info: VideoInfo) -> None:
    """Under --strict (:func:`reading_policy`), a video whose end the probe found damaged is
    refused before any work; otherwise nothing (the shortfall is said once decoded)."""
    if info.damage and _policy["strict"]:
        said = f"; the container announces {info.frame_count} frames" if info.frame_count else ""
        raise BadInput(f"{info.path}: truncated or damaged video ({info.damage}{said}); --strict refuses it")


def _probe_container(p: Path, container) -> VideoInfo:
    import av  # PyAV, loaded with the first video probed (start-up, image folders)
    video = _main_video_stream(container)
    if video is None:
        raise BadInput(f"{p}: not a video ffmpeg can read (no video stream)")
    first, complaint = _first_frame(container, video)
    if first is None:
        why = f": {complaint}" if complaint else ""
        raise BadInput(f"{p}: not a video ffmpeg can read (no frame decodes{why})")
    # ffmpeg turns the frames upright while decoding (its display-matrix angle is counter-clockwise).
    rotation = int(round(-first.rotation)) % 360
    w, h = first.width, first.height
    size = (h, w) if rotation in (90, 270) else (w, h)
    fps, average_is_real = _frame_rate(video)
    start = container.start_time / av.time_base if container.start_time is not None else 0.0
    if container.duration:
        duration = container.duration / av.time_base
    elif video.duration and video.time_base:
        duration = float(video.duration * video.time_base)
    else:
        duration = 0.0
    count = int(round(duration * fps)) if duration > 0 else None
    if average_is_real and video.frames > 0:
        # The container's own count (exact in mp4/mov/avi) may include frames an edit list
        # leaves out (a clip cut without re-encoding): the smaller of the two.
        count = min(video.frames, count) if count else video.frames
    damage = _damage_at_the_end(container, video, start + duration, fps) if duration > 0 else None
    if count and not video.frames and first.time is not None and damage is None:
        # A duration-based count (mkv, webm) counts the longest stream: an audio track that runs
        # on past the last picture adds frames.  The last video timestamp, read from the packets
        # near the end (demuxed, not decoded), bounds it.  (Not for a damaged end: the count
        # announced is what tells a truncated file.)
        last = _last_video_time(container, video, start + duration)
        if last is not None and last >= first.time:
            count = min(count, int(round((last - first.time) * fps)) + 1)
    others = tuple(_stream_meta(s) for s in container.streams if s.index != video.index)
    audio = next((s.codec for s in others if s.kind == "audio"), None)
    return VideoInfo(str(p), size, size, fps, count, duration, rotation, audio, damage=damage,
                     stream_index=video.index, streams=others)


def audio_codec_of(path: str | Path) -> str | None:
    """The codec of the first audio stream of any media file (a sound file too); None when it
    has none or libav cannot open it."""
    import av  # PyAV, loaded with the first video probed (start-up, image folders)
    try:
        with av.open(str(path), metadata_errors="replace") as container:
            return next((s.codec_context.name for s in container.streams.audio if s.codec_context is not None), None)
    except (av.error.FFmpegError, OSError, ValueError):
        return None


def _main_video_stream(container):
    """The video stream ffmpeg would pick: the largest picture, cover art (attached pictures) last."""
    import av  # PyAV, loaded with the first video probed (start-up, image folders)
    streams = [s for s in container.streams.video if s.codec_context is not None]
    if not streams:
        return None

    def score(s) -> tuple:
        cover = bool(s.disposition & av.stream.Disposition.attached_pic)
        return (not cover, (s.codec_context.width or 0) * (s.codec_context.height or 0), -s.index)

    return max(streams, key=score)


def _frame_rate(video) -> tuple[float, bool]:
    """(the rate to play at, whether it is the average rate): the average rate, unless it is
    far from the stream's base rate, which is then a muxing artefact (h264 copied into avi
    averages 600 fps at a 30 fps base rate)."""
    average = float(video.average_rate) if video.average_rate else 0.0
    base = float(video.base_rate) if video.base_rate else 0.0
    if average and (not base or 0.5 < average / base < 2.0):
        return average, True
    return (base or DEFAULT_FOLDER_FPS), False


@contextlib.contextmanager
def _libav_log() -> Iterator[list]:
    """libav's warnings and errors meanwhile, as (level, context, message) tuples, instead of
    nowhere (PyAV's default) and instead of Python's logging (which would print them)."""
    import av  # PyAV, loaded with the first video probed (start-up, image folders)
    level, repeated = av.logging.get_level(), av.logging.get_skip_repeated()
    try:
        with av.logging.Capture(local=False) as logs:
            av.logging.set_skip_repeated(False)
            av.logging.set_level(av.logging.WARNING)
            yield logs
    finally:
        av.logging.set_level(level)
        av.logging.set_skip_repeated(repeated)


def _complaint(logs: list, error: Exception | None, signs: Sequence[str] = ()) -> str | None:
    """The first logged line that says what went wrong (one with a damage sign when ``signs``),
    else the error raised."""
    for _, _, message in logs:
        text = message.strip()
        if text and (not signs or any(sign in text.lower() for sign in signs)):
            return text
    if error is not None:
        return getattr(error, "strerror", None) or str(error)
    return None


def _first_frame(container, video):
    """(the first decodable frame or None, libav's complaint when there is none)."""
    import av  # PyAV, loaded with the first video probed (start-up, image folders)
    error: Exception | None = None
    with _libav_log() as logs:
        try:
            for frame in container.decode(video):
                return frame, None
        except av.error.FFmpegError as exc:
            error = exc
    return None, _complaint(logs, error)


def _damage_at_the_end(container, video, end: float, fps: float) -> str | None:
    """libav's complaint when no frame decodes in the last :data:`TAIL_SECONDS` the container
    announces (cheap: a seek there, then at most a keyframe interval decoded); None when one does."""
    import av  # PyAV, loaded with the first video probed (start-up, image folders)
    target = end - TAIL_SECONDS
    error: Exception | None = None
    with _libav_log() as logs:
        try:
            if target > 0 and video.time_base:
                container.seek(int(target / video.time_base), stream=video, backward=True)
            else:
                container.seek(0)
            for frame in container.decode(video):
                if frame.time is None or frame.time >= target - 0.5 / fps:
                    return None
        except av.error.FFmpegError as exc:
            error = exc
    # No frame there and no complaint: the container's duration is another stream's (a longer audio track).
    return _complaint(logs, error, DAMAGE_SIGNS)


def _last_video_time(container, video, end: float) -> float | None:
    """The presentation time of the last video packet in the container's final seconds (None
    when none is found there or libav fails): read by demuxing only, from a seek near the end."""
    import av  # PyAV, loaded with the first video probed (start-up, image folders)
    if not video.time_base:
        return None
    last = None
    with _libav_log():
        try:
            container.seek(int(max(end - 2 * TAIL_SECONDS, 0.0) / video.time_base), stream=video, backward=True)
            for packet in container.demux(video):
                if packet.pts is not None and packet.size:
                    time = float(packet.pts * video.time_base)
                    last = time if last is None else max(last, time)
        except av.error.FFmpegError:
            return None
    return last


def _stream_meta(stream) -> StreamMeta:
    context = stream.codec_context  # (none for a data stream, whose codec only has a name)
    codec = (context.name if context is not None else None) or getattr(stream, "name", None) or "none"
    tag = getattr(stream, "codec_tag", "") or ""
    return StreamMeta(stream.index, stream.type, codec, tag.strip("\x00"))


# --- Decoding: the bundled ffmpeg on a pipe --------------------------------------------------

_PIX_FMT = {"rgb": "rgb24", "gray": "gray", "yuv420p": "yuv420p"}


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
                 select: str | None = None, seek: float | None = None, frames: int | None = None):
        if pixels not in PIXELS:
            raise ValueError(f"pixels must be one of {', '.join(PIXELS)}, got {pixels}")
        self.size = size or info.source_size
        if pixels == "yuv420p" and (self.size != info.source_size or self.size[0] % 2 or self.size[1] % 2):
            raise ValueError(f"yuv420p frames are read at the source size, even only; got {self.size}")
        self.shape = frame_shape(pixels, self.size)
        self.error: str | None = None
        cmd = [ffmpeg_exe(), "-hide_banner", "-nostdin", "-loglevel", "error"]
        if seek is not None:
            cmd += ["-ss", f"{seek:.4f}"]
        stream = f"0:{info.stream_index}" if info.stream_index is not None else "0:v:0"
        cmd += ["-i", info.path, "-map", stream]
        filters = [select] if select else []
        if self.size != info.source_size:
            filters.append(f"scale={self.size[0]}:{self.size[1]}:flags=area")
        if filters:
            cmd += ["-vf", ",".join(filters)]
        if frames is not None:
            cmd += ["-frames:v", str(int(frames))]
        # Every decoded frame exactly once: ffmpeg's default for a pipe would resample a
        # variable frame rate to a constant one, duplicating and dropping frames.
        cmd += ["-fps_mode", "passthrough", "-f", "rawvideo", "-pix_fmt", _PIX_FMT[pixels], "pipe:1"]
        self._log = tempfile.TemporaryFile()  # ffmpeg's complaints
        try:
            # Its own session: the terminal's Ctrl-C reaches mosaic alone, which then stops it.
            self._proc: subprocess.Popen | None = subprocess.Popen(
                cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=self._log, start_new_session=True, bufsize=0)
        except OSError as exc:
            self._log.close()
            raise BadInput(f"{info.path}: cannot start ffmpeg ({exc.strerror})") from None
        _widen_pipe(self._proc.stdout, int(np.prod(self.shape)))

    def __iter__(self) -> Iterator[np.ndarray]:
        assert self._proc is not None and self._proc.stdout is not None
        pipe = self._proc.stdout
        nbytes = int(np.prod(self.shape))
        got = 0
        while True:
            frame = np.empty(self.shape, np.uint8)
            got = read_into(pipe, memoryview(frame.reshape(-1)))
            if got < nbytes:
                break
            yield frame
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
) -> VideoStream:
    """Open ``path`` (a video file or a folder of numbered images) as a stream of frames.

    ``width`` downscales inside the decoder (aspect kept); ``gray`` yields (h, w) uint8 frames
    instead of RGB; ``yuv420p`` (video files of even size, no ``width``) the planes as ffmpeg
    decodes them, (h * 3 // 2, w), with no conversion; ``fps`` overrides the frame rate of an
    image folder; ``start`` skips frames.  ``info``: the file's :func:`probe`, when the caller
    has it (else it is probed here).
    """
    p = Path(path)
    if p.is_dir():
        if yuv420p:
            raise ValueError("yuv420p frames are read from video files only")
        stream = _open_folder(p, width, fps, gray)
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
    decoder = Decoder(info, pixels, size, select=f"select=gte(n\\,{int(start)})" if start else None)

    def frames() -> Iterator[np.ndarray]:
        yield from decoder
        stream.decode_error = decoder.error

    stream = VideoStream(info, frames(), decoder.close)
    stream.frames_skipped = int(start)  # (a start past the end reads no frame, and says so)
    return stream


def frames_at(info: VideoInfo, indices: Sequence[int], width: int | None = None) -> Iterator[np.ndarray]:
    """The RGB frames of ``indices`` (sorted), in one decoder pass that converts and pipes only
    those (ffmpeg's select filter), yielded as they come; fewer when the file ends first."""
    if len(indices) == 0:
        return
    picks = "+".join(f"eq(n\\,{int(k)})" for k in indices)
    with Decoder(info, "rgb", scaled_size(info.source_size, width), select=f"select='{picks}'") as decoder:
        yield from decoder


def frame_at(info: VideoInfo, seconds: float, width: int | None = None) -> np.ndarray | None:
    """The first RGB frame at or after ``seconds`` (ffmpeg seeks to the keyframe before it and
    decodes from there), None when there is none."""
    with Decoder(info, "rgb", scaled_size(info.source_size, width), seek=seconds, frames=1) as decoder:
        return next(iter(decoder), None)


# --- Frames missing at the end: decoded fewer than the container announced -------------------
# The run goes on with what decoded, after one warning line; under ``reading_policy(strict=True)``
# (the commands' --strict) it is an error instead.  What was found is kept per path for the
# outputs' metadata (:func:`shortfalls`).

SHORTFALL_TOLERANCE = 2  # frames: rounding of a duration-based count, an edit list's last frame
EXACT_COUNT_SUFFIXES = {".mp4", ".mov", ".m4v", ".3gp", ".avi"}  # containers that store the count itself
_policy: dict = {"strict": False}
_shortfalls: dict[str, Shortfall] = {}


@dataclass(frozen=True)
class Shortfall:
    """A video that decoded to fewer frames than its container announced."""

    path: str
    decoded: int
    announced: int
    reason: str | None = None  # ffmpeg's complaint, when it made one

    def message(self) -> str:
        why = f" ({self.reason})" if self.reason else ""
        return (f"{self.path}: decoded {self.decoded} of the {self.announced} frames the container announces: "
                f"truncated or damaged{why}")

    def as_meta(self) -> dict:
        """For the outputs' metadata: ``{"frames_decoded", "frames_announced", "truncated", "reason"}``."""
        return {"frames_decoded": self.decoded, "frames_announced": self.announced, "truncated": True,
                "reason": self.reason}


@contextlib.contextmanager
def reading_policy(strict: bool = False) -> Iterator[None]:
    """For one command's run: whether a short video is an error (``strict``) or a warning; also
    forgets what earlier runs in this process found."""
    previous = dict(_policy)
    _policy["strict"] = bool(strict)
    _shortfalls.clear()
    try:
        yield
    finally:
        _policy.update(previous)


def shortfalls() -> dict[str, Shortfall]:
    """Each video of this run found short, by path."""
    return dict(_shortfalls)


def account_for_frames(info: VideoInfo, decoded: int, decode_error: str | None = None) -> Shortfall | None:
    """Compare the frames decoded to the end with those the container announced.

    Short by more than :data:`SHORTFALL_TOLERANCE`: under --strict a BadInput; else one warning
    line on stderr (once per video and run) and the :class:`Shortfall`.  A count worked out from
    the container's duration (mkv, webm) can exceed the video where the audio runs longer, so
    there a complaint from ffmpeg is also needed."""
    if info.is_image_folder or not info.frame_count:
        return None
    exact = Path(info.path).suffix.lower() in EXACT_COUNT_SUFFIXES
    reason = info.damage or decode_error
    if info.frame_count - decoded <= SHORTFALL_TOLERANCE or not (exact or reason or not info.has_audio):
        return None
    found = Shortfall(info.path, decoded, info.frame_count, reason)
    if _policy["strict"]:
        raise BadInput(f"{found.message()}; --strict refuses it")
    if info.path not in _shortfalls:
        _shortfalls[info.path] = found
        sys.stderr.write(f"mosaic: warning: {found.message()}; going on with the {decoded} decoded\n")
        sys.stderr.flush()
    return found
