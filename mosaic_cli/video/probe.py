"""Probing: what a video file holds, read once.

:func:`probe` opens the file in-process with PyAV (libav's own structures: the exact rates, the
display matrix, every stream and its codec), once per command: the :class:`VideoInfo` is passed
down to whatever reads the file next, so nothing probes it again.  It also decodes the end of
the file, to catch a truncated one before any long work (docs/developer/video.md)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from pathlib import Path

from mosaic_cli.errors import BadInput
from mosaic_cli.video.folders import DEFAULT_FOLDER_FPS, open_folder
from mosaic_cli.video.info import StreamMeta, VideoInfo
from mosaic_cli.video.policy import refuse_damaged

# The end of the file is decoded from this long before it, to catch a truncated file before any work.
TAIL_SECONDS = 0.5
# What libav says when the data ends before the container says it should.
DAMAGE_SIGNS = ("partial file", "ended prematurely", "invalid data", "invalid nal", "corrupt", "truncat", "error while decoding")



def probe(path: str | Path) -> VideoInfo:
    """What a video file or image folder holds, with user-facing errors for bad input.

    A command probes its input once and passes the result down (``info=`` of the readers)."""
    p = Path(path)
    if not p.exists():
        raise BadInput(f"{p}: no such file or folder")
    if p.is_dir():
        with open_folder(p, None, None, False) as stream:
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
                     stream_index=video.index, streams=others, video_codec=video.codec_context.name if video.codec_context else None,
                     pixel_format=first.format.name, color_matrix=_code(first, "colorspace"), color_range=_code(first, "color_range"))


def _code(frame, name: str) -> int | None:
    """libav's integer code of a frame's colour property (PyAV gives ints or enums)."""
    value = getattr(frame, name, None)
    try:
        return int(value) if value is not None else None
    except (TypeError, ValueError):
        return None


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
