"""Drone telemetry: DJI SRT, GPX, CSV and MISB ST 0601 KLV, read into one ``FlightLog`` and
aligned to the video's frames.

    log = read_telemetry("flight.SRT")            # or find_telemetry("flight.mp4") for a log inside the video
    aligned = align_to_frames(log, frame_times)    # per-frame interpolated fixes + a report
"""

from __future__ import annotations

from pathlib import Path

from mosaic_cli.errors import BadInput
from mosaic_cli.inputs import VIDEO_SUFFIXES
from mosaic_cli.telemetry.align import AlignedTelemetry, align_to_frames
from mosaic_cli.telemetry.flight_log import FlightLog

__all__ = ["FlightLog", "AlignedTelemetry", "align_to_frames", "read_telemetry", "find_telemetry", "read_photo_folder"]


def read_telemetry(path: str | Path) -> FlightLog:
    """Read a telemetry file, its format from the extension (or its content)."""
    from mosaic_cli.telemetry.klv import UAS_LS_KEY, read_klv
    from mosaic_cli.telemetry.logs import read_csv, read_gpx
    from mosaic_cli.telemetry.srt import looks_like_srt, read_srt

    p = Path(path)
    if not p.exists():
        raise BadInput(f"--telemetry {p}: no such file")
    if p.is_dir():
        raise BadInput(f"--telemetry {p}: a folder, not a telemetry file")
    suffix = p.suffix.lower()
    if suffix in VIDEO_SUFFIXES:
        track = find_telemetry(p)
        if track is None:
            raise BadInput(f"--telemetry {p}: the video holds no subtitle (SRT) or KLV telemetry stream")
        return track
    readers = {".srt": read_srt, ".gpx": read_gpx, ".csv": read_csv, ".klv": read_klv, ".bin": read_klv}
    if suffix in readers:
        return readers[suffix](p)
    head = p.read_bytes()[:4096]
    if UAS_LS_KEY in head:
        return read_klv(p)
    text = head.decode("utf-8", "replace")
    if "<gpx" in text:
        return read_gpx(p)
    if looks_like_srt(text):
        return read_srt(p)
    if "," in text.splitlines()[0] if text.strip() else False:
        return read_csv(p)
    raise BadInput(f"--telemetry {p}: not a telemetry format mosaic reads (DJI .SRT, .gpx, .csv or MISB .klv)")


def find_telemetry(video: str | Path, info=None) -> FlightLog | None:
    """The first telemetry stream inside ``video`` that holds any, else None; for a folder of
    photos, their EXIF GPS (None when no photo has any).  ``info``: the video's probe
    (:func:`mosaic_cli.video.probe`), when the caller has it."""
    from mosaic_cli.telemetry.embedded import find_streams, read_embedded

    if Path(video).is_dir():
        return read_photo_folder(video)

    for stream in find_streams(video, info):
        try:
            return read_embedded(video, stream)
        except BadInput:
            continue  # a subtitle track without telemetry (captions): look further
    return None


def read_photo_folder(folder: str | Path) -> FlightLog | None:
    """The EXIF GPS of a folder's photos as a flight log, None when no photo has a fix: photo i at
    i / rate seconds, the rate the camera took them at (``photo_rate``; the stitch reads the
    folder at it), each photo's tags in ``FlightLog.photos``."""
    from mosaic_cli.telemetry.photos import photo_log, photo_rate, read_photo_tags
    from mosaic_cli.video.folders import folder_images

    tags = [read_photo_tags(p) for p in folder_images(Path(folder))]
    if not any(t.has_fix for t in tags):
        return None
    return photo_log(tags, photo_rate(tags), str(folder))
