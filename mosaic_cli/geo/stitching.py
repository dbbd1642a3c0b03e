"""The georeferencing hooks of ``stitch()``: find the telemetry before any work, lay the
registered keyframes on the ground, write the georeferenced outputs."""

from __future__ import annotations

import contextlib
import glob
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from mosaic_cli.atomic import check_writable, private_folder
from mosaic_cli.errors import BadInput, require_geo
from mosaic_cli.geo.georef import Georeference, GeorefOptions
from mosaic_cli.geometry import normalize
from mosaic_cli.telemetry import FlightLog, find_telemetry, read_telemetry
from mosaic_cli.video import VideoInfo


def georef_telemetry(video: str | Path, out: str | Path, options: GeorefOptions | None, span: tuple[float, float] | None = None,
                     info: VideoInfo | None = None) -> FlightLog | None:
    """The telemetry to georeference with: the file given, else a track inside the video, else
    the DJI log beside it (``sidecar_log``; None when there is none, or when the track inside
    holds no GPS, e.g. captions), with the outputs that
    need it checked before any work.  (Not ``mosaic_cli.track.load_track``, which reads a
    track JSON back.)  ``span``: the seconds of video to stitch, when known, to refuse a log
    that misses them before any work; ``info``: the video's probe (its streams are where an
    embedded track is looked for)."""
    if options is None:
        check_plain_output(out, "--telemetry none was given")
        return None
    for flag, path in (("--footprints", options.footprints), ("--html", options.html)):
        if path is not None:
            check_writable(path)
            if Path(path).resolve() == Path(out).resolve():
                raise BadInput(f"{flag} must differ from the panorama output")
    if options.footprints is not None and options.html is not None and Path(options.footprints).resolve() == Path(options.html).resolve():
        raise BadInput("--html must differ from --footprints")
    photos = Path(video).is_dir()
    if photos and options.telemetry is not None:
        raise BadInput(f"--telemetry {options.telemetry}: a photo folder's positions are its photos' EXIF GPS; "
                       f"--telemetry none stitches it without them")
    if options.telemetry is not None:
        track = read_telemetry(options.telemetry)
    else:
        track = find_telemetry(video, info)
    wanted = map_output_flag(out) + options.without_telemetry()
    if track is None and options.telemetry is None and (beside := sidecar_log(video)) is not None:
        try:
            track = read_telemetry(beside)
        except BadInput:
            if wanted:  # a map was asked for: what is wrong with the log beside is the answer
                raise
            # else subtitles that are no flight log (captions), or a damaged one: a plain panorama, as without it
    if track is None and wanted:
        if photos:
            raise BadInput(f"{wanted[0]} needs GPS (no photo in {video} has EXIF GPS)")
        raise BadInput(f"{wanted[0]} needs telemetry: give --telemetry (no SRT or KLV track inside {video}, "
                       f"and no {Path(video).stem}.SRT beside it)")
    if track is not None and not track.has_fix.any():
        if options.telemetry is None and not wanted:
            return None  # an embedded track without positions: a plain panorama, as without one
        raise BadInput(f"{track.source}: no GPS fix in its {len(track)} samples (all without coordinates)")
    if track is not None:
        require_geo()  # a map will be made: its packages are checked before any work
    if track is not None and span is not None and span[1] > span[0]:
        fixed = track.time[track.has_fix] + options.offset
        covered = max(0.0, min(span[1], fixed.max()) - max(span[0], fixed.min()))
        if covered < options.min_coverage * (span[1] - span[0]):
            raise BadInput(
                f"{track.source}: the telemetry does not cover the video: fixes span {fixed.min():.1f}-{fixed.max():.1f} s, "
                f"the video {span[0]:.1f}-{span[1]:.1f} s; check --telemetry-offset"
            )
    return track


def sidecar_log(video: str | Path) -> Path | None:
    """The DJI log a drone writes beside its video (``DJI_0001.SRT`` for ``DJI_0001.MP4``, any
    case), None when there is none (or ``video`` is a stream or a folder)."""
    path = Path(video)
    if not path.is_file():
        return None
    return next((p for p in sorted(path.parent.glob(f"{glob.escape(path.stem)}.*")) if p.suffix.lower() == ".srt" and p.is_file()), None)


def map_output_flag(out: str | Path) -> list[str]:
    """``["-o map.kmz"]`` when ``out`` is an output only a map can be (KMZ, MBTiles, web tiles)."""
    from mosaic_cli.inputs import MAP_FORMATS, output_format

    fmt = output_format(out)
    return [f"-o {out} ({MAP_FORMATS[fmt]})"] if fmt in MAP_FORMATS else []


def check_plain_output(out: str | Path, why: str) -> None:
    """Refuse, before any work, an output only a map can be when there is no telemetry."""
    if wanted := map_output_flag(out):
        raise BadInput(f"{wanted[0]} needs telemetry ({why})")


def gps_straightener(track: FlightLog, ref: int, indices: list[int], frame_size, fps: float, options: GeorefOptions):
    """Drift control's GPS prior: before loops are looked for, the scan's placements are moved
    toward the GPS track (loosely: see drift.py), so that neighbouring survey lines that drift
    had pulled apart are predicted to overlap again and get registered."""
    from dataclasses import replace

    from mosaic_cli.geo.drift import DriftOptions
    from mosaic_cli.geo.georef import georeference

    loose = replace(options, drift=DriftOptions(link_fraction=0.005))

    def straighten(world: list[np.ndarray]) -> list[np.ndarray]:
        try:
            moved = georeference(world, ref, indices, frame_size, fps, track, loose).straightened(world)
        except BadInput:
            return world  # the georeference after registration says what is wrong
        to_reference = np.linalg.inv(moved[ref])  # the reference keyframe stays the identity
        return [normalize(to_reference @ H) for H in moved]

    return straighten


def map_homographies(georef: Georeference, to_canvas: np.ndarray, frame_to_canvas: list[np.ndarray]) -> list[np.ndarray]:
    """Each keyframe's frame pixels -> (east, north) metres in ``georef.crs``."""
    from mosaic_cli.geo.output import canvas_to_ground

    G = canvas_to_ground(georef, to_canvas)
    return [normalize(G @ H) for H in frame_to_canvas]


def write_outputs(out, staged, georef: Georeference, options: GeorefOptions, to_canvas, frame_to_canvas, frame_size, fps,
                  boxes: dict[int, tuple[int, int, int, int]] | None = None) -> bool:
    """The map ``out`` when it is one (GeoTIFF, KMZ, MBTiles, web tiles), the footprints and the
    quick-look page, all read from ``staged`` (the panorama as a georeferenced GeoTIFF on disk,
    stitch/raster.py: ``path``, ``size``); False when ``out`` is left to the
    plain writer (PNG/JPEG: the north-up mosaic without a geotransform).  ``boxes``: where the
    photos of another shape lie in their frames (their footprints), by frame index."""
    from mosaic_cli.atomic import write_json
    from mosaic_cli.geo.output import footprint_collection, write_cog
    from mosaic_cli.inputs import MAP_FORMATS, output_format

    fmt = output_format(out)
    features = footprint_collection(georef, map_homographies(georef, to_canvas, frame_to_canvas), frame_size, fps, boxes)
    if options.footprints is not None:
        write_json(options.footprints, features)
    staged.close()
    if fmt == "tiff":
        write_cog(out, staged.path, staged.size)
    if fmt not in MAP_FORMATS and options.html is None:
        return fmt == "tiff"
    with _with_overviews(out, fmt, staged) as raster:
        if fmt == "kmz":
            from mosaic_cli.geo.kmz import write_kmz

            write_kmz(out, raster, features)
        elif fmt == "mbtiles":
            from mosaic_cli.geo.tiles import write_mbtiles

            write_mbtiles(out, raster)
        elif fmt == "pmtiles":
            from mosaic_cli.geo.tiles import write_pmtiles

            write_pmtiles(out, raster)
        elif fmt == "tiles":
            from mosaic_cli.geo.tiles import write_tiles

            write_tiles(out, raster)
        if options.html is not None:
            from mosaic_cli.geo.quicklook import write_quicklook

            write_quicklook(options.html, raster, features, title=Path(out).stem or Path(out).name)
    return fmt == "tiff" or fmt in MAP_FORMATS


@contextlib.contextmanager
def _with_overviews(out, fmt: str, staged) -> Iterator[Path]:
    """The map with overviews that the writers below read (warping it whole at coarser scales):
    the COG just written as ``out``, else one made from ``staged`` in a private folder beside
    ``out`` and removed after."""
    from mosaic_cli.geo.output import write_cog

    if fmt == "tiff":
        yield Path(out)
        return
    with private_folder(Path(out)) as folder:
        raster = folder / "map.tif"
        write_cog(raster, staged.path, staged.size, for_output=out)
        yield raster
