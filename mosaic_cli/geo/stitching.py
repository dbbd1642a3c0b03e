"""The georeferencing hooks of ``stitch()``: find the telemetry before any work, lay the
registered keyframes on the ground, write the georeferenced outputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mosaic_cli.atomic import check_writable
from mosaic_cli.errors import BadInput
from mosaic_cli.geo.georef import Georeference, GeorefOptions
from mosaic_cli.geometry import normalize
from mosaic_cli.telemetry import Track, find_telemetry, read_telemetry


def load_track(video: str | Path, out: str | Path, options: GeorefOptions | None) -> Track | None:
    """The telemetry to georeference with: the file given, else a track inside the video
    (None when there is none, or when it holds no GPS, e.g. captions)."""
    if options is None:
        return None
    options.validate()
    if options.footprints is not None:
        check_writable(options.footprints)
        if Path(options.footprints).resolve() == Path(out).resolve():
            raise BadInput("--footprints must differ from the panorama output")
    if options.telemetry is not None:
        track = read_telemetry(options.telemetry)
    else:
        track = find_telemetry(video)
    if track is None and options.footprints is not None:
        raise BadInput(f"--footprints needs telemetry: give --telemetry (no SRT or KLV track inside {video})")
    if track is not None and not track.has_fix.any():
        if options.telemetry is None:
            return None  # an embedded track without positions: a plain panorama, as without one
        raise BadInput(f"{track.source}: no GPS fix in its {len(track)} samples (all without coordinates)")
    return track


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
