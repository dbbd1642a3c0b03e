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
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import Estimator
from mosaic_cli.overlay import FrameMask
from mosaic_cli.progress import progress_task
from mosaic_cli.stabilize.rolling import parse_rolling_shutter, plan_rolling
from mosaic_cli.stitch.cluster import connect, tile_runner
from mosaic_cli.stitch.keyframes import FlightScan, FlightSpan, Keyframe
from mosaic_cli.stitch.pipeline import (
    PreparedFlight,
    ScannedFlight,
    StitchOptions,
    StitchResult,
    finish_stitch,
    frames_to_scan,
    plan_stitch_estimator,
    prepare_flight,
    scan_prepared,
)
from mosaic_cli.telemetry import FlightLog
from mosaic_cli.telemetry.flight_log import FIELDS
from mosaic_cli.telemetry.photos import photo_metadata_notes
from mosaic_cli.video.folders import folder_images, other_cameras_note

GAP_SECONDS = 60.0  # between one flight's last frame and the next one's first, in the one count
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


def segment_ranges(frames: int, start: int, workers: int, least: int) -> list[tuple[int, int]]:
    """``(first frame, frames)`` of each segment a flight of ``frames`` frames from ``start`` is
    cut into: one a worker, each at least ``least`` frames long (each worker builds an estimator
    and looks for overlays of its own: a short segment would cost more than it saves); the
    whole flight as one where fewer than two such segments fit."""
    count = min(workers, frames // max(least, 1))
    if count < 2:
        return [(start, frames)]
    bounds = np.linspace(0, frames, count + 1).round().astype(int)
    return [(start + int(a), int(b - a)) for a, b in zip(bounds[:-1], bounds[1:])]


def scan_segments(flight: PreparedFlight, client, spill: str, seconds: dict[str, float], show_progress: bool,
                  least: int) -> ScannedFlight | None:
    """One video cut into segments scanned at once on the cluster's workers (segment_ranges), as
    one scan: each keyframe keeps its frame number, each segment starts a segment of the scan
    (the register stage joins them by registration, as it joins the parts of a flight after a
    cut: consecutive segments see the same ground at their boundary).  Each worker finds the
    overlays of its own segment; the rolling shutter is measured here, over the whole video,
    once the segments are back.  None when the video is too short to cut (or its length unknown)."""
    info, options = flight.info, flight.options
    frames = frames_to_scan(info, options)
    if info.is_image_folder or not frames:
        return None
    workers = sum(w.get("nthreads", 1) for w in client.scheduler_info()["workers"].values())
    ranges = segment_ranges(frames, options.start, workers, least)
    if len(ranges) < 2:
        return None
    parts = [dataclasses.replace(flight, options=dataclasses.replace(options, start=first, max_frames=count, rolling_shutter="off"))
             for first, count in ranges]
    try:
        scans, masks, restarted = scan_on_workers(client, parts, "segments", spill, seconds, show_progress)
    except BadInput:  # a segment with no usable frame (a black stretch): the whole video is scanned here instead,
        return None  # which says what it drops and why
    scan, _ = merge_scans(scans, [f"frames {a}-{a + n - 1}" for a, n in ranges], one_flight=True)
    rolling = None
    mode = parse_rolling_shutter(options.rolling_shutter)
    if mode != "off":
        clock = time.perf_counter()
        rolling = plan_rolling(flight.video, info, mode, show_progress, "stitch: rolling shutter", None, flight.lens)
        seconds["rolling"] = time.perf_counter() - clock
    return ScannedFlight(scan, masks[0], rolling, None, restarted)


def scan_on_workers(client, flights: list[PreparedFlight], what: str, spill: str, seconds: dict[str, float],
                    show_progress: bool) -> tuple[list[FlightScan], list[FrameMask | None], bool]:
    """Each of ``flights`` (flights, or a video's segments: ``what``) scanned by a worker of the
    cluster (scan_remote), in their order: the scans, their overlay masks, and whether an
    overlay found late restarted any; ``seconds["scan"]`` the wall time.  A scan that fails
    raises its error here, the others' tasks cancelled."""
    clock = time.perf_counter()
    futures = [client.submit(scan_remote, flight, spill, pure=False) for flight in flights]
    scans, masks, restarted = [], [], False
    try:
        with progress_task(f"scan {len(futures)} {what} (cluster)", len(futures), unit=f"{what}/s", disable=not show_progress) as advance:
            for future in futures:
                scan, mask, again = future.result()
                scans.append(scan)
                masks.append(mask)
                restarted = restarted or again
                advance(1)
    except BaseException:
        client.cancel(futures)
        raise
    seconds["scan"] = time.perf_counter() - clock
    return scans, masks, restarted


def scan_remote(flight: PreparedFlight, spill: str):
    """(Run on a worker.)  One flight's scan with an estimator of its own: the scan (its
    keyframe pixels spilled to ``spill``, a folder the stitch's machine sees), its overlay
    mask, and whether an overlay found late restarted it."""
    scanned = scan_prepared(flight, plan_stitch_estimator(flight.options), False, spill, {})
    return scanned.scan, scanned.mask, scanned.restarted


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


def merge_scans(scans: list[FlightScan], names: list[str], one_flight: bool = False) -> tuple[FlightScan, list[FlightSpan]]:
    """The scans laid end to end as one (see the module doc): frame numbers shifted into one
    count with a gap of ``GAP_SECONDS`` between flights, segments numbered apart, each
    keyframe's link to its predecessor kept; the first flight's overlay mask is the scan's, a
    later flight's own is carried by each of its keyframes (``Keyframe.use``).  ``one_flight``:
    the scans are segments of one video, each already numbered in its count (no gap, no shift)."""
    fps = scans[0].fps
    gap = 0 if one_flight else int(round(GAP_SECONDS * fps))
    keyframes: list[Keyframe] = []
    dropped, relocalised, spans = [], [], []
    start = scans[0].first_index
    segment = 0
    pairs = failed = 0
    for scan, name in zip(scans, names):
        shift = 0 if one_flight else start - scan.first_index
        base = len(keyframes)
        for key in scan.keyframes:
            key.index += shift
            key.segment += segment
            if key.link_to is not None:
                key.link_to += base
            if scan.use is not scans[0].use and key.use is None:  # (a fitted photo's own includes its flight's)
                key.use = scan.use
            keyframes.append(key)
        dropped += [(i + shift, why) for i, why in scan.dropped]
        relocalised += [i + shift for i in scan.relocalised]
        spans.append(FlightSpan(name, start, scan.frames))
        segment = max(k.segment for k in keyframes) + 1
        pairs += scan.pairs_tried
        failed += scan.failed_pairs
        start += scan.frames + gap
    merged = FlightScan(keyframes, scans[0].source_size, fps, sum(s.frames for s in scans), scans[0].first_index, failed, relocalised,
                        sum(s.seconds for s in scans), dropped, scans[0].photos, scans[0].use, pairs, [] if one_flight else spans)
    return merged, spans


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
