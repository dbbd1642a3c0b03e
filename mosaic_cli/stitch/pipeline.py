"""``stitch()``: a video in, a panorama out, in five stages.

1. scan      decode once, chain the estimator's pairwise homographies, keep keyframes, each
             placed by direct registration with the previous one
2. register  close loops, refine all placements jointly (drift control)
3. canvas    pick the reference keyframe, size the canvas (``max_size``), refuse degenerate chains
4. compose   warp each keyframe in its bounding box, exposure, seams, multi-band blending
5. write     the image (PNG/JPEG/TIFF) and the transforms JSON, atomically
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import Estimator
from mosaic_cli.geo.georef import Georeference, GeorefOptions, georeference
from mosaic_cli.geo.output import transforms_extra
from mosaic_cli.geo.stitching import gps_straightener, load_track, map_homographies, write_outputs
from mosaic_cli.geometry import normalize, resize_matrix
from mosaic_cli.progress import progress_task
from mosaic_cli.stitch.canvas import CanvasOptions, choose_reference, parse_reference, plan_canvas
from mosaic_cli.stitch.compose import ComposeOptions, PlacedImage, compose
from mosaic_cli.stitch.features import FeatureExtractor, FeatureMatcher, FeatureOptions
from mosaic_cli.stitch.keyframes import FlightScan, FlightScanner, KeyframeOptions, scan_flight
from mosaic_cli.stitch.output import check_outputs, write_panorama, write_transforms
from mosaic_cli.stitch.registration import RegistrationOptions, RegistrationReport, chain_neighbours, register_keyframes
from mosaic_cli.video import VideoInfo, open_video, probe
from mosaic_cli.video.reader import scaled_size


@dataclass
class StitchOptions:
    keyframes: KeyframeOptions = field(default_factory=KeyframeOptions)
    features: FeatureOptions = field(default_factory=FeatureOptions)
    registration: RegistrationOptions = field(default_factory=RegistrationOptions)
    canvas: CanvasOptions = field(default_factory=CanvasOptions)
    compose: ComposeOptions = field(default_factory=ComposeOptions)
    start: int = 0
    max_frames: int | None = None
    # Hold keyframe pixels in a temporary folder ($TMPDIR) rather than in memory: a survey's
    # held pixels add up to several canvases (see spill.py).
    spill: bool = True
    # Telemetry to lay the mosaic on the ground with (see mosaic_cli/geo); None: a plain panorama.
    georef: "GeorefOptions | None" = None


@dataclass
class StitchResult:
    canvas_size: tuple[int, int]
    transforms: list[tuple[int, np.ndarray]]  # (frame index, frame -> panorama) per keyframe
    reference_frame: int
    frames: int
    keyframes: int
    registration: RegistrationReport
    seconds: dict[str, float]
    georef: "Georeference | None" = None

    @property
    def frames_per_second(self) -> float:
        return self.frames / max(sum(self.seconds.values()), 1e-9)


def stitch(
    video: str | Path,
    out: str | Path,
    estimator: Estimator,
    options: StitchOptions | None = None,
    transforms: str | Path | None = None,
    show_progress: bool = True,
) -> StitchResult:
    """Stitch ``video`` into the panorama ``out`` (format by extension), optionally writing
    every keyframe's frame -> panorama homography to ``transforms``.  Raises ``BadInput``
    before any work for unusable input, ``ProcessingError`` when the flight cannot be
    stitched; never leaves a partial file."""
    options = options or StitchOptions()
    info, reference = _check_inputs(video, out, transforms, options)
    track = load_track(video, out, options.georef, _time_span(info, options))  # geo hook: before any work

    # Keyframe pixels wait here between the scan and the compositing (see spill.py); the
    # folder goes however the stitch ends.
    with tempfile.TemporaryDirectory(prefix="mosaic-stitch-") as spill:
        seconds: dict[str, float] = {}
        clock = time.perf_counter()
        scan = _scan(video, info, estimator, options, show_progress, spill if options.spill else None)
        seconds["scan"] = time.perf_counter() - clock

        if not scan.keyframes:
            raise BadInput(f"{video}: no frame is usable (all black, blank or over-exposed)")

        clock = time.perf_counter()
        indices = [k.index for k in scan.keyframes]
        ref = choose_reference(indices, reference, scan.first_index + scan.frames - 1)
        straighten = None  # geo hook: with telemetry, drift control starts from GPS-straightened placements
        if track is not None:
            straighten = gps_straightener(track, ref, indices, scan.source_size, info.fps, options.georef)
        placements, report = _register(scan, ref, options, show_progress, straighten)
        georef = None
        if track is not None:  # geo hook: the mosaic laid north-up on the ground, in ground pixels
            georef = georeference(placements, ref, indices, scan.source_size, info.fps, track, options.georef)
            placements = georef.placements_in_pixels(placements)
        seconds["register"] = time.perf_counter() - clock

        clock = time.perf_counter()
        drawn = [k.composited for k in scan.keyframes]
        canvas = plan_canvas(placements, indices, scan.source_size, options.canvas, drawn)
        frame_to_canvas = [canvas.frame_to_canvas(H) for H in placements]
        panorama = _compose(scan, frame_to_canvas, canvas.size, options.compose, show_progress)
        seconds["compose"] = time.perf_counter() - clock

        clock = time.perf_counter()
        extra = None
        if georef is not None:  # geo hook: GeoTIFF, footprints, map homographies
            written = write_outputs(out, panorama, georef, options.georef, canvas.to_canvas, frame_to_canvas, scan.source_size, info.fps)
            extra = transforms_extra(georef, map_homographies(georef, canvas.to_canvas, frame_to_canvas))
        if georef is None or not written:
            write_panorama(out, panorama)
        del panorama
        # Every keyframe is reported, also those over ground already drawn (used for registration).
        frames = list(zip(indices, frame_to_canvas))
        if transforms is not None:
            write_transforms(transforms, canvas.size, frames, extra)
        seconds["write"] = time.perf_counter() - clock
        return StitchResult(canvas.size, frames, indices[ref], scan.frames, len(scan.keyframes), report, seconds, georef)


def _check_inputs(video, out, transforms, options: StitchOptions) -> tuple[VideoInfo, str | int]:
    """Every check that can fail fast, before decoding a single frame."""
    check_outputs(out, transforms, options.canvas.max_size)
    reference = parse_reference(options.canvas.reference)
    options.compose.validate()
    if options.canvas.max_size is not None and options.canvas.max_size < 64:
        raise BadInput(f"--max-size must be at least 64 pixels, got {options.canvas.max_size}")
    if options.start < 0:
        raise BadInput(f"--start must be 0 or more, got {options.start}")
    if options.max_frames is not None and options.max_frames < 2:
        raise BadInput("--max-frames must be at least 2")
    if options.registration.max_loop_pairs < 0:
        raise BadInput(f"--max-loop-pairs must be 0 or more, got {options.registration.max_loop_pairs}")
    info = probe(video)
    if info.frame_count is not None and options.start >= info.frame_count > 0:
        raise BadInput(f"--start {options.start} is past the end of {video} ({info.frame_count} frames)")
    if isinstance(reference, int) and info.frame_count and reference >= options.start + info.frame_count:
        raise BadInput(f"--reference {reference} is past the end of {video} ({info.frame_count} frames)")
    return info, reference


def _time_span(info: VideoInfo, options: StitchOptions) -> tuple[float, float] | None:
    """Seconds of video the stitch covers, when the frame count is known."""
    if not info.frame_count or info.fps <= 0:
        return None
    end = info.frame_count if options.max_frames is None else min(info.frame_count, options.start + options.max_frames)
    return options.start / info.fps, (end - 1) / info.fps


def _scan(video, info: VideoInfo, estimator: Estimator, options: StitchOptions, show_progress: bool, spill: str | None) -> FlightScan:
    # Decode no larger than the canvas could use: frames are kept for compositing at most at max_size.
    max_size = options.canvas.max_size
    width = None
    if max_size and max(info.source_size) > max_size:
        width = max(2, int(info.source_size[0] * max_size / max(info.source_size)))
    decode_size = scaled_size(info.source_size, width)
    with open_video(video, width=width, start=options.start) as stream:
        total = stream.info.frame_count
        if total is not None:
            total = max(0, total - options.start)
            if options.max_frames is not None:
                total = min(total, options.max_frames)
        scanner = FlightScanner(
            info.source_size, decode_size, info.fps, options.start, options.keyframes, options.features, max_size, spill
        )

        def frames():
            for k, frame in enumerate(stream):
                if options.max_frames is not None and k >= options.max_frames:
                    return
                yield frame

        with progress_task(f"scan ({estimator.name})", total, disable=not show_progress) as advance:
            return scan_flight(frames(), estimator, scanner, advance)


def _register(scan: FlightScan, ref: int, options: StitchOptions, show_progress: bool, straighten=None):
    """Keyframe -> reference placements: jointly refined, or chained from the neighbours'
    registrations when drift control is off.  ``straighten`` (telemetry) corrects the scan's
    placements before loops are looked for."""
    keyframes = scan.keyframes
    world = [normalize(np.linalg.inv(keyframes[ref].placement) @ k.placement) for k in keyframes]
    if straighten is not None and options.registration.enabled and len(keyframes) >= 2:
        world = straighten(world)
    neighbours = [k.link for k in keyframes[1:]]
    if not options.registration.enabled or len(keyframes) < 2:
        return chain_neighbours(neighbours, world, ref), RegistrationReport()
    matcher = FeatureMatcher(FeatureExtractor(scan.source_size, options.features))
    features = [k.features for k in keyframes]
    with progress_task("register", None, unit="pairs/s", disable=not show_progress) as advance:
        placements, report = register_keyframes(features, world, neighbours, ref, matcher, options.registration, advance)
        advance(0, status=f"{report.loops - report.loops_dropped} loops, residual {report.residual_after:.2f} px")
    return placements, report


def _compose(scan: FlightScan, frame_to_canvas, canvas_size, options: ComposeOptions, show_progress: bool):
    placed = []
    for keyframe, H in zip(scan.keyframes, frame_to_canvas):
        if not keyframe.composited:
            continue
        image, keyframe.image = keyframe.image, None  # compose() frees each image once drawn
        to_source = np.linalg.inv(resize_matrix(scan.source_size, (image.shape[1], image.shape[0])))
        placed.append(PlacedImage(image, normalize(H @ to_source)))
        del image
    with progress_task(f"compose {canvas_size[0]}x{canvas_size[1]}", canvas_size[1], unit="rows/s", disable=not show_progress) as advance:
        return compose(placed, canvas_size, options, advance)
