"""One video cut into segments and scanned at once on a Dask cluster's workers (``--workers``,
``--scheduler``; :mod:`.cluster` connects), or several flights each scanned on a worker: each
worker builds an estimator of its own and spills its keyframe pixels where the stitch's machine
reads them."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.overlay import FrameMask
from mosaic_cli.progress import progress_task
from mosaic_cli.stabilize.rolling import parse_rolling_shutter, plan_rolling
from mosaic_cli.stitch.keyframes import FlightScan
from mosaic_cli.stitch.scan import PreparedFlight, ScannedFlight, frames_to_scan, merge_scans, plan_stitch_estimator, scan_prepared


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
