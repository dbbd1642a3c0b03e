"""How mosaic recognises its inputs, one rule each: what counts as a video file, where the
simulated flights of a folder are (``X.<video>`` with ``X.gt.json`` beside it), how a
``WxH`` size is written, and the bounds of the flags several commands share (``--max-frames``,
``--threads``, ``--timeout``), which their options' ``validate()`` apply.  (The encoder's
``--crf`` and ``--preset`` are ``video.writer``'s; a ``--mask`` image is checked against the input
by ``overlay.check_mask_file``.)"""

from __future__ import annotations

import os
import re
from pathlib import Path

from mosaic_cli.errors import BadInput

# Containers ffmpeg reads that a drone or an editor writes: a folder scan takes these and no
# others, and a ``--telemetry`` file with one of them is a video whose embedded track is read.
# (What mosaic writes is narrower: ``video.writer.OUTPUT_SUFFIXES``.)
VIDEO_SUFFIXES = frozenset(
    {".mp4", ".mov", ".mkv", ".avi", ".webm", ".m4v", ".mpg", ".mpeg", ".ts", ".mts", ".m2ts", ".wmv", ".flv"}
)


# A live input ends when it sends nothing for this long (``--timeout``, seconds).
DEFAULT_TIMEOUT = 10.0

def is_video_file(path: str | Path) -> bool:
    """A visible file whose suffix is one of :data:`VIDEO_SUFFIXES` (any case)."""
    p = Path(path)
    return p.suffix.lower() in VIDEO_SUFFIXES and not p.name.startswith(".")


def ground_truth_path(video_path: str | Path) -> Path:
    """flight.mp4 -> flight.gt.json (beside the video); a folder of frames flight/ -> flight.gt.json."""
    p = Path(video_path)
    return p.with_name((p.name if p.is_dir() else p.stem) + ".gt.json")


def find_flights(folder: str | Path, flag: str) -> list[Path]:
    """Every video in ``folder`` (not its subfolders) with a ``.gt.json`` ground truth beside it
    (``mosaic simulate`` writes both), sorted by name; videos without one are left out.  A
    folder of frames ``X/`` with an ``X.gt.json`` beside it is a flight too.
    BadInput, naming the user's ``flag``, when ``folder`` is not a folder or holds no flight."""
    root = Path(folder)
    if not root.is_dir():
        raise BadInput(f"{flag} {root}: not a folder")
    videos = sorted(p for p in root.iterdir() if (is_video_file(p) and p.is_file()) or p.is_dir())
    flights = [v for v in videos if ground_truth_path(v).is_file()]
    if not flights:
        raise BadInput(f"{flag} {root}: no video (X.mp4, X.mov, ...) with an X.gt.json beside it "
                       "(make some with mosaic simulate)")
    return flights


def parse_size(text: str, flag: str, low: int = 16, high: int = 8192) -> tuple[int, int]:
    """``"1280x720"`` -> (1280, 720); each side must lie in [``low``, ``high``] pixels.
    BadInput naming the user's ``flag`` otherwise."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", str(text))
    if not m:
        raise BadInput(f"{flag} must look like 1280x720, got {text!r}")
    w, h = int(m.group(1)), int(m.group(2))
    if not (low <= w <= high and low <= h <= high):
        raise BadInput(f"{flag} must be between {low}x{low} and {high}x{high}, got {w}x{h}")
    return w, h


def check_max_frames(frames: int | None) -> None:
    """``--max-frames``: None (every frame) or at least a pair."""
    if frames is not None and frames < 2:
        raise BadInput(f"--max-frames must be at least 2, got {frames}")


def check_threads(threads: int | None) -> None:
    """``--threads``: None (torch's default) or at least one."""
    if threads is not None and threads < 1:
        raise BadInput(f"--threads must be at least 1, got {threads}")


def check_timeout(seconds: float) -> None:
    """``--timeout`` of a live input: a positive number of seconds."""
    if not seconds > 0:
        raise BadInput(f"--timeout must be positive, got {seconds}")


__all__ = ["DEFAULT_TIMEOUT", "VIDEO_SUFFIXES", "check_max_frames", "check_threads", "check_timeout", "find_flights", "ground_truth_path", "is_video_file", "parse_size"]


# What an output's name makes it (stitch's panorama, geo's maps): PNG, JPEG or TIFF by extension;
# outputs only a map can be (they need the mosaic's place on the ground: telemetry); "tiles" is
# a folder of web tiles, given as DIR/ (a trailing slash) or an existing folder.
FORMATS = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg", ".tif": "tiff", ".tiff": "tiff", ".kmz": "kmz", ".mbtiles": "mbtiles",
           ".pmtiles": "pmtiles"}
MAP_FORMATS = {"kmz": "KMZ", "mbtiles": "MBTiles", "pmtiles": "PMTiles", "tiles": "web tiles"}


def output_format(out: str | Path) -> str | None:
    """The output's format by its extension; "tiles" for a folder (a trailing slash, or one that
    exists); None for an extension no writer has."""
    if str(out).endswith(("/", os.sep)) or Path(out).is_dir():
        return "tiles"
    return FORMATS.get(Path(out).suffix.lower())


def check_weights_file(path: str | os.PathLike) -> Path:
    """A weights file the user named: it must be a file (one ``BadInput`` line otherwise).
    Without torch, so that a command refuses it before anything loads."""
    p = Path(path)
    if p.is_dir():
        raise BadInput(f"{p}: a folder, not a weights file (.safetensors)")
    if not p.is_file():
        raise BadInput(f"{p}: no such weights file")
    return p
