"""Many flights, one map: ``mosaic stitch f1.mp4 f2.mp4 ... -o map.tif`` (or a folder of videos,
or a folder of photo folders).

Each flight is checked and scanned as a stitch of it alone would be (its own overlays, its own
telemetry), then the scans are laid end to end as one flight with a cut between flights: each
flight's keyframes keep their own segments, and the stages after the scan (pipeline.finish_stitch)
join the segments that overlap by registration, as they join the parts of one flight after a
cut.  With telemetry, parts that join nothing are still laid on one map, each where its own log
places it (``StitchOptions.one_map``).  The frame numbers of the flights follow each other in
one count (flight k's frame i is ``start_k + i``, with a gap between flights); the transforms
JSON names each keyframe's flight and its own frame number.
"""

from __future__ import annotations

import dataclasses
import functools
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import Estimator
from mosaic_cli.overlay import FrameMask
from mosaic_cli.stitch.cluster import connect, tile_runner
from mosaic_cli.stitch.keyframes import FlightScan, FlightSpan
from mosaic_cli.stitch.options import StitchOptions
from mosaic_cli.stitch.pipeline import StitchResult, finish_stitch
from mosaic_cli.stitch.scan import PreparedFlight, merge_scans, plan_stitch_estimator, prepare_flight, scan_prepared
from mosaic_cli.stitch.workers import scan_on_workers
from mosaic_cli.telemetry import FlightLog
from mosaic_cli.telemetry.flight_log import FIELDS
from mosaic_cli.telemetry.photos import photo_metadata_notes
from mosaic_cli.video.folders import folder_images, other_cameras_note

VIDEO_SUFFIXES = {".mp4", ".mov", ".mkv", ".avi", ".ts", ".m4v", ".mts", ".webm", ".mpg", ".mpeg"}


def expand_flights(inputs: Sequence[str | Path]) -> list[str]:
    """The flights the inputs name: each video file or photo folder as given; a folder holding
    video files: each of them (sorted); a folder holding photo folders: each of those."""
    flights: list[str] = []
    for given in inputs:
        path = Path(given)
        if path.is_dir() and not _has_images(path):
            videos = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)
            folders = sorted(p for p in path.iterdir() if p.is_dir() and _has_images(p))
            if not videos and not folders:
                raise BadInput(f"{path}: no photos, videos or photo folders in it")
            flights += [str(p) for p in videos + folders]
        else:
            flights.append(str(given))
    if len(set(map(lambda f: str(Path(f).resolve()), flights))) < len(flights):
        raise BadInput("a flight is named twice: " + ", ".join(sorted({f for f in flights if flights.count(f) > 1})))
    return flights


def _has_images(folder: Path) -> bool:
    try:
        return bool(folder_images(folder))
    except BadInput:
        return False


def stitch_flights(flights: Sequence[str | Path], out: str | Path, estimator: Estimator | None = None,
                   options: StitchOptions | None = None, transforms: str | Path | None = None,
                   show_progress: bool = True) -> StitchResult:
    """Stitch several flights into the panorama or map ``out`` (see the module doc); one flight
    is :func:`mosaic_cli.stitch.pipeline.stitch`'s.  Every flight is checked before any is
    scanned; flights of different frame sizes, or photo folders mixed with videos, are refused."""
    options = options or StitchOptions()
    if len(flights) < 2:
        raise BadInput("stitch_flights needs two flights or more")
    if options.georef is not None and options.georef.telemetry is not None:
        raise BadInput(f"--telemetry {options.georef.telemetry} names one log for several flights: each flight's log is "
                       f"the track inside it, or the .SRT beside it (FLIGHT.SRT)")
    if options.rolling_shutter not in ("off", 0, 0.0):
        raise BadInput("--rolling-shutter applies to one flight at a time: stitch each flight alone, or give --rolling-shutter off")
    prepared, reference = [], None
    for video in flights:
        flight, spec = prepare_flight(video, out, transforms, options)  # each with its own log (geo/stitching.py)
        prepared.append(flight)
        reference = spec if reference is None else reference
    _check_alike(prepared)
    build: Callable[[], Estimator] = plan_stitch_estimator(options) if estimator is None else (lambda: estimator)
    with tempfile.TemporaryDirectory(prefix="mosaic-stitch-") as spill, connect(options.cluster, spill) as client:
        seconds: dict[str, float] = {}
        scans: list[FlightScan] = []
        masks: list[FrameMask | None] = []
        restarted = False
        if client is not None:  # one task a flight, each worker with its own estimator
            scans, masks, restarted = scan_on_workers(client, prepared, "flights", spill, seconds, show_progress)
        for flight in prepared if client is None else []:
            scanned = scan_prepared(flight, build, show_progress, spill, seconds)
            assert scanned.estimator is not None  # built here
            build = functools.partial(_same, scanned.estimator)  # the next flights reuse the network built for the first
            scans.append(scanned.scan)
            masks.append(scanned.mask)
            restarted = restarted or scanned.restarted
        scan, spans = merge_scans(scans, [str(f.video) for f in prepared])
        tracks = [f.track for f in prepared]
        track = merge_logs(tracks, spans, scan.fps, [s.fps for s in scans]) if any(t is not None for t in tracks) else None
        first = prepared[0].options
        if track is not None and first.georef is None:  # a later flight has a log, the first none
            first = next(f.options for f in prepared if f.track is not None)
        final = dataclasses.replace(first, one_map=track is not None)
        result = finish_stitch(scan, reference if reference is not None else "middle", out, final, transforms, show_progress,
                               seconds, masks[0], track, None, tile_runner(client) if client is not None else None)
        result.overlay_restart = restarted
        result.metadata_notes = [note for f in prepared for note in other_cameras_note(f.info)]
        result.metadata_notes += [note for t in tracks if t is not None and t.photos is not None for note in photo_metadata_notes(t.photos)]
        return result


def _same(estimator: Estimator) -> Estimator:
    return estimator


def _check_alike(flights: list[PreparedFlight]) -> None:
    """One kind of input and one frame size: the keyframes of all flights are placed, matched and
    drawn in one frame's pixels."""
    kinds = {f.info.is_image_folder for f in flights}
    if len(kinds) > 1:
        raise BadInput("photo folders and videos cannot be stitched together: stitch each kind on its own")
    sizes = {f.info.source_size for f in flights}
    if len(sizes) > 1:
        said = ", ".join(f"{Path(f.video).name} {f.info.source_size[0]}x{f.info.source_size[1]}" for f in flights)
        raise BadInput(f"the flights' frames differ in size ({said}): stitch flights of one camera setting together")


def merge_logs(tracks: list[FlightLog | None], spans: list[FlightSpan], fps: float, rates: list[float]) -> FlightLog:
    """The flights' logs as one, each in the one count's time: flight k's sample at its own t
    seconds lands at ``start_k / fps + t * rate_k / fps`` (its frames at ``rate_k`` a second
    are numbered from ``start_k`` in a count at ``fps``), so that every keyframe finds its own
    flight's fixes."""
    parts = [(t, span, rate) for t, span, rate in zip(tracks, spans, rates) if t is not None]
    time = np.concatenate([span.start / fps + t.time * rate / fps for t, span, rate in parts])
    columns = {name: np.concatenate([getattr(t, name) for t, _, _ in parts]) for name in FIELDS}
    photos = [p for t, _, _ in parts for p in (t.photos or [])] if all(t.photos is not None for t, _, _ in parts) else None
    notes = [note for t, _, _ in parts for note in t.notes]
    breaks = [span.start / fps + float(t.time[0]) * rate / fps for t, span, rate in parts[1:] if len(t)]
    return FlightLog(" + ".join(t.source for t, _, _ in parts), time, **columns, clock_time=any(t.clock_time for t, _, _ in parts),
                     notes=notes, photos=photos, breaks=breaks)
