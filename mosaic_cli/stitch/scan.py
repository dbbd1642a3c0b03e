"""Stages 0 and 1 of :mod:`.pipeline` for one input: every check that can fail fast, its
telemetry read (:func:`prepare_flight`), then the overlays looked for beside the scan and the scan
itself (:func:`scan_prepared`); and scans laid end to end as one (:func:`merge_scans`: several
flights, or one video's segments scanned on a cluster's workers, :mod:`.workers`)."""

from __future__ import annotations

import dataclasses
import functools
import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import Estimator, plan_estimator
from mosaic_cli.geo.stitching import georef_telemetry
from mosaic_cli.overlay import FrameMask, Gate, MaskChanged, PendingMask, Speculation, check_mask_file, frame_mask_pending, speculate
from mosaic_cli.progress import progress_group, progress_task
from mosaic_cli.stabilize.rolling import RollingCorrection, RollingProbe, parse_rolling_shutter, plan_rolling
from mosaic_cli.stitch.canvas import parse_reference
from mosaic_cli.stitch.guide import GroundGuide
from mosaic_cli.stitch.keyframes import FlightScan, FlightScanner, FlightSpan, Keyframe, scan_flight, scan_photos
from mosaic_cli.stitch.options import StitchOptions
from mosaic_cli.stitch.output import check_outputs
from mosaic_cli.telemetry import FlightLog
from mosaic_cli.telemetry.photos import photo_log_rate
from mosaic_cli.video import VideoInfo, open_video, probe
from mosaic_cli.video.lens_filter import ImageFilter
from mosaic_cli.video.reader import refuse_damaged, scaled_size

GAP_SECONDS = 60.0  # between one flight's last frame and the next one's first, in the one count


@dataclass
class PreparedFlight:
    """One input, checked, with the options it is stitched with (a photo folder's own), its
    telemetry (None: none) and the filter its frames are read through (``--lens``; None: as
    decoded)."""

    video: str | Path
    info: VideoInfo
    options: StitchOptions
    track: FlightLog | None
    lens: ImageFilter | None = None


@dataclass
class ScannedFlight:
    scan: FlightScan
    mask: FrameMask | None
    rolling: RollingCorrection | None
    estimator: Estimator | None  # built for the first flight, reused by the next (None: built on a cluster's workers)
    restarted: bool  # an overlay was found after the scan had started without it


def prepare_flight(video: str | Path, out: str | Path, transforms: str | Path | None, options: StitchOptions,
                   info: VideoInfo | None = None, lens: ImageFilter | None = None) -> tuple[PreparedFlight, str | int]:
    """Every check of one input that can fail fast (before any work), its telemetry read, and the
    reference keyframe asked for.  ``info``: the caller's probe; ``lens``: the input's filter."""
    info, reference = _check_inputs(video, out, transforms, options, info)
    if info.is_image_folder:
        # Photos are registered by features alone: describe them finer than video frames.
        f = options.features
        photo = dataclasses.replace(f, width=max(f.width, f.photo_width), n_features=max(f.n_features, f.photo_features),
                                    max_source_threshold=f.photo_threshold)
        options = dataclasses.replace(options, features=photo)
        if parse_rolling_shutter(options.rolling_shutter) != "off":
            raise BadInput(f"{video}: --rolling-shutter applies to videos, not to photo folders")
        # The photos' EXIF GPS is their telemetry (geo hook: before any work): the folder is
        # read at the rate the camera took them, so that the track's times are the flight's.
        track = georef_telemetry(video, out, options.georef, None, info)
        if track is not None:
            assert options.georef is not None
            info = dataclasses.replace(info, fps=photo_log_rate(track))
            georef = dataclasses.replace(options.georef, align=dataclasses.replace(options.georef.align, per_photo=True),
                                         bend_to_gps=False)
            options = dataclasses.replace(options, georef=georef)
    else:
        track = georef_telemetry(video, out, options.georef, _time_span(info, options), info)  # geo hook: before any work
    if options.canvas.gsd is not None and track is None:
        raise BadInput(f"--gsd needs telemetry (a GPS log, or photos with EXIF GPS): without it {video} has no ground distance; "
                       f"--max-size bounds a plain panorama")
    return PreparedFlight(video, info, options, track, lens), reference


def scan_prepared(flight: PreparedFlight, build: Callable[[], Estimator], show_progress: bool, spill: str,
                  seconds: dict[str, float]) -> ScannedFlight:
    """Stage 0 and 1 (and the rolling shutter's pass) of one prepared input: the estimator built
    (``build``) beside the overlay detection, the scan; ``seconds`` gains their times.  Each
    reads the input through ``flight.lens``."""
    video, info, options, track, lens = flight.video, flight.info, flight.options, flight.track, flight.lens
    clock = time.perf_counter()
    # `auto`'s probe rides on the scan's first frames: a global shutter costs no pass of its own.
    mode = parse_rolling_shutter(options.rolling_shutter)
    probe = RollingProbe(info) if mode == "auto" else None
    with progress_group(disable=not show_progress):
        # The estimator is built (a network: torch, the weights) while the overlays are looked
        # for, and the scan starts once it is, the overlays still being looked for; it starts
        # again if one is found (_scan).
        pending, scanner = frame_mask_pending(build, video, options.mask, info, show_progress, lens)
        with pending:
            built = time.perf_counter() - clock
            clock = time.perf_counter()
            guide = GroundGuide(track, info.source_size) if info.is_image_folder and track is not None else None
            scan, speculation = _scan(video, info, scanner, options, show_progress, spill if options.spill else None,
                                      pending, probe, guide, lens)
            scanned = time.perf_counter() - clock
    mask = pending.result()
    # The overlays' share: the build (the detection beside it), the scan's end waiting for
    # the detection, and a scan discarded for an overlay found (left out of "scan").
    seconds["overlays"] = seconds.get("overlays", 0.0) + built + speculation.seconds
    seconds["scan"] = seconds.get("scan", 0.0) + scanned - speculation.seconds

    rolling = None
    if mode != "off":
        clock = time.perf_counter()
        rolling = plan_rolling(video, info, mode, show_progress, "stitch: rolling shutter", probe, lens)
        seconds["rolling"] = seconds.get("rolling", 0.0) + time.perf_counter() - clock + (probe.seconds if probe is not None else 0.0)

    if not scan.keyframes:
        raise BadInput(f"{video}: no frame is usable (all black, blank or over-exposed)")
    return ScannedFlight(scan, mask, rolling, scanner, speculation.restarted)


def _check_inputs(video, out, transforms, options: StitchOptions, info: VideoInfo | None = None) -> tuple[VideoInfo, str | int]:
    """Every check of the input and the outputs that can fail fast, before decoding a single
    frame (the options checked themselves when they were made).  ``info``: the caller's probe."""
    check_outputs(out, transforms, options.canvas.max_size)
    reference = parse_reference(options.canvas.reference)
    if info is None:
        info = probe(video)
    else:
        refuse_damaged(info)
    if info.frame_count is not None and options.start >= info.frame_count > 0:
        raise BadInput(f"--start {options.start} is past the end of {video} ({info.frame_count} frames)")
    if isinstance(reference, int) and info.frame_count and reference >= options.start + info.frame_count:
        raise BadInput(f"--reference {reference} is past the end of {video} ({info.frame_count} frames)")
    check_mask_file(options.mask, info)
    return info, reference


def plan_stitch_estimator(options: StitchOptions) -> Callable[[], Estimator]:
    """The scan's estimator as ``options`` name it (``--estimator``, ``--work-width``,
    ``--weights``, ``--device``), checked now and built when the returned function is called."""
    return plan_estimator(options.estimator, work_width=options.work_width, weights=options.weights, device=options.device)


def make_stitch_estimator(options: StitchOptions) -> Estimator:
    """The scan's estimator as ``options`` name it, built."""
    return plan_stitch_estimator(options)()


def _time_span(info: VideoInfo, options: StitchOptions) -> tuple[float, float] | None:
    """Seconds of video the stitch covers, when the frame count is known."""
    if not info.frame_count or info.fps <= 0:
        return None
    end = info.frame_count if options.max_frames is None else min(info.frame_count, options.start + options.max_frames)
    return options.start / info.fps, (end - 1) / info.fps


def frames_to_scan(info: VideoInfo, options: StitchOptions) -> int | None:
    """How many frames the scan reads (from ``--start``, at most ``--max-frames``), by the
    reader's own count (it rescales, it does not recount); None where that count is unknown."""
    if info.frame_count is None:
        return None
    total = max(0, info.frame_count - options.start)
    return total if options.max_frames is None else min(total, options.max_frames)


def _scan(video, info: VideoInfo, estimator: Estimator, options: StitchOptions, show_progress: bool, spill: str | None,
          mask: PendingMask, probe: RollingProbe | None = None, guide: GroundGuide | None = None,
          lens: ImageFilter | None = None) -> tuple[FlightScan, Speculation]:
    """The scan (keyframes, their placements and pixels), started with the mask known so far
    and started again, its keyframes and their spilled pixels dropped, if the overlays found
    change it (:func:`~mosaic_cli.overlay.speculate`); its progress is shown once the mask is
    settled.  ``lens``: the frames' filter (``--lens``)."""
    # Decode no larger than the canvas could use: frames are kept for compositing at most at max_size.
    max_size = options.canvas.max_size
    width = None
    if max_size and max(info.source_size) > max_size:
        width = max(2, int(info.source_size[0] * max_size / max(info.source_size)))
    decode_size = scaled_size(info.source_size, width)
    total = frames_to_scan(info, options)
    photos = info.is_image_folder
    label, unit = ("scan (photos, features)", "photos/s") if photos else (f"scan ({estimator.name})", "fr/s")

    def attempt(use: np.ndarray | None, gate: Gate) -> FlightScan:
        if gate.restarted and probe is not None:
            probe.restart()
        estimator.set_mask(use)
        scanner = FlightScanner(info.source_size, decode_size, info.fps, options.start, options.keyframes, options.features,
                                max_size, spill, use, guide, info.photo_fits)
        try:
            # Only frames whose pixels the scan keeps (the keyframes) are converted to RGB; the
            # others serve only their gray copies.
            with open_video(video, width=width, start=options.start, info=info, lazy_rgb=True, lens=lens) as stream:
                frames = gate.frames(itertools.islice(stream, options.max_frames))
                shown = functools.partial(gate.emit, advance)
                if photos:
                    scan = scan_photos(frames, scanner, shown)
                else:
                    scan = scan_flight(frames if probe is None else probe.tap(frames), estimator, scanner, shown)
            gate.wait()
        except MaskChanged:
            scanner.discard()  # its spilled pixels go now, not with the stitch's folder
            raise
        return scan

    with progress_task(label, total, unit=unit, disable=not show_progress) as advance:
        return speculate(mask, attempt)


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
