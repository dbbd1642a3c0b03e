"""The georeferencing hooks of ``stitch()``: find the telemetry before any work, lay the
registered keyframes on the ground, write the georeferenced outputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mosaic_cli.atomic import check_writable
from mosaic_cli.errors import BadInput, require_geo
from mosaic_cli.geo.georef import Georeference, GeorefOptions
from mosaic_cli.geometry import normalize
from mosaic_cli.telemetry import Track, find_telemetry, read_telemetry
from mosaic_cli.video import VideoInfo


def load_track(video: str | Path, out: str | Path, options: GeorefOptions | None, span: tuple[float, float] | None = None,
               info: VideoInfo | None = None) -> Track | None:
    """The telemetry to georeference with: the file given, else a track inside the video
    (None when there is none, or when it holds no GPS, e.g. captions).  ``span``: the seconds
    of video to stitch, when known, to refuse a log that misses them before any work;
    ``info``: the video's probe (its streams are where an embedded track is looked for)."""
    if options is None:
        return None
    if options.footprints is not None:
        check_writable(options.footprints)
        if Path(options.footprints).resolve() == Path(out).resolve():
            raise BadInput("--footprints must differ from the panorama output")
    if options.telemetry is not None:
        track = read_telemetry(options.telemetry)
    else:
        track = find_telemetry(video, info)
    wanted = options.without_telemetry()
    if track is None and wanted:
        raise BadInput(f"{wanted[0]} needs telemetry: give --telemetry (no SRT or KLV track inside {video})")
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


def gps_straightener(track: Track, ref: int, indices: list[int], frame_size, fps: float, options: GeorefOptions):
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


def write_outputs(out, panorama, georef: Georeference, options: GeorefOptions, to_canvas, frame_to_canvas, frame_size, fps) -> bool:
    """The GeoTIFF (when ``out`` is one) and the footprints; False when ``out`` is left to the
    plain writer (PNG/JPEG: the north-up mosaic without a geotransform)."""
    from mosaic_cli.geo.output import write_cog, write_footprints

    written = False
    if Path(out).suffix.lower() in (".tif", ".tiff"):
        write_cog(out, panorama, georef, to_canvas)
        written = True
    if options.footprints is not None:
        write_footprints(options.footprints, georef, map_homographies(georef, to_canvas, frame_to_canvas), frame_size, fps)
    return written
