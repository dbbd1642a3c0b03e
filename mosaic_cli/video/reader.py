"""Read a video file (anything ffmpeg decodes) or a folder of numbered images as a stream of
RGB uint8 frames, (h, w, 3), one at a time."""

from __future__ import annotations

import contextlib
import logging
import re
import subprocess
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Iterator

import cv2
import imageio_ffmpeg
import numpy as np

from mosaic_cli.errors import BadInput

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp"}
DEFAULT_FOLDER_FPS = 30.0

# imageio-ffmpeg warns on every downscaled read; the size change is what we asked for.
logging.getLogger("imageio_ffmpeg").setLevel(logging.ERROR)


@dataclass(frozen=True)
class VideoInfo:
    """What is known about a video before decoding it.

    ``size`` is the (w, h) of the frames the reader yields (after rotation and any downscale);
    ``source_size`` the (w, h) at full resolution after rotation, which is the resolution every
    homography mosaic reports is expressed in.  ``frame_count`` is an estimate from the
    container's duration (None when unknown).  ``rotation`` is the clockwise turn (0, 90,
    180, 270) the file asks for on display; frames are always yielded upright."""

    path: str
    size: tuple[int, int]
    source_size: tuple[int, int]
    fps: float
    frame_count: int | None
    duration: float
    rotation: int = 0
    audio_codec: str | None = None
    is_image_folder: bool = False
    damage: str | None = None  # ffmpeg's complaint when the end of the file does not decode

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
            raise BadInput(f"{self.info.path}: no decodable frames")
        self.shortfall = account_for_frames(self.info, self.frames_skipped + self.frames_read, self.decode_error)

    def close(self) -> None:
        if self._closer is not None:
            self._closer()
            self._closer = None

    def __enter__(self) -> "VideoStream":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _natural_key(path: Path) -> list:
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", path.name)]


def _folder_images(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()), key=_natural_key)


def _read_image_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise BadInput(f"{path}: not an image OpenCV can read")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _open_folder(folder: Path, width: int | None, fps: float | None, gray: bool) -> VideoStream:
    files = _folder_images(folder)
    if not files:
        raise BadInput(f"{folder}: folder holds no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
    first = _read_image_rgb(files[0])
    source_size = (first.shape[1], first.shape[0])
    size = scaled_size(source_size, width)
    rate = fps or DEFAULT_FOLDER_FPS
    info = VideoInfo(str(folder), size, source_size, rate, len(files), len(files) / rate, is_image_folder=True)

    def frames() -> Iterator[np.ndarray]:
        for k, path in enumerate(files):
            img = first if k == 0 else _read_image_rgb(path)
            if (img.shape[1], img.shape[0]) != source_size:
                raise BadInput(f"{path}: size {img.shape[1]}x{img.shape[0]} differs from the first image's {source_size[0]}x{source_size[1]}")
            if size != source_size:
                img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
            yield cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if gray else img

    return VideoStream(info, frames())


TBR = re.compile(r"Stream #.*Video: .* ([0-9]+(?:\.[0-9]+)?) tbr")
DISPLAY_MATRIX = re.compile(r"Display Matrix: rotation of (-?[0-9.]+) degrees")
# What ffmpeg says when the data ends before the container says it should.
DAMAGE_SIGNS = ("partial file", "ended prematurely", "invalid data", "invalid nal", "corrupt", "truncat", "error while decoding")


@dataclass(frozen=True)
class _TailCheck:
    rotation: int  # clockwise degrees, like the old ``rotate`` tag phones write
    damage: str | None  # ffmpeg's complaint when the last half second does not decode
    tbr: float | None  # ffmpeg's guess of the stream's base frame rate


def _check_tail(path: str, duration: float) -> _TailCheck:
    """Decode one frame near the end (cheap: ffmpeg seeks there) to catch truncated files
    before any long work, and read the display rotation from ffmpeg's stream header
    (imageio-ffmpeg only knows the old ``rotate`` tag, which ffmpeg no longer prints)."""
    seek = ["-sseof", "-0.5"] if duration > 0.5 else []
    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-nostdin", *seek, "-i", path,
           "-map", "0:v:0", "-frames:v", "1", "-f", "rawvideo", "-pix_fmt", "gray", "-"]
    try:
        run = subprocess.run(cmd, capture_output=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return _TailCheck(0, None, None)
    log = run.stderr.decode("utf-8", "replace")
    match = DISPLAY_MATRIX.search(log)
    # ffmpeg's display matrix angle is counter-clockwise; report the clockwise rotation.
    rotation = int(round(-float(match.group(1)))) % 360 if match else 0
    damage = None
    if not run.stdout:
        lines = [ln.strip() for ln in log.splitlines() if any(sign in ln.lower() for sign in DAMAGE_SIGNS)]
        if lines:
            damage = re.sub(r"^(\[[^]]*\] ?)+", "", lines[0])
    tbr = TBR.search(log)
    return _TailCheck(rotation, damage, float(tbr.group(1)) if tbr else None)


def _ffmpeg_frames(path: str, size: tuple[int, int], source_size: tuple[int, int], gray: bool, start: int = 0):
    output_params: list[str] = []
    filters = []
    if start:
        filters.append(f"select=gte(n\\,{int(start)})")
    if size != source_size:
        filters.append(f"scale={size[0]}:{size[1]}:flags=area")
    if filters:
        output_params += ["-vf", ",".join(filters)]
    # Every decoded frame exactly once: ffmpeg's default for a pipe would resample a variable
    # frame rate to a constant one, duplicating and dropping frames.
    output_params += ["-fps_mode", "passthrough"]
    pix_fmt, bpp = ("gray", 8) if gray else ("rgb24", 24)
    gen = imageio_ffmpeg.read_frames(path, pix_fmt=pix_fmt, bits_per_pixel=bpp, output_params=output_params)
    next(gen)  # metadata, already known
    shape = (size[1], size[0]) if gray else (size[1], size[0], 3)
    return gen, shape


def probe(path: str | Path) -> VideoInfo:
    """Metadata of a video file or image folder, with user-facing errors for bad input."""
    p = Path(path)
    if not p.exists():
        raise BadInput(f"{p}: no such file or folder")
    if p.is_dir():
        with _open_folder(p, None, None, False) as stream:
            return stream.info
    if p.stat().st_size == 0:
        raise BadInput(f"{p}: file is empty")
    try:
        gen = imageio_ffmpeg.read_frames(str(p))
        meta = next(gen)
        gen.close()
    except (OSError, RuntimeError, IndexError, AttributeError, ValueError, StopIteration) as exc:
        raise BadInput(f"{p}: not a video ffmpeg can read") from exc
    # ffmpeg applies the display rotation while decoding: "size" is already upright.
    size = tuple(int(v) for v in meta["size"])
    duration = float(meta.get("duration") or 0.0)
    tail = _check_tail(str(p), duration)
    fps = float(meta.get("fps") or 0.0)
    if tail.tbr and not 0.5 < fps / tail.tbr < 2.0:
        # An average rate far from the stream's base rate is a muxing artefact (h264 copied
        # into avi reports 600 fps at 30 tbr); the base rate is the one to play at.
        fps = tail.tbr
    fps = fps or DEFAULT_FOLDER_FPS
    announced = container_frames(p)
    count = int(round(duration * fps)) if duration > 0 else None
    if announced.fps is not None and abs(announced.fps - fps) < 0.01:
        # The container's figures where its rate is the stream's (an avi of copied h264
        # announces 600 fps and 20 times the frames): the exact rate (ffmpeg's log rounds to 2
        # decimals, 23.98 for 24000/1001) and the frame count, which may include frames an
        # edit list leaves out (a clip cut without re-encoding): the smaller of the two.
        fps = announced.fps
        if announced.frames:
            count = min(announced.frames, count) if count else announced.frames
    if tail.damage and _policy["strict"]:  # known before any work: refuse at once
        said = f"; the container announces {count} frames" if count else ""
        raise BadInput(f"{p}: truncated or damaged video ({tail.damage}{said}); --strict refuses it")
    return VideoInfo(str(p), size, size, fps, count, duration, tail.rotation, meta.get("audio_codec"),
                     damage=tail.damage)


@dataclass(frozen=True)
class ContainerCount:
    """What the container itself says of its video stream."""

    frames: int | None  # the frame count it announces (exact in mp4/mov/avi; else from the duration)
    fps: float | None  # the average frame rate, unrounded


def container_frames(path: str | Path) -> ContainerCount:
    """The video stream's announced frame count and exact average rate (OpenCV's FFmpeg
    backend reads them from the stream header; ffmpeg's log prints rounded figures only)."""
    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    try:
        if not capture.isOpened():
            return ContainerCount(None, None)
        frames = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(capture.get(cv2.CAP_PROP_FPS))
    finally:
        capture.release()
    return ContainerCount(frames if frames > 0 else None, fps if fps > 0 else None)


def open_video(
    path: str | Path,
    width: int | None = None,
    gray: bool = False,
    fps: float | None = None,
    start: int = 0,
) -> VideoStream:
    """Open ``path`` (a video file or a folder of numbered images) as a stream of frames.

    ``width`` downscales inside the decoder (aspect kept); ``gray`` yields (h, w) uint8 frames
    instead of RGB; ``fps`` overrides the frame rate of an image folder; ``start`` skips frames.
    """
    p = Path(path)
    if p.is_dir():
        stream = _open_folder(p, width, fps, gray)
        if start:
            stream._frames = (f for k, f in enumerate(stream._frames) if k >= start)
        return stream
    info = probe(p)
    size = scaled_size(info.source_size, width)
    info = replace(info, size=size)
    try:
        gen, shape = _ffmpeg_frames(str(p), size, info.source_size, gray, start)
    except (OSError, RuntimeError, StopIteration) as exc:
        raise BadInput(f"{p}: not a video ffmpeg can read") from exc

    def frames() -> Iterator[np.ndarray]:
        try:
            for raw in gen:
                yield np.frombuffer(raw, dtype=np.uint8).reshape(shape)
        except RuntimeError as exc:
            # A truncated stream: ffmpeg delivered what it could decode; stop there (and say so).
            stream.decode_error = str(exc).strip().splitlines()[-1] if str(exc).strip() else "decoder error"
            return

    stream = VideoStream(info, frames(), gen.close)
    stream.frames_skipped = int(start)  # (a start past the end reads no frame, and says so)
    return stream


# --- Frames missing at the end: decoded fewer than the container announced -------------------
# The run goes on with what decoded, after one warning line; under ``reading_policy(strict=True)``
# (the commands' --strict) it is an error instead.  What was found is kept per path for the
# outputs' metadata (:func:`shortfalls`).

SHORTFALL_TOLERANCE = 2  # frames: rounding of a duration-based count, an edit list's last frame
EXACT_COUNT_SUFFIXES = {".mp4", ".mov", ".m4v", ".3gp", ".avi"}  # containers that store the count itself
_policy: dict = {"strict": False}
_shortfalls: dict[str, "Shortfall"] = {}


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
