"""``stitch()``: a video in, a panorama out, in five stages.

0. overlays  burned-in logos, text and letterbox bars found on frames sampled over the clip,
             merged with --mask: kept out of estimation, registration and the panorama; found
             beside the scan, which starts with --mask's alone and starts again (its keyframes
             dropped) if an overlay is found (mosaic_cli/overlay/speculate.py)
1. scan      decode once, chain the estimator's pairwise homographies, keep keyframes, each
             placed by direct registration with the previous one (photos: registered
             directly, no estimator); a cut starts a new segment.  Stages 0 and 1 are
             scan.py's (on a cluster's workers: workers.py)
   rolling   --rolling-shutter auto|R only: each row band's correction to its frame's mid-time
             pose, from a tracking pass of its own (stabilize/rolling.py; `auto` first probes
             the scan's first frames, and a global shutter stops there); compose then draws
             each keyframe's rows through their correction and the keyframe's placement
2. register  relocalise segments on each other, close loops, refine all placements jointly
             (drift control); segments that join nothing become panoramas of their own
3. canvas    pick the reference keyframe, size the canvas (``max_size``), refuse degenerate chains
4. compose   warp each keyframe in its bounding box, exposure, seams, multi-band blending (the
             warps and the blend on the GPU when --device is one: stitch/device_blend.py)
5. write     the image (PNG/JPEG/TIFF) and the transforms JSON, atomically; a flight in
             several parts: the largest (most frames or photos) takes the name given, the
             others are numbered in decreasing size: pano.png, pano-2.png, ...

With telemetry (``StitchOptions.georef``, see mosaic_cli/geo) the log is read before any work,
drift control starts from GPS-straightened placements, and each panorama whose keyframes the
log covers is laid north-up on the ground before its canvas is planned (GeoTIFF, footprints,
map homographies in the transforms).
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mosaic_cli.device import check_device, resolve_device
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import Estimator
from mosaic_cli.geo.georef import Georeference, GeorefOptions, TooFewFixes, georeference
from mosaic_cli.geo.output import geotransform, transforms_extra
from mosaic_cli.geo.stitching import gps_straightener, map_homographies, write_outputs
from mosaic_cli.geometry import is_valid, normalize, resize_matrix
from mosaic_cli.geometry.rolling_shutter import band_centres, similarity_matrix, undo_row_correction
from mosaic_cli.overlay import FrameMask
from mosaic_cli.progress import progress_task
from mosaic_cli.stabilize.rolling import RollingCorrection
from mosaic_cli.stitch.canvas import choose_reference, plan_canvas
from mosaic_cli.stitch.cluster import connect, tile_runner
from mosaic_cli.stitch.compose import ComposeOptions, PlacedImage, RowMap, TileRunner, TileSink, compose, fill_holes, tile_count
from mosaic_cli.stitch.features import FeatureExtractor, FeatureMatcher
from mosaic_cli.stitch.keyframes import FlightScan, FlightSpan, KeyframeOptions
from mosaic_cli.stitch.options import StitchOptions
from mosaic_cli.stitch.output import JPEG_MAX_SIDE, numbered, output_format, write_transforms
from mosaic_cli.stitch.raster import MemoryPanorama, StagedPanorama, staged_panorama, write_image
from mosaic_cli.stitch.registration import RegistrationReport, chain_sequence, register_keyframes
from mosaic_cli.stitch.scan import plan_stitch_estimator, prepare_flight, scan_prepared
from mosaic_cli.stitch.segments import Joined, join_segments
from mosaic_cli.stitch.workers import scan_segments
from mosaic_cli.telemetry import FlightLog
from mosaic_cli.telemetry.photos import photo_metadata_notes
from mosaic_cli.video import VideoInfo
from mosaic_cli.video.folders import other_cameras_note
from mosaic_cli.video.lens_filter import ImageFilter


@dataclass
class Panorama:
    path: Path
    transforms_path: Path | None
    canvas_size: tuple[int, int]
    transforms: list[tuple[int, np.ndarray]]  # (frame index, frame -> panorama) per keyframe
    reference_frame: int
    segments: int  # segments of the flight joined in it
    georef: Georeference | None = None  # laid on the ground (telemetry covering its keyframes)
    # The frames (photos) of the flight it stands for, as inclusive runs of indices: a video
    # keyframe stands for the frames up to the next one, those placed nowhere left out.
    spans: list[tuple[int, int]] = field(default_factory=list)
    # --rolling-shutter (applied): each keyframe's (K, 3, 3) frame -> panorama of its row bands'
    # centre rows (the band's correction, then the keyframe's transform), in the order of transforms.
    bands: list[np.ndarray] | None = None
    filled: int = 0  # --fill-holes: pixels of interior holes inpainted
    shrunk_from: tuple[int, int] | None = None  # the (W, H) it was scaled down from, if it was
    shrunk_by: str | None = None  # what scaled it down: --max-size N, --gsd D, JPEG's limit
    off_map: str | None = None  # with telemetry, why it is a plain panorama, not laid on the ground

    @property
    def size(self) -> int:
        """Frames (photos) of the flight in it: what orders the panoramas of a flight."""
        return sum(b - a + 1 for a, b in self.spans)


@dataclass
class StitchResult:
    canvas_size: tuple[int, int]  # of the first panorama (the largest, written to the name given)
    transforms: list[tuple[int, np.ndarray]]  # (frame index, frame -> panorama) per keyframe, ditto
    reference_frame: int
    frames: int
    keyframes: int
    registration: RegistrationReport
    # Wall seconds of each stage: "overlays" the time before the scan could start (the
    # estimator's build, the overlays looked for beside it) and the time the scan then lost to
    # them (its end waiting for the detection, a scan discarded for an overlay found); "scan" the
    # kept scan; then "rolling", "register", "compose", "write": together about the wall time.
    seconds: dict[str, float]
    panoramas: list[Panorama] = field(default_factory=list)  # all of them, the largest first
    dropped: list[tuple[int, str]] = field(default_factory=list)  # (frame index, why) not placed anywhere
    photos: bool = False
    mask: FrameMask | None = None  # what was kept out of estimation and the panoramas
    georef: Georeference | None = None  # the first panorama's, with telemetry (see Panorama.georef for the others)
    rolling: RollingCorrection | None = None  # --rolling-shutter: the readout and each band's correction
    # An overlay was found after the scan had started without it: the scan started again
    # (mosaic_cli/overlay/speculate.py); the panoramas are those of the final mask either way.
    overlay_restart: bool = False
    # A photo folder's metadata that could not serve: each photo with damaged or partial EXIF/XMP
    # and those without GPS among geotagged ones, placed by their pixels (said as warnings).
    metadata_notes: list[str] = field(default_factory=list)
    pairs_tried: int = 0  # photos: pairs matched by the scan and as loop candidates (not counting segment joins)
    flights: list[FlightSpan] = field(default_factory=list)  # several flights: each one's frames in the one count

    @property
    def frames_per_second(self) -> float:
        return self.frames / max(sum(self.seconds.values()), 1e-9)


def stitch(
    video: str | Path,
    out: str | Path,
    estimator: Estimator | None = None,
    options: StitchOptions | None = None,
    transforms: str | Path | None = None,
    show_progress: bool = True,
    info: VideoInfo | None = None,
    *,
    lens: ImageFilter | None = None,
) -> StitchResult:
    """Stitch ``video`` into the panorama ``out`` (format by extension), optionally writing
    every keyframe's frame -> panorama homography to ``transforms``.  Raises ``BadInput``
    before any work for unusable input, ``ProcessingError`` when the flight cannot be
    stitched; never leaves a partial file.  ``estimator``: None builds the one ``options``
    name (:func:`make_stitch_estimator`) once the input is checked.  ``info``: the video's
    probe, when the caller has it.  ``lens``: each frame through this filter as it is decoded
    (``--lens``: the panorama a pinhole view of the ground), the mask carried into the
    undistorted frame."""
    options = options or StitchOptions()
    flight, reference = prepare_flight(video, out, transforms, options, info, lens)
    build: Callable[[], Estimator] = plan_stitch_estimator(flight.options) if estimator is None else (lambda: estimator)
    # Keyframe pixels wait here between the scan and the compositing (see spill.py); the
    # folder goes however the stitch ends.
    with tempfile.TemporaryDirectory(prefix="mosaic-stitch-") as spill, connect(options.cluster, spill) as client:
        seconds: dict[str, float] = {}
        scanned = None
        if client is not None and estimator is None:
            scanned = scan_segments(flight, client, spill, seconds, show_progress, options.cluster.segment_frames)
        if scanned is None:
            scanned = scan_prepared(flight, build, show_progress, spill, seconds)
        result = finish_stitch(scanned.scan, reference, out, flight.options, transforms, show_progress, seconds, scanned.mask,
                               flight.track, scanned.rolling, tile_runner(client) if client is not None else None)
        result.overlay_restart = scanned.restarted
        result.metadata_notes = other_cameras_note(flight.info)
        if flight.track is not None and flight.track.photos is not None:
            result.metadata_notes += photo_metadata_notes(flight.track.photos)
        return result


def finish_stitch(scan: FlightScan, reference: str | int, out: str | Path, options: StitchOptions,
                  transforms: str | Path | None, show_progress: bool, seconds: dict[str, float],
                  mask: FrameMask | None = None, track: FlightLog | None = None,
                  rolling: RollingCorrection | None = None, runner: TileRunner | None = None) -> StitchResult:
    """The stages after the scan, shared by the offline and the live stitch: register the
    keyframes (loop closure, relocalisation of segments, drift control), then plan, compose and
    write each panorama; the overlays of ``scan.use`` are drawn in none (``mask``: what the
    result reports of them).  ``seconds`` gains each stage's time.  With ``track`` (telemetry,
    see geo/stitching.py) drift control starts from GPS-straightened placements and each
    panorama whose keyframes the log covers is laid north-up on the ground (GeoTIFF, footprints,
    map homographies in the transforms).  ``rolling`` (applied): each keyframe is drawn row band
    by row band (its bands' correction, then its placement).  ``runner``: the compose stage's
    tiles blended elsewhere (stitch/cluster.py)."""
    clock = time.perf_counter()
    planned, rolling = rolling, rolling if rolling is not None and rolling.applied else None  # `auto` may read a global shutter
    if rolling is not None:
        _to_mid_time(scan, rolling)
    groups, report = _register(scan, reference, options, show_progress, track)
    if options.one_map and track is not None and len(groups) > 1:
        groups = _on_one_map(groups, scan, track, options)
    seconds["register"] = time.perf_counter() - clock
    # The user's name goes to the largest part, the others numbered in decreasing size (ties:
    # in flight order), whichever part the flight began with.
    held = _frames_held(scan)
    spans = [_runs(sorted(i for k in members for i in held[k])) for members, *_ in groups]
    order = sorted(range(len(groups)), key=lambda g: -sum(b - a + 1 for a, b in spans[g]))
    groups, spans = [groups[g] for g in order], [spans[g] for g in order]

    seconds["compose"] = seconds["write"] = 0.0
    panoramas = [_panorama(number, group, spans[number], scan, track, options, out, transforms, show_progress, seconds, rolling, runner)
                 for number, group in enumerate(groups)]
    first = panoramas[0]
    return StitchResult(
        first.canvas_size, first.transforms, first.reference_frame, scan.frames, len(scan.keyframes), report,
        seconds, panoramas, scan.dropped, scan.photos, mask, first.georef, planned,
        pairs_tried=scan.pairs_tried + report.loop_candidates, flights=scan.flights,
    )


def _panorama(number: int, group, span: list[tuple[int, int]], scan: FlightScan, track: FlightLog | None, options: StitchOptions,
              out: str | Path, transforms: str | Path | None, show_progress: bool, seconds: dict[str, float],
              rolling: RollingCorrection | None, runner: TileRunner | None) -> Panorama:
    """One part of the flight (``group``: its keyframes, their placements, its reference, its
    segments) laid on the ground (with telemetry), planned, composed and written under its name
    (``number`` 0: the name given; then pano-2, ...); ``seconds`` gains the stages' times."""
    members, placements, ref, segments = group
    keyframes = [scan.keyframes[k] for k in members]
    indices = [k.index for k in keyframes]
    georef, off_map = None, None
    if track is not None:  # geo hook: the mosaic laid north-up on the ground, in ground pixels
        clock = time.perf_counter()
        # a video's first part must be laid on the ground; a photo folder's may be one photo
        georef, off_map = _georeference(placements, ref, indices, scan, track, options.georef, first=0 in members and not scan.photos)
        if georef is not None:
            placements = georef.placements_in_pixels(placements)
        seconds["register"] += time.perf_counter() - clock

    clock = time.perf_counter()
    drawn = [k.composited for k in keyframes]
    path, json_path = numbered(out, number), Path(numbered(transforms, number)) if transforms is not None else None
    fmt = output_format(path) or ""  # (check_outputs knew it)
    canvas_options, limit = options.canvas, None
    if fmt == "jpeg" and canvas_options.max_size is None:
        canvas_options = dataclasses.replace(canvas_options, max_size=JPEG_MAX_SIDE)
        limit = f"JPEG's limit of {JPEG_MAX_SIDE} pixels a side (a .png or .tif keeps every pixel)"
    canvas = plan_canvas(placements, indices, scan.source_size, canvas_options, drawn, georef.gsd if georef is not None else None, limit)
    frame_to_canvas = [canvas.frame_to_canvas(H) for H in placements]
    crs, transform = (None, None) if georef is None else (georef.projection.crs.to_wkt(), geotransform(georef, canvas.to_canvas))
    # The panorama goes tile by tile into a file beside the output (stitch/raster.py), from
    # which every format is written: no canvas is ever held in memory.
    with staged_panorama(path, canvas.size, crs, transform, keep=fmt == "tiff" and georef is None) as staged:
        _compose(keyframes, scan.source_size, frame_to_canvas, canvas.size, _compose_options(options), show_progress,
                 scan.use, rolling, staged, runner)
        filled = _fill_holes(staged, options.compose.fill_holes)
        seconds["compose"] += time.perf_counter() - clock

        clock = time.perf_counter()
        extra, written = None, False
        if georef is not None:  # geo hook: GeoTIFF, footprints, map homographies
            assert options.georef is not None
            footprints, html = options.georef.footprints, options.georef.html
            own = dataclasses.replace(options.georef, footprints=Path(numbered(footprints, number)) if footprints is not None else None,
                                      html=Path(numbered(html, number)) if html is not None else None)
            written = write_outputs(path, staged, georef, own, canvas.to_canvas, frame_to_canvas, scan.source_size, scan.fps,
                                    _photo_boxes(scan))
            extra = transforms_extra(georef, map_homographies(georef, canvas.to_canvas, frame_to_canvas))
        if not written:
            write_image(path, staged, fmt)
    # Every keyframe is reported, also those over ground already drawn (used for registration).
    frames = list(zip(indices, frame_to_canvas))
    if json_path is not None:
        write_transforms(json_path, canvas.size, frames, _per_frame_keys(extra, frames, scan))
    seconds["write"] += time.perf_counter() - clock
    bands = None
    if rolling is not None:
        centres = band_centres(scan.source_size[1], rolling.corrections.shape[1])
        bands = [normalize(H @ similarity_matrix(rolling.row_channels(i, centres), scan.source_size)) for i, H in frames]
    shrunk_from = canvas.native_size if canvas.scale < 1.0 else None
    return Panorama(Path(path), json_path, canvas.size, frames, indices[ref], segments, georef, span, bands, filled, shrunk_from,
                    canvas.shrunk_by, off_map)


def _on_one_map(groups, scan: FlightScan, track: FlightLog, options: StitchOptions):
    """Several flights with telemetry: the parts that registration did not join, each laid where
    its own fit to the log places it (its mosaic -> ground similarity, in the first part's
    mosaic frame), drawn as one part; parts the log does not cover stay apart."""
    fitted = []
    for members, placements, ref, _ in groups:
        fitted.append(_georeference(placements, ref, [scan.keyframes[k].index for k in members], scan, track, options.georef, first=False)[0])
    on_ground = [(group, georef) for group, georef in zip(groups, fitted) if georef is not None]
    if len(on_ground) < 2:
        return groups
    (first_members, _, first_ref, _), first = on_ground[0]
    back = np.linalg.inv(first.mosaic_to_ground)
    entries = sorted((member, normalize(back @ georef.mosaic_to_ground @ H))
                     for (members, placements, _, _), georef in on_ground for member, H in zip(members, placements))
    members = [m for m, _ in entries]
    merged = (members, [H for _, H in entries], members.index(first_members[first_ref]), sum(g[3] for g, _ in on_ground))
    return [merged] + [group for group, georef in zip(groups, fitted) if georef is None]


def _per_frame_keys(extra: tuple[dict, list[dict]] | None, frames: list[tuple[int, np.ndarray]], scan: FlightScan):
    """The transforms JSON's per-frame keys, with each keyframe's flight and its own frame number
    when several flights were stitched, and a photo of another camera's place in the frame its
    ``H`` maps (``photo``: its name, size and ``to_frame``, photo pixels -> frame pixels)."""
    fits = {k.index: k.fit for k in scan.keyframes if k.fit is not None}
    if not scan.flights and not fits:
        return extra
    top, per_frame = extra if extra is not None else ({}, [{} for _ in frames])
    named = []
    for (index, _), more in zip(frames, per_frame):
        more = dict(more)
        if scan.flights:
            span = next(f for f in scan.flights if f.holds(index))
            more.update(flight=span.name, frame=index - span.start)
        if (fit := fits.get(index)) is not None:
            x, y, w, h = fit.box
            to_frame = [[w / fit.photo_size[0], 0.0, float(x)], [0.0, h / fit.photo_size[1], float(y)], [0.0, 0.0, 1.0]]
            more["photo"] = {"name": fit.name, "size": list(fit.photo_size), "to_frame": to_frame}
        named.append(more)
    return top, named


def _photo_boxes(scan: FlightScan) -> dict[int, tuple[int, int, int, int]]:
    """Where the photos of another shape lie in the frame (x, y, w, h), by frame index."""
    return {k.index: k.fit.box for k in scan.keyframes if k.fit is not None and not k.fit.fills(scan.source_size)}


def _frames_held(scan: FlightScan) -> list[list[int]]:
    """The frames each keyframe stands for: a photo itself; a video keyframe the frames from it
    to the next keyframe, less those placed nowhere (they are reported on their own)."""
    if scan.photos:
        return [[k.index] for k in scan.keyframes]
    dropped = {i for i, _ in scan.dropped}
    starts = [k.index for k in scan.keyframes]
    ends = [*starts[1:], scan.first_index + scan.frames]
    for n, a in enumerate(starts):  # several flights: a flight's last keyframe stands for its frames only
        span = next((f for f in scan.flights if f.holds(a)), None)
        if span is not None:
            ends[n] = min(ends[n], span.start + span.frames)
    return [[i for i in range(a, b) if i not in dropped] for a, b in zip(starts, ends)]


def _runs(indices: list[int]) -> list[tuple[int, int]]:
    """Sorted indices as inclusive runs: [0, 1, 2, 5] -> [(0, 2), (5, 5)]."""
    runs: list[tuple[int, int]] = []
    for i in indices:
        if runs and i == runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], i)
        else:
            runs.append((i, i))
    return runs


def _georeference(placements, ref: int, indices: list[int], scan: FlightScan, track: FlightLog, options: GeorefOptions | None,
                  first: bool) -> tuple[Georeference | None, str | None]:
    """One panorama laid on the ground, or None and why not.  ``first``: it must be (a video's
    first part: the log was checked to cover the video, what is wrong is said); else a part
    whose keyframes the log does not place stays a plain panorama: a later segment of a video,
    or photos that join no others with fewer than two GPS fixes among them."""
    assert options is not None
    try:
        return georeference(placements, ref, indices, scan.source_size, scan.fps, track, options), None
    except BadInput as exc:
        if first:
            raise
        if scan.photos and isinstance(exc, TooFewFixes):
            photos = f"{exc.keyframes} photo{'s' if exc.keyframes > 1 else ''}"
            return None, f"its {photos} give{'s' if exc.keyframes == 1 else ''} {exc.fixes} GPS fix{'es' if exc.fixes != 1 else ''}, and laying photos on the ground takes two"
        return None, "the telemetry gives its keyframes no position"


def _register(scan: FlightScan, reference: str | int, options: StitchOptions, show_progress: bool, track: FlightLog | None = None):
    """The panoramas: for each, its keyframes (positions in ``scan.keyframes``), their
    keyframe -> reference placements (jointly refined, or chained from the scan's
    registrations when drift control is off), the reference (a position in the group) and
    how many segments it joins.  ``track`` (telemetry) straightens each group's placements
    toward the GPS before loops are looked for."""
    keyframes = scan.keyframes

    def progress(description: str, total: int):
        return progress_task(description, total, unit="pairs/s", disable=not show_progress)

    matcher = FeatureMatcher(FeatureExtractor(scan.source_size, options.features, scan.use))
    loops = options.registration.loop_budget(len(keyframes), scan.photos)
    options = dataclasses.replace(options, registration=dataclasses.replace(options.registration, max_loop_pairs=loops))
    features = [k.features for k in keyframes]
    segments = [k.segment for k in keyframes]
    world = [k.placement for k in keyframes]
    if len(set(segments)) > 1:
        joined = join_segments(features, world, segments, matcher, options.registration, options.joining, progress)
    else:
        joined = Joined(world, [list(range(len(keyframes)))])
    last_frame = scan.first_index + scan.frames - 1
    if isinstance(reference, int):
        choose_reference([k.index for k in keyframes], reference, last_frame)  # refuses a frame past the end
        nearest = int(np.argmin([abs(k.index - reference) for k in keyframes]))
    groups, total = [], RegistrationReport()
    for members in joined.groups:
        local = {k: i for i, k in enumerate(members)}
        indices = [keyframes[k].index for k in members]
        spec = reference if not isinstance(reference, int) or nearest in local else "middle"
        ref = choose_reference(indices, spec, last_frame)
        to_ref = np.linalg.inv(joined.placements[members[ref]])
        placements = [normalize(to_ref @ joined.placements[k]) for k in members]
        sequence = [
            (local[k], local[to], keyframes[k].link)
            for k in members
            if (to := keyframes[k].link_to) is not None and to in local
        ]
        extra = [
            dataclasses.replace(l, a=local[l.a], b=local[l.b]) for l in joined.links if l.a in local and l.b in local
        ]
        chained = chain_sequence(sequence, placements, ref)
        if not options.registration.enabled or len(members) < 2:
            placements, report = chained, RegistrationReport()
        else:
            placements = _start(placements, chained, scan.source_size, options.keyframes)
            if track is not None and options.georef is not None and options.georef.bend_to_gps:
                # geo hook: drift control starts from GPS-straightened placements
                straighten = gps_straightener(track, ref, indices, scan.source_size, scan.fps, options.georef)
                placements = straighten(placements)
            placements, report = register_keyframes(
                [features[k] for k in members], placements, sequence, ref, matcher, options.registration, progress, extra
            )
        _add_report(total, report)
        groups.append((members, placements, ref, len({segments[k] for k in members})))
    return groups, total


def _start(world: list[np.ndarray], chained: list[np.ndarray], size, options: KeyframeOptions) -> list[np.ndarray]:
    """Drift control's starting placements: the scan's registrations chained in full (their
    perspective included), or the scan's affine world where that chain folds a keyframe."""
    limit = options.max_scale_change**2
    return chained if all(is_valid(H, size, max_area_ratio=limit) for H in chained) else world


def _add_report(total: RegistrationReport, report: RegistrationReport) -> None:
    for name in ("sequential", "chained", "loop_candidates", "loops", "loops_dropped"):
        setattr(total, name, getattr(total, name) + getattr(report, name))
    total.residual_before = max(total.residual_before, report.residual_before)
    total.links += report.links
    if total.links:
        total.residual_after = float(np.median([l.residual for l in total.links]))


def _compose_options(options: StitchOptions) -> ComposeOptions:
    """compose's options, its warps and blend on the GPU that ``--device`` names (or ``auto``
    finds); on a CPU, OpenCV's (torch's CPU blend is several times slower), unless they name a
    torch device themselves."""
    if options.compose.torch_device is not None or check_device(options.device) == "cpu":
        return options.compose
    device = resolve_device(options.device)
    return dataclasses.replace(options.compose, torch_device=str(device)) if device.type == "cuda" else options.compose


def _compose(keyframes, source_size, frame_to_canvas, canvas_size, options: ComposeOptions, show_progress: bool,
             use: np.ndarray | None, rolling: RollingCorrection | None, sink: TileSink, runner: TileRunner | None = None) -> None:
    placed = []
    for keyframe, H in zip(keyframes, frame_to_canvas):
        if not keyframe.composited:
            continue
        image, keyframe.image = keyframe.image, None  # compose() frees each image once drawn
        to_source = np.linalg.inv(resize_matrix(source_size, (image.shape[1], image.shape[0])))
        rows, reach = (None, 0.0) if rolling is None else _row_map(rolling, keyframe.index, source_size, to_source)
        placed.append(PlacedImage(image, normalize(H @ to_source), keyframe.use if keyframe.use is not None else use, rows, reach))
        del image
    tiles = tile_count(placed, canvas_size, options)
    with progress_task(f"compose {canvas_size[0]}x{canvas_size[1]}", tiles, unit="tiles/s", disable=not show_progress) as advance:
        compose(placed, canvas_size, options, advance, sink, runner)


def _fill_holes(staged: StagedPanorama | MemoryPanorama, max_share: float) -> int:
    """--fill-holes: the small interior holes inpainted, on the whole canvas read back into
    memory (the one step whose memory follows the canvas; off by default)."""
    if max_share <= 0:
        return 0
    rgba = staged.read()
    filled = fill_holes(rgba, max_share)
    if filled:
        staged.write(0, 0, rgba)
    return filled


def _row_map(rolling: RollingCorrection, index: int, source_size: tuple[int, int], to_source: np.ndarray) -> tuple[RowMap, float]:
    """A keyframe's rows for compose (see ``PlacedImage.rows``), in the pixels it is held at
    (``to_source``: those -> the source's), and how far (held px) they reach beyond its outline.
    Its placement is its mid-time pose's (the keyframes were registered on corrected points)."""
    table = rolling.row_channels(index, np.arange(source_size[1], dtype=np.float64))  # (h, 4), source px
    sx, bx, sy, by = to_source[0, 0], to_source[0, 2], to_source[1, 1], to_source[1, 2]

    def rows(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u, v = undo_row_correction(table, source_size, sx * x + bx, sy * y + by)
        return (u - bx) / sx, (v - by) / sy

    w, h = source_size
    edge_y = np.tile(np.arange(h, dtype=np.float64), 2)  # the left and right edges, every row
    edge_x = np.repeat([0.0, w - 1.0], h)
    u, v = rows((edge_x - bx) / sx, (edge_y - by) / sy)
    u, v = sx * u + bx, sy * v + by
    reach = float(max(np.max(np.abs(u - edge_x)), np.max(np.abs(v - edge_y)))) / min(sx, sy) + 1.0
    return rows, reach


def _to_mid_time(scan: FlightScan, rolling: RollingCorrection) -> None:
    """The keyframes' points (features, their links' correspondences) moved from the rows that
    saw them to their frame's mid-time pose, and the links' homographies refitted to them: the
    keyframes are then registered (and placed) as their mid-time poses, which compose draws each
    row band from.  (Registered on the raw points, a placement fits the rows the overlap with
    its neighbour happens to hold, and the errors chain along the flight.)"""
    import cv2

    def moved(index: int, points: np.ndarray) -> np.ndarray:
        return rolling.correct_points(index, points).astype(points.dtype)

    for key in scan.keyframes:
        key.features.points = moved(key.index, key.features.points)
        if key.link is not None and key.link_to is not None:
            to = scan.keyframes[key.link_to]
            link = key.link
            link.points_a, link.points_b = moved(key.index, link.points_a), moved(to.index, link.points_b)
            if len(link.points_a) >= 4:
                H, _ = cv2.findHomography(link.points_a.astype(np.float64), link.points_b.astype(np.float64), 0)
                if H is not None:
                    link.H = normalize(H)
